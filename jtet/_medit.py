"""Medit (``.mesh``) sections of MMG's that meshio 5.3 skips or refuses: the required
vertices, edges, triangles and tets jtet reads itself (and the vertices and tets it
writes), and the sections it removes from a temporary copy for meshio to read the rest."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ._errors import MeshFileError, MeshInputError


def _keyword_positions(data, section: str):
    """Offsets in ``data`` (a Medit file's bytes) of the keyword ``section`` where it
    stands alone on its line (``find()``, not a regular expression over the whole file:
    34 -> 2 ms for a 182k-tet file)."""
    keyword = section.encode()
    # the keyword with what may surround it on its line (from the character before it)
    alone = re.compile(rb"(?:^|[\s])" + keyword + rb"[ \t]*\r?(?:\n|$)")
    at = data.find(keyword)
    while at >= 0:
        if alone.match(data[max(at - 1, 0) : at + len(keyword) + 4]):
            yield at
        at = data.find(keyword, at + 1)


def _section_ids(data, at: int, section: str, path: Path) -> tuple[list[bytes], int]:
    """The ids (as byte strings) of the section whose keyword is at ``at``: a count,
    then as many ids (at most ~21 bytes each: bounded slices of the map); and the offset
    just after the last one. ``MeshInputError`` for a count that is no number or fewer
    ids than it."""
    end = at + len(section)
    head = data[end : end + 32].split(maxsplit=1)
    count = int(head[0]) if head and head[0].isdigit() else -1
    tokens = list(re.finditer(rb"\S+", data[end : end + 32 + 24 * max(count, 0)]))
    if count < 0 or len(tokens) < count + 1:
        raise MeshInputError(f"{path}: unreadable {section} section")
    return [t.group() for t in tokens[1 : count + 1]], end + tokens[count].end()


def _medit_required(path: Path, sections: tuple[str, ...]) -> dict[str, np.ndarray | None]:
    """{section: 0-based ids (k,), or None without it} of an ASCII Medit file's
    ``sections`` (``RequiredVertices``, ``RequiredEdges``, ``RequiredTriangles``,
    ``RequiredTetrahedra``: what MMG never moves or changes; meshio skips or refuses
    them; the ids of the edges, triangles and tets are in the file's sections of
    those), read from one map of the file."""
    import mmap

    found = {}
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        for section in sections:
            at = next(_keyword_positions(data, section), None)
            found[section] = None if at is None else _section_ids(data, at, section, path)[0]
    return {
        section: None if ids is None else _ids(ids, section, path) for section, ids in found.items()
    }


def _ids(ids: list[bytes], section: str, path: Path) -> np.ndarray:
    """0-based ids (k,) of a section's 1-based id byte strings."""
    try:  # one C-level conversion of the byte strings, not a Python loop over the ids
        values = np.array(ids, dtype=bytes).astype(np.int64) if ids else np.zeros(0, np.int64)
    except ValueError:
        values = None
    if values is None or (values < 1).any():
        raise MeshInputError(f"{path}: unreadable {section} section")
    return values - 1


# Medit sections of MMG's that meshio 5.3 refuses ("Unknown keyword"), all a count and as
# many ids: jtet reads the required tets, triangles and edges itself (``_medit_required``)
_MESHIO_UNKNOWN_SECTIONS = (
    "RequiredTetrahedra",
    "RequiredTriangles",
    "RequiredEdges",
    "RequiredQuadrilaterals",
)


def _medit_without_unknown_sections(path: Path) -> Path | None:
    """A temporary copy of the ASCII Medit file ``path`` without the sections of
    ``_MESHIO_UNKNOWN_SECTIONS`` (for meshio to read), or None when it has none of them.
    The caller removes the copy."""
    import mmap
    import tempfile

    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        cuts = sorted(
            (at, _section_ids(data, at, section, path)[1])
            for section in _MESHIO_UNKNOWN_SECTIONS
            for at in _keyword_positions(data, section)
        )
        if not cuts:
            return None
        fd, name = tempfile.mkstemp(prefix="jtet-medit-", suffix=".mesh")
        with os.fdopen(fd, "wb") as out:
            start = 0
            for a, b in cuts:
                out.write(data[start:a])
                start = b
            out.write(data[start:])
    return Path(name)


def _medit_required_tets(ids: np.ndarray | None, tets: np.ndarray, path: Path):
    """The tets (k, 4) of ``tets`` (the file's, in its order) that the Medit file's
    ``RequiredTetrahedra`` lists (``ids``, from ``_medit_required``); None without the
    section."""
    if ids is None:
        return None
    if len(ids) and ids.max() >= len(tets):
        raise MeshInputError(
            f"{path}: RequiredTetrahedra lists tet {int(ids.max()) + 1} of {len(tets)}"
        )
    return tets[ids]


def _append_required(path: Path, sections: dict[str, np.ndarray]) -> None:
    """Put each of ``sections`` (Medit keyword -> 0-based ids (k,)), 1-based, before the
    final ``End`` of the ASCII Medit file meshio wrote at ``path``."""
    with open(path, "r+b") as f:
        f.seek(max(f.seek(0, os.SEEK_END) - 64, 0))
        tail = f.read()
        end = tail.rfind(b"End")
        if end < 0:
            raise MeshFileError(f"{path}: the Medit file has no final End")
        f.seek(f.tell() - len(tail) + end)
        f.truncate()
        for keyword, values in sections.items():
            ids = "\n".join(map(str, (np.asarray(values) + 1).tolist()))
            f.write(f"{keyword}\n{len(values)}\n{ids}\n\n".encode())
        f.write(b"End\n")
