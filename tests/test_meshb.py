"""Binary Medit meshes (``.meshb``, ``jtet._meshb``), against MMG and the ASCII twin.

``tests/data/mmg_required.meshb`` and ``mmg_required.mesh`` were written by mmg3d 5.7
(the pymmg package) from one jtet mesh (327 tets, two regions, three required tets and
vertices, labelled boundary triangles) with ``-nomove -noinsert -noswap -nosurf``: the
same mesh in both encodings, with MMG's Corners, Ridges, Normals and Tangents and its
required vertices, edges, triangles and tets (code 12 in the binary file).
"""

import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from helpers import delaunay_mesh, read_as_unit_tet, run_mmg3d, unit_tet10

import jtet
from jtet._errors import MeshFileError, MeshInputError
from jtet.cli import main

DATA = Path(__file__).parent / "data"
FIELDS = ("points", "tets", "region", "protected_faces", "protected_face_labels",
          "protected_edges", "protected_edge_labels", "protected_vertices",
          "protected_tets")  # fmt: skip


def _assert_same(a, b, atol=0.0):
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape, name
        np.testing.assert_allclose(x, y, atol=atol, rtol=0, err_msg=name)


@pytest.fixture(scope="module")
def marked():
    """A mesh with two regions and every kind of protected entity, with labels."""
    mesh = delaunay_mesh(60, seed=3, surface_points=30)
    T = mesh.topology
    faces = T.faces[T.boundary_face]
    sides = np.sort(faces[:4][:, [[0, 1], [1, 2], [0, 2]]].reshape(-1, 2), axis=1)
    region = np.where(mesh.points[mesh.tets].mean(axis=1)[:, 2] < 0.5, 3, 8)
    return mesh.replace(
        region=region,
        protected_faces=faces,
        protected_face_labels=np.arange(len(faces)) % 5 + 1,
        protected_edges=np.unique(sides, axis=0),
        protected_edge_labels=np.arange(len(np.unique(sides, axis=0))) + 20,
        # the first four faces' vertices too: those faces and their sides are kept
        # exactly (RequiredTriangles, RequiredEdges)
        protected_vertices=np.union1d(faces[:4].reshape(-1), [1, 4, 9]),
        protected_tets=mesh.tets[[0, 5]],
    )


def test_mmg_binary_file_reads_as_its_ascii_twin():
    """MMG's binary file gives what meshio's reading of its ASCII twin gives (points to
    1e-12: the ASCII file prints 15 digits of coordinates below 1), required tets (code
    12, which meshio refused) included."""
    binary, ascii_ = jtet.load(DATA / "mmg_required.meshb"), jtet.load(DATA / "mmg_required.mesh")
    _assert_same(binary, ascii_, atol=1e-12)
    assert len(binary.protected_tets) == 3 and len(binary.protected_vertices) >= 3
    assert sorted(set(binary.region.tolist())) == [1, 2]


def test_binary_file_holds_what_the_ascii_file_holds(tmp_path, marked):
    """Every region, label and protected entity comes back from ``.meshb`` exactly, as
    from ``.mesh`` (float64 coordinates: bit for bit), and saving warns of nothing."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jtet.save(marked, tmp_path / "m.meshb")
        jtet.save(marked, tmp_path / "m.mesh")
    back = jtet.load(tmp_path / "m.meshb")
    _assert_same(back, jtet.load(tmp_path / "m.mesh"))
    _assert_same(back, marked)


def test_binary_file_is_version_2_with_the_sections_mmg_reads(tmp_path, marked):
    """The header and keyword codes, read with struct: version 2 (32-bit positions, what
    MMG 5.7 reads; meshio wrote version 4, which it reads as a mesh of dimension 0), and
    each position is where the next keyword starts."""
    path = tmp_path / "m.meshb"
    jtet.save(marked, path)
    data = path.read_bytes()
    assert struct.unpack("<ii", data[:8]) == (1, 2)
    codes, at = [], 8
    while True:
        (code,) = struct.unpack("<i", data[at : at + 4])
        codes.append(code)
        if code == 54:
            break
        (at,) = struct.unpack("<i", data[at + 4 : at + 8])
    assert codes == [3, 4, 8, 6, 5, 15, 16, 17, 12, 54]


@pytest.mark.parametrize("version", [1, 2, 3, 4])
@pytest.mark.parametrize("order", ["<", ">"])
def test_every_version_and_byte_order(tmp_path, version, order):
    """A two-tet file written line by line with struct, in each version and byte order,
    with a keyword jtet skips (Normals) between its sections and a required tet under
    MMG's code 12."""
    points = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1)]
    tets = [(1, 2, 3, 4, 7), (2, 3, 4, 5, 9)]  # 1-based, then the reference
    real, integer, pos = {1: "fii", 2: "dii", 3: "diq", 4: "dqq"}[version]
    out = bytearray(struct.pack(order + "ii", 1, version))

    def keyword(code, body, count=None):
        head = struct.calcsize(order + "i" + pos) + (
            0 if count is None else struct.calcsize(integer)
        )
        nxt = len(out) + head + len(body)
        out.extend(struct.pack(order + "i" + pos, code, nxt))
        if count is not None:
            out.extend(struct.pack(order + integer, count))
        out.extend(body)

    keyword(3, struct.pack(order + "i", 3))
    keyword(4, b"".join(struct.pack(order + 3 * real + integer, *p, 0) for p in points), 5)
    keyword(60, struct.pack(order + 3 * real, 0, 0, 1), 1)  # Normals: skipped
    keyword(8, b"".join(struct.pack(order + 5 * integer, *t) for t in tets), 2)
    keyword(12, struct.pack(order + integer, 2), 1)
    out.extend(struct.pack(order + "i" + pos, 54, 0))
    path = tmp_path / "m.meshb"
    path.write_bytes(bytes(out))
    mesh = jtet.load(path)
    np.testing.assert_array_equal(mesh.points, points)
    assert sorted(map(sorted, mesh.tets.tolist())) == [[0, 1, 2, 3], [1, 2, 3, 4]]
    assert sorted(mesh.region.tolist()) == [7, 9]
    assert sorted(mesh.protected_tets[0].tolist()) == [1, 2, 3, 4]


