"""Binary Medit meshes (``.meshb``: the GMF format of libMeshb, which MMG reads and
writes), read and written here with NumPy, one array per section.

A file is a 32-bit code (1, or 1 byte-swapped for the other endianness), a version and
a list of keywords. Each keyword is a 32-bit code, the file position of the next keyword,
then (for a section of lines) a count and the lines. The version sets the widths:

    version   reals     integers   positions
    1         float32   int32      int32
    2         float64   int32      int32
    3         float64   int32      int64
    4         float64   int64      int64

The sections read and written are those of an ASCII ``.mesh`` file (``_io.load``):
``Vertices``, ``Tetrahedra`` (reference -> region), ``Triangles`` and ``Edges`` (with
references, -> labelled protected faces and edges) and MMG's required entities
(``RequiredVertices``, ``RequiredEdges``, ``RequiredTriangles``, and ``RequiredTetrahedra``
under code 12, where MMG writes it). Every other keyword is skipped by its position.

Why not meshio: meshio 5.3 writes version 4 when the cells are int64, and MMG 5.7 reads
such a file as a mesh of dimension 0 ("BAD MESH DIMENSION"); meshio refuses MMG's own
files with required tets (code 12, "Unsupported field"); and it drops the required
entities. Files are written in version 2 (what MMG writes and reads) unless their
positions pass 2**31 bytes (~40M tets): version 3 then, which libMeshb reads but the MMG
5.7 reader does not.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._errors import MeshFileError, MeshInputError

END, DIMENSION, VERTICES = 54, 3, 4
#: keyword code -> (meshio cell type, vertices per line) of the cells read and written
CELLS = {5: ("line", 2), 6: ("triangle", 3), 8: ("tetra", 4)}
#: keyword code -> the section of ids it is (12: MMG's code for required tets; libMeshb
#: itself names no code for them)
REQUIRED = {
    15: "RequiredVertices",
    16: "RequiredEdges",
    17: "RequiredTriangles",
    12: "RequiredTetrahedra",
}
#: volume elements other than linear tets: refused, with their counts
OTHER_VOLUMES = {
    9: ("wedge", 6),
    10: ("hexahedron", 8),
    49: ("pyramid", 5),
    30: ("tetra10", 10),
    33: ("hexahedron27", 27),
}
#: keyword code -> (meshio cell type, nodes per line) of the second-order (P2) cells:
#: the corners, then the nodes of the edges in VTK's order (as in ``_medit``), read as
#: their corners with ``load(..., linear=True)`` and written for a quadratic output
P2_CELLS = {30: ("tetra10", 10), 24: ("triangle6", 6), 25: ("line3", 3)}
#: meshio cell type -> keyword code
ORDER = {name: code for code, (name, _) in {**CELLS, **P2_CELLS}.items()}


def _widths(version: int) -> tuple[str, str, str]:
    """(real, integer, position) dtype codes of a file ``version``, without byte order."""
    return {1: ("f4", "i4", "i4"), 2: ("f8", "i4", "i4"), 3: ("f8", "i4", "i8")}.get(
        version, ("f8", "i8", "i8")
    )


def read_meshb(path: Path, source: str):
    """(points (n, 3) float64, blocks [(meshio cell type, cells (k, j) 0-based int64,
    references (k,) int64)], required {section name: 0-based ids (k,)}) of the binary
    Medit file ``path``, in its sections' order. ``MeshFileError`` for a file that is no
    such file or is damaged, ``MeshInputError`` for one of another kind of mesh (2-D,
    other volume elements)."""
    from ._io import _MESHIO_QUADRATIC, quadratic_corners, reading_linear

    data = np.fromfile(path, np.uint8)
    reader = _Reader(data, source)
    points, blocks, required, others = None, [], {}, {}
    dim = None
    at = 8
    while True:
        code = reader.word(at)
        if code == END:
            break
        nxt = reader.position(at + 4)
        body = at + 4 + reader.pos_size
        if code == DIMENSION:
            dim = reader.dimension(body, nxt)
        elif code in (VERTICES, *CELLS, *REQUIRED, *OTHER_VOLUMES) or (
            code in P2_CELLS and reading_linear()
        ):
            count = reader.count(body)
            start = body + reader.int_size
            if code == VERTICES:
                if dim is None:
                    raise _unreadable(source, "Vertices before Dimension")
                rows = reader.table(start, count, [reader.real] * dim + [reader.int])
                points = rows[:, :dim].astype(np.float64)
                end = start + count * (dim * reader.real.itemsize + reader.int.itemsize)
            elif code in P2_CELLS and reading_linear():  # P2 cells as their corners
                kind, width = P2_CELLS[code]
                rows = reader.table(start, count, [reader.int] * (width + 1)).astype(np.int64)
                end = start + count * (width + 1) * reader.int.itemsize
                name, k = _MESHIO_QUADRATIC[kind]
                blocks.append((name, quadratic_corners(rows[:, :width] - 1, k), rows[:, -1]))
            elif code in OTHER_VOLUMES:
                name, k = OTHER_VOLUMES[code]
                others[name] = others.get(name, 0) + count
                end = start + count * (k + 1) * reader.int.itemsize
                reader.check_end(end, f"keyword {code}'s lines")
            else:
                k = CELLS[code][1] + 1 if code in CELLS else 1
                rows = reader.table(start, count, [reader.int] * k).astype(np.int64)
                end = start + count * k * reader.int.itemsize
                if code in CELLS:
                    blocks.append((CELLS[code][0], rows[:, :-1] - 1, rows[:, -1]))
                else:
                    required[REQUIRED[code]] = _ids(rows[:, 0], REQUIRED[code], source)
            if nxt == 0:  # some writers leave it to the reader: the section's end
                nxt = end
            elif nxt < end:
                raise _unreadable(source, f"keyword {code} overlaps the next")
        elif nxt == 0:
            raise _unreadable(source, f"keyword {code} has no position")
        if nxt <= at:  # positions only move forward: a damaged file cannot loop
            raise _unreadable(source, f"keyword {code} points backwards")
        at = nxt
    if dim is not None and dim != 3:
        raise MeshInputError(f"{source}: the points are {dim}-D; jtet needs a 3-D tet mesh")
    if points is None:
        raise MeshInputError(f"{source}: the file has no Vertices")
    if others:
        from ._io import _non_tet_message

        raise MeshInputError(
            _non_tet_message(source, list(others), list(others.values()), "tetra10" in others)
        )
    return points, blocks, required


def _unreadable(source: str, why: str) -> MeshFileError:
    return MeshFileError(f"{source}: not a readable binary Medit file ({why})")


def _ids(values: np.ndarray, section: str, source: str) -> np.ndarray:
    """0-based ids of a required section's 1-based ones."""
    if len(values) and values.min() < 1:
        raise MeshInputError(f"{source}: {section} lists id {int(values.min())}")
    return values - 1


