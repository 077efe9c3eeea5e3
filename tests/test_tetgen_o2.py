"""TetGen's second-order files (``tetgen -o2``, ``_tetgen_o2``): TetGen 1.6's own output
(``tests/data/tetgen_o2``, how it was made is in its README) read with ``--linear``
against TetGen's linear run of the same input, the edge order against TetGen's nodes,
and jtet's quadratic TetGen output read back by hand."""

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from helpers import TETGEN_EDGES, TETGEN_FACE_EDGES, delaunay_mesh, tetgen_face_file, tetgen_file

import jtet
from jtet._errors import MeshFileError, MeshInputError
from jtet.cli import main

DATA = Path(__file__).parent / "data" / "tetgen_o2"


def _load_linear(path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = jtet.load(path, linear=True)
    return mesh, [str(w.message) for w in caught]


def test_tetgen_edge_order_is_tetgens():
    """In TetGen's own -o2 file every edge node of every element (but element 0, whose
    ids TetGen 1.6 writes wrong) is the midpoint of the edge ``TETGEN_EDGES`` gives,
    exactly (TetGen averages the two ends), and the module's constant is that order."""
    from jtet._tetgen import TETGEN_MID_EDGES

    points, tets, _ = tetgen_file(DATA / "ball.1.node")
    assert TETGEN_MID_EDGES.tolist() == [list(e) for e in TETGEN_EDGES]
    good = tets[1:]
    for k, (a, b) in enumerate(TETGEN_EDGES):
        mid = 0.5 * (points[good[:, a]] + points[good[:, b]])
        np.testing.assert_array_equal(points[good[:, 4 + k]], mid)
    assert (tets[0, 4:8] < 0).any() or (tets[0, 4:8] >= len(points)).any()


def test_tetgen_face_edge_order_is_tetgens():
    """In TetGen's own -o2 .face file the three nodes after a face's corners are the
    midpoints of its edges in the order ``TETGEN_FACE_EDGES`` gives (ab, bc, ca), for
    every face whose ids are nodes (one face lists element 0's wrong ids)."""
    points, _, _ = tetgen_file(DATA / "ball.1.node")
    faces, markers = tetgen_face_file(DATA / "ball.1.node")
    good = (faces < len(points)).all(axis=1) & (faces >= 0).all(axis=1)
    assert good.sum() == len(faces) - 1 and set(markers.tolist()) == {5}
    for k, (a, b) in enumerate(TETGEN_FACE_EDGES):
        mid = 0.5 * (points[faces[good, a]] + points[faces[good, b]])
        np.testing.assert_array_equal(points[faces[good, 3 + k]], mid)


def test_tetgen_o2_output_reads_as_tetgens_linear_mesh():
    """--linear reads TetGen's -o2 output as the mesh TetGen's linear run of the same
    input gives: the same points, tets, region attributes and (from the 6-node .face
    file) protected faces with their markers; the edge nodes are left out with a
    warning, element 0's wrong ids with one naming it."""
    mesh, said = _load_linear(DATA / "ball.1.node")
    linear = jtet.load(DATA / "ball_linear.1.node")
    np.testing.assert_array_equal(mesh.points, linear.points)
    np.testing.assert_array_equal(mesh.tets, linear.tets)
    np.testing.assert_array_equal(mesh.region, linear.region)
    np.testing.assert_array_equal(mesh.protected_faces, linear.protected_faces)
    np.testing.assert_array_equal(mesh.protected_face_labels, linear.protected_face_labels)
    assert set(mesh.protected_face_labels.tolist()) == {5} and len(mesh.protected_faces) == 98
    assert not mesh.has_curved_edges  # TetGen's edge nodes are midpoints
    assert any("1 element(s) (0)" in s and "TetGen 1.6" in s for s in said)
    assert any("254 mid-edge node(s) left out" in s for s in said)
    # the .ele file by itself names the pair too
    again, _ = _load_linear(DATA / "ball.1.ele")
    np.testing.assert_array_equal(again.tets, mesh.tets)


def test_tetgen_o2_without_linear_is_refused_with_the_way(tmp_path, capsys):
    with pytest.raises(MeshInputError, match=r"10-node tetrahedron x 148.*--linear"):
        jtet.load(DATA / "ball.1.node")
    assert main(["stats", str(DATA / "ball.1.node")]) == 2
    assert "--linear" in capsys.readouterr().err
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["stats", "--linear", str(DATA / "ball.1.node")]) == 0