def test_mmg3d_reads_what_jtet_writes(tmp_path, marked):
    """mmg3d (pymmg; skipped without it) reads jtet's .meshb and keeps its required tets
    and vertices: the same tets and vertex coordinates in its output."""
    back = run_mmg3d(marked, tmp_path / "in.meshb", tmp_path / "out.meshb", "-optim", "-nosurf")

    def corners(mesh, rows):
        return {tuple(sorted(map(tuple, mesh.points[r].tolist()))) for r in rows}

    assert corners(back, back.protected_tets) == corners(marked, marked.protected_tets)
    kept = {tuple(p) for p in back.points[back.protected_vertices].tolist()}
    assert {tuple(p) for p in marked.points[marked.protected_vertices].tolist()} <= kept


def _minimal(tmp_path, *sections, version=2):
    """A file of the given (code, count or None, body) keywords, then End."""
    out = bytearray(struct.pack("<ii", 1, version))
    for code, count, body in sections:
        head = 8 + (0 if count is None else 4)
        out += struct.pack("<ii", code, len(out) + head + len(body))
        out += b"" if count is None else struct.pack("<i", count)
        out += body
    out += struct.pack("<ii", 54, 0)
    path = tmp_path / "bad.meshb"
    path.write_bytes(bytes(out))
    return path


VERTS = (4, 4, b"".join(struct.pack("<dddi", *p, 0) for p in np.eye(4, 3, -1)))
TET = (8, 1, struct.pack("<5i", 1, 2, 3, 4, 0))


@pytest.mark.parametrize(
    "sections, error, match",
    [
        ([(3, None, struct.pack("<i", 2)), VERTS, TET], MeshInputError, "2-D"),
        ([(3, None, struct.pack("<i", 3)), TET], MeshInputError, "no Vertices"),
        ([(3, None, struct.pack("<i", 3)), VERTS], MeshInputError, "no tetrahedra"),
        (
            [(3, None, struct.pack("<i", 3)), VERTS, TET, (10, 1, struct.pack("<9i", *[1] * 9))],
            MeshInputError,
            "hexahedron",
        ),
        (
            [(3, None, struct.pack("<i", 3)), VERTS, (8, 1, struct.pack("<5i", 1, 2, 3, 9, 0))],
            MeshInputError,
            "out of range|index",
        ),  # fmt: skip
        (
            [(3, None, struct.pack("<i", 3)), VERTS, TET, (12, 1, struct.pack("<i", 5))],
            MeshInputError,
            "RequiredTetrahedra lists tet 5 of 1",
        ),  # fmt: skip
        ([(3, None, struct.pack("<i", 3)), (4, -3, b"")], MeshFileError, "-3 lines"),
        ([(3, None, struct.pack("<i", 3)), (4, 400, b"")], MeshFileError, "pass the end"),
    ],
)
def test_bad_files_are_clear_errors(tmp_path, sections, error, match):
    with pytest.raises(error, match=match):
        jtet.load(_minimal(tmp_path, *sections))


def test_damaged_headers_and_positions(tmp_path):
    path = tmp_path / "bad.meshb"
    for data, match in [
        (struct.pack("<ii", 7, 2), "first word is 7"),
        (struct.pack("<ii", 1, 9), "version 9"),
        (struct.pack("<iiii", 1, 2, 3, 4), "ends before its End"),
        (struct.pack("<iiiii", 1, 2, 3, 4, 3), "points backwards"),
        (struct.pack("<iiiiii", 1, 2, 60, 0, 0, 0), "no position"),
    ]:
        path.write_bytes(data)
        with pytest.raises(MeshFileError, match="not a readable binary Medit file") as e:
            jtet.load(path)
        assert match in str(e.value)


def test_cli_converts_between_ascii_and_binary(tmp_path):
    """``jtet convert`` from MMG's binary file to ASCII and back loses nothing."""
    src = DATA / "mmg_required.meshb"
    assert main(["convert", str(src), str(tmp_path / "a.mesh")]) == 0
    assert main(["convert", str(tmp_path / "a.mesh"), str(tmp_path / "b.meshb")]) == 0
    _assert_same(jtet.load(tmp_path / "b.meshb"), jtet.load(src))


def test_p2_tets_read_as_linear(tmp_path, monkeypatch):
    """A TetrahedraP2 section (keyword 30: corners first, then the mid-edge nodes; written
    here by jtet's writer given that keyword) is refused with the --linear hint, and read
    as its corners with ``linear=True``."""
    from jtet import _meshb

    _, points = unit_tet10()
    monkeypatch.setitem(_meshb.ORDER, "tetra10", 30)
    path = tmp_path / "p2.meshb"
    _meshb.write_meshb(path, points, [("tetra10", np.arange(10)[None], np.array([7]))], {})
    mesh = read_as_unit_tet(path)
    np.testing.assert_array_equal(mesh.region, [7])