class _Reader:
    """Bounds-checked views of a GMF file's bytes ``data``, in its byte order and widths."""

    def __init__(self, data: np.ndarray, source: str):
        self.data, self.source = data, source
        if len(data) < 8:
            raise _unreadable(source, "too short")
        code = int(data[:4].view("<i4")[0])
        order = {1: "<", 1 << 24: ">"}.get(code)
        if order is None:
            raise _unreadable(source, f"its first word is {code}, not 1")
        self.order = order
        version = int(data[4:8].view(order + "i4")[0])
        if version not in (1, 2, 3, 4):
            raise _unreadable(source, f"version {version}; jtet reads 1-4")
        real, integer, position = _widths(version)
        self.real, self.int = np.dtype(order + real), np.dtype(order + integer)
        self.pos = np.dtype(order + position)
        self.int_size, self.pos_size = self.int.itemsize, self.pos.itemsize

    def _scalar(self, at: int, dtype: np.dtype) -> int:
        if at < 0 or at + dtype.itemsize > len(self.data):
            raise _unreadable(self.source, "it ends before its End keyword")
        return int(self.data[at : at + dtype.itemsize].view(dtype)[0])

    def word(self, at: int) -> int:
        return self._scalar(at, np.dtype(self.order + "i4"))

    def position(self, at: int) -> int:
        return self._scalar(at, self.pos)

    def count(self, at: int) -> int:
        n = self._scalar(at, self.int)
        if n < 0:
            raise _unreadable(self.source, f"a section of {n} lines")
        return n

    def dimension(self, at: int, nxt: int) -> int:
        # a 32-bit word in every version; an 8-byte one where the next keyword says so
        wide = nxt - at == 8 and self.int_size == 8
        return self._scalar(at, self.int if wide else np.dtype(self.order + "i4"))

    def check_end(self, end: int, what: str) -> None:
        if end > len(self.data):
            raise _unreadable(self.source, f"{what} pass the end of the file")

    def table(self, at: int, count: int, fields: list[np.dtype]) -> np.ndarray:
        """(count, len(fields)) float64 / int64 array of ``count`` packed lines at ``at``."""
        row = np.dtype([(f"f{i}", d) for i, d in enumerate(fields)])
        end = at + count * row.itemsize
        self.check_end(end, "a section's lines")
        lines = self.data[at:end].view(row)
        kind = np.float64 if any(d.kind == "f" for d in fields) else np.int64
        out = np.empty((count, len(fields)), kind)
        for i in range(len(fields)):  # a column at a time (a handful of fields)
            out[:, i] = lines[f"f{i}"]
        return out