def _copy(tmp_path: Path, ele_text: str | None = None) -> Path:
    for name in ("ball.1.node", "ball.1.ele"):
        shutil.copy(DATA / name, tmp_path / name)
    if ele_text is not None:
        (tmp_path / "ball.1.ele").write_text(ele_text)
    return tmp_path / "ball.1.node"


@pytest.mark.parametrize(
    "change, error, match",
    [
        (lambda rows: rows[:-2], MeshFileError, "elements of 10 nodes"),  # cut short
        (
            lambda rows: [rows[0], rows[1].replace(" 18 ", " 9999 ", 1), *rows[2:]],
            MeshInputError,
            "element 1 has a corner that is no node",
        ),  # fmt: skip
        (lambda rows: [rows[0], rows[1] + " 2.5", *rows[2:]], MeshFileError, "announced"),
        (
            lambda rows: [rows[0], rows[1].rsplit(" ", 1)[0] + " 1.5", *rows[2:]],
            MeshInputError,
            "attribute '1.5'",
        ),  # fmt: skip
        (
            lambda rows: [rows[0], rows[1].replace("64", "x", 1), *rows[2:]],
            MeshFileError,
            "a word",
        ),  # fmt: skip
    ],
)
def test_damaged_tetgen_o2_files_are_refused(tmp_path, change, error, match):
    """A damaged 10-node .ele file gets a clear error, and the temporary linear copy
    jtet makes for meshio is gone after it."""
    lines = (DATA / "ball.1.ele").read_text().splitlines()
    header, rows = lines[0], [ln for ln in lines[1:] if not ln.startswith("#")]
    node = _copy(tmp_path, "\n".join([header, *change(rows)]) + "\n")
    import tempfile

    before = set(Path(tempfile.gettempdir()).glob("jtet-tetgen-o2-*"))
    with pytest.raises(error, match=match), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        jtet.load(node, linear=True)
    assert set(Path(tempfile.gettempdir()).glob("jtet-tetgen-o2-*")) == before


