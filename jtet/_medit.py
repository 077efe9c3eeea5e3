"""Medit (``.mesh``) sections that meshio 5.3 skips or refuses: MMG's required vertices,
edges, triangles and tets, which jtet reads itself (and writes), and the second-order
(P2) sections, which jtet reads as linear ones and writes for a quadratic output; and
the temporary copy of a file that meshio reads without them."""

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


# Medit's second-order sections (libMeshb's P2 elements) -> (the linear section, corners,
# nodes per line): the corners, then the nodes of the edges in VTK's order
# (``_quadratic.MID_EDGES``: Gmsh's Medit writer puts them so, checked in the tests),
# then the reference
P2_SECTIONS = {
    "TetrahedraP2": ("Tetrahedra", 4, 10),
    "TrianglesP2": ("Triangles", 3, 6),
    "EdgesP2": ("Edges", 2, 3),
}
# the start of the line after a section's numbers: the next keyword
_NEXT_KEYWORD = re.compile(rb"\n[ \t]*[A-Za-z]")


def _p2_rows(data, at: int, section: str, width: int, path: Path) -> tuple[np.ndarray, int]:
    """(rows (k, width + 1): 1-based node ids and the reference; the offset after the
    last) of the P2 section whose keyword is at ``at``, in one C-level parse;
    ``MeshFileError`` for a count that does not match its numbers."""
    import warnings

    start = at + len(section)
    nxt = _NEXT_KEYWORD.search(data, start)
    end = nxt.start() + 1 if nxt else len(data)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # np.fromstring warns and stops at a word
        try:
            values = np.fromstring(bytes(data[start:end]), dtype=np.int64, sep=" ")
        except (ValueError, DeprecationWarning):
            values = np.zeros(0, np.int64)
    count = int(values[0]) if len(values) else -1
    if count < 0 or len(values) != 1 + count * (width + 1):
        raise MeshFileError(f"{path}: unreadable {section} section")
    return values[1:].reshape(count, width + 1), end


def _medit_readable_copy(path: Path) -> Path | None:
    """A temporary copy of the ASCII Medit file ``path`` for meshio to read, or None
    when meshio reads the file as it is: without the sections of
    ``_MESHIO_UNKNOWN_SECTIONS``, and (``load(..., linear=True)``) with its P2 sections
    (``P2_SECTIONS``) as linear sections of their corners, their edge nodes noted for
    ``load`` (``quadratic_corners``). The caller removes the copy. ``MeshInputError``
    for P2 sections without ``linear``."""
    import mmap
    import tempfile

    from ._io import _non_tet_message, format_rows, quadratic_corners, reading_linear

    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        cuts = [
            (at, _section_ids(data, at, section, path)[1], b"")
            for section in _MESHIO_UNKNOWN_SECTIONS
            for at in _keyword_positions(data, section)
        ]
        found = {}
        for section, (linear, corners, width) in P2_SECTIONS.items():
            for at in _keyword_positions(data, section):
                rows, end = _p2_rows(data, at, section, width, path)
                found[section] = found.get(section, 0) + len(rows)
                if not reading_linear():
                    continue
                kept = quadratic_corners(rows[:, :width] - 1, corners) + 1
                table = np.column_stack([kept, rows[:, -1]])
                text = f"{linear}\n{len(rows)}\n" + format_rows(
                    table, "%d" + " %d" * corners + "\n"
                )
                cuts.append((at, end, text.encode()))
        if found and not reading_linear():
            if "TetrahedraP2" in found:
                raise MeshInputError(
                    _non_tet_message(
                        str(path), ["10-node tetrahedron"], [found["TetrahedraP2"]], True
                    )
                )
            listing = ", ".join(f"{k} x {v}" for k, v in found.items())
            raise MeshInputError(
                f"{path}: second-order sections ({listing}); --linear, jtet.load(path, "
                "linear=True), reads them as their corners"
            )
        if not cuts:
            return None
        fd, name = tempfile.mkstemp(prefix="jtet-medit-", suffix=".mesh")
        with os.fdopen(fd, "wb") as out:
            start = 0
            for a, b, replacement in sorted(cuts):
                out.write(data[start:a])
                out.write(replacement)
                start = b
            out.write(data[start:])
    return Path(name)


def write_medit_p2(path: Path, points: np.ndarray, blocks) -> None:
    """An ASCII Medit file of second-order cells at ``path``: ``points`` (n, 3) with
    reference 0, and ``blocks`` [(meshio cell type "tetra10" / "triangle6" / "line3",
    cells (k, j) 0-based in VTK's order, references (k,))] as P2 sections, then ``End``
    (``_append_required`` puts the Required* sections before it)."""
    from ._io import format_rows

    # the section of a block by its nodes per cell (10, 6, 3)
    sections = {width: name for name, (_, _, width) in P2_SECTIONS.items()}
    points = np.asarray(points, np.float64)
    with open(path, "w") as f:
        f.write("MeshVersionFormatted 2\n\nDimension 3\n\n")
        f.write(f"Vertices\n{len(points)}\n")
        table = np.column_stack([points, np.zeros(len(points))])
        f.write(format_rows(table, "%.17g %.17g %.17g %d\n"))
        for _, cells, refs in blocks:
            cells = np.asarray(cells, np.int64)
            table = np.column_stack([cells + 1, np.asarray(refs, np.int64)])
            f.write(f"\n{sections[cells.shape[1]]}\n{len(cells)}\n")
            f.write(format_rows(table, "%d" + " %d" * cells.shape[1] + "\n"))
        f.write("\nEnd\n")


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