def write_meshb(path: Path, points: np.ndarray, blocks, required: dict) -> None:
    """Write a binary Medit file: ``points`` (n, 3) with reference 0, ``blocks``
    [(meshio cell type "line" / "triangle" / "tetra", or "line3" / "triangle6" /
    "tetra10" (P2, in VTK's order), cells (k, j) 0-based, references (k,))],
    ``required`` {section name of ``REQUIRED``: 0-based ids (k,)} (empty ones are
    left out). Version 2, or 3 when the file passes 2 GiB (see the module docstring)."""
    n = len(points)
    sizes = [len(points) * 28] + [len(c) * (c.shape[1] + 1) * 4 for _, c, _ in blocks]
    sizes += [len(ids) * 4 for ids in required.values()]
    version = 2 if sum(sizes) + 64 * (len(sizes) + 2) < 2**31 else 3
    if n >= 2**31 - 1 or any(len(c) >= 2**31 for _, c, _ in blocks):
        version = 4
    real, integer, position = (np.dtype("<" + t) for t in _widths(version))
    int_size = integer.itemsize
    codes = {name: code for code, name in REQUIRED.items()}
    chunks = [np.array([1, version], "<i4").tobytes()]
    offset = 8

    def section(code: int, count: int | None, body: bytes) -> None:
        nonlocal offset
        head = 4 + position.itemsize + (0 if count is None else int_size)
        nxt = offset + head + len(body)
        chunks.append(np.array([code], "<i4").tobytes() + np.array([nxt], position).tobytes())
        if count is not None:
            chunks.append(np.array([count], integer).tobytes())
        chunks.append(body)
        offset = nxt

    section(DIMENSION, None, np.array([3], "<i4").tobytes())
    vertex = np.zeros(n, np.dtype([("xyz", real, (3,)), ("ref", integer)]))
    vertex["xyz"] = points
    section(VERTICES, n, vertex.tobytes())
    for kind, cells, refs in sorted(blocks, key=lambda b: -b[1].shape[1]):
        cells = np.asarray(cells, np.int64)
        table = np.concatenate([cells + 1, np.asarray(refs, np.int64)[:, None]], axis=1)
        section(ORDER[kind], len(cells), table.astype(integer).tobytes())
    for name, ids in required.items():
        if len(ids):
            section(
                codes[name], len(ids), (np.asarray(ids, np.int64) + 1).astype(integer).tobytes()
            )
    end = offset + 4 + position.itemsize
    chunks.append(np.array([END], "<i4").tobytes() + np.array([end], position).tobytes())
    with open(path, "wb") as f:
        for chunk in chunks:
            f.write(chunk)