def test_quadratic_tetgen_output_round_trip_with_curved_edges(tmp_path):
    """save(..., quadratic=True) to .node writes 10-node tets in TetGen's order: parsed
    by hand, each edge node is the mesh's curved edge node or the edge's midpoint; read
    back with --linear it gives the same corners, curved edges, regions, protected
    faces and point data."""
    mesh = delaunay_mesh(60, seed=3)
    rng = np.random.default_rng(3)
    edges = np.unique(np.sort(mesh.tets[:, [0, 1]], axis=1), axis=0)[:12]
    length = np.linalg.norm(mesh.points[edges[:, 1]] - mesh.points[edges[:, 0]], axis=1)
    bent = 0.5 * mesh.points[edges].sum(axis=1) + 0.05 * length[:, None] * rng.normal(
        size=(len(edges), 3)
    )
    faces = np.sort(mesh.tets[:5, :3], axis=1)
    mesh = mesh.replace(
        curved_edges=(edges, bent),
        region=np.arange(mesh.n_tets) % 3,
        protected_faces=faces,
        protected_face_labels=np.arange(5) + 7,
        point_data={"T": np.arange(mesh.n_points, dtype=np.float64)},
    )
    out = tmp_path / "q.node"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a bent edge may fold a tet (folded_tets)
        jtet.save(mesh, out, quadratic=True)
    points, tets, attributes = tetgen_file(out)
    expected = {tuple(e): p for e, p in zip(edges.tolist(), bent, strict=True)}
    np.testing.assert_array_equal(tets[:, :4], mesh.tets)
    np.testing.assert_array_equal(attributes[:, 0], mesh.region)
    for k, (a, b) in enumerate(TETGEN_EDGES):
        for t in range(len(tets)):
            key = tuple(sorted((int(tets[t, a]), int(tets[t, b]))))
            want = expected.get(key, 0.5 * (points[key[0]] + points[key[1]]))
            np.testing.assert_allclose(points[tets[t, 4 + k]], want, rtol=0, atol=1e-15)
    again, said = _load_linear(out)
    np.testing.assert_array_equal(again.points, mesh.points)
    np.testing.assert_array_equal(again.tets, mesh.tets)
    np.testing.assert_array_equal(again.region, mesh.region)
    order = np.lexsort(again.curved_edges.edges.T[::-1])
    np.testing.assert_array_equal(again.curved_edges.edges[order], edges)
    np.testing.assert_array_equal(again.curved_edges.points[order], bent)
    np.testing.assert_array_equal(again.protected_faces, mesh.protected_faces)
    np.testing.assert_array_equal(again.protected_face_labels, mesh.protected_face_labels)
    np.testing.assert_array_equal(again.point_data["T"], mesh.point_data["T"])
    assert any("12 off their edges' midpoints" in s for s in said)
    # the .face file lists each face's edge nodes as TetGen -o2 does: the tets' nodes
    faces, markers = tetgen_face_file(out)
    np.testing.assert_array_equal(faces[:, :3], mesh.protected_faces)
    np.testing.assert_array_equal(markers, mesh.protected_face_labels)
    node_of = {}
    for k, (a, b) in enumerate(TETGEN_EDGES):
        for t in range(len(tets)):
            node_of[tuple(sorted((int(tets[t, a]), int(tets[t, b]))))] = int(tets[t, 4 + k])
    for k, (a, b) in enumerate(TETGEN_FACE_EDGES):
        for f in range(len(faces)):
            key = tuple(sorted((int(faces[f, a]), int(faces[f, b]))))
            assert faces[f, 3 + k] == node_of[key]


def test_cli_improves_tetgen_o2_to_tetgen_o2(tmp_path):
    """``jtet improve ball.1.node out.node --linear --quadratic``: TetGen's -o2 mesh in,
    a 10-node TetGen mesh out, improved, with the ball's facets and region."""
    out = tmp_path / "out.node"
    args = ["improve", str(DATA / "ball.1.node"), str(out), "-q", "--linear", "--quadratic"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(args) == 0
    header = (tmp_path / "out.ele").read_text().splitlines()[1].split()
    assert header[1:] == ["10", "1"]  # 10-node tets, the region attribute
    improved, _ = _load_linear(out)
    before = jtet.stats(jtet.load(DATA / "ball_linear.1.node"))
    assert jtet.stats(improved).min_dihedral > before.min_dihedral
    assert set(improved.protected_face_labels.tolist()) == {5}
    assert set(improved.region.tolist()) == {1}


def test_tetgen_reads_jtet_quadratic_output(tmp_path):
    """TetGen's own reader (tetgenpy, AGPL: tests only) takes jtet's 10-node .node /
    .ele files: the same points, the same 10 nodes per tet in the file's order, and the
    region attribute."""
    tetgenpy = pytest.importorskip("tetgenpy")
    mesh = delaunay_mesh(50, seed=4)
    mesh = mesh.replace(region=np.arange(mesh.n_tets) % 2 + 1)
    jtet.save(mesh, tmp_path / "q.node", quadratic=True)
    points, tets, attributes = tetgen_file(tmp_path / "q.node")
    io = tetgenpy.TetgenIO()
    io.load_node(str(tmp_path / "q")), io.load_tet(str(tmp_path / "q"))
    np.testing.assert_array_equal(io.points(), points)
    np.testing.assert_array_equal(io.tetrahedra(), tets)
    np.testing.assert_array_equal(np.ravel(io.tetrahedronattributes()), attributes[:, 0])
