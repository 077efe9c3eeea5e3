"""Cell data (``TetMesh.cell_data``): checked on construction, carried through
``improve`` (integer arrays with their interfaces kept, every new tet with the values of
an input tet it overlaps), read and written by the VTK and XDMF formats."""

import contextlib
import io
import warnings

import numpy as np
import pytest
from helpers import barycentric_in_every_tet, delaunay_mesh

import jtet
from jtet import MeshInputError
from jtet._cell_data import (
    _SAMPLE_WEIGHTS,
    _same_tets,
    carried_cell_data,
    id_arrays,
    interface_faces,
)
from jtet._point_data import moved_vertices


def _volumes(mesh: jtet.TetMesh) -> np.ndarray:
    p = mesh.points[mesh.tets]
    return np.linalg.det(p[:, 1:] - p[:, :1]) / 6


def _labelled(mesh: jtet.TetMesh) -> jtet.TetMesh:
    """``mesh`` with an integer material (the octant of its tets' centroids: interfaces
    that zigzag through the mesh), a density that is a function of the material, and a
    float field with one distinct value per tet."""
    c = mesh.points[mesh.tets].mean(axis=1)
    mat = (c[:, 0] > 0.5).astype(np.int32) + 2 * (c[:, 1] > 0.4).astype(np.int32)
    density = np.column_stack([1.0 + 0.25 * mat, -mat.astype(np.float64)])
    return mesh.replace(cell_data={"mat": mat, "density": density, "x": c[:, 0]})


@pytest.fixture(scope="module")
def carried_run():
    mesh = _labelled(delaunay_mesh(150, seed=1))
    # two rounds: this mesh's rounds take ~10 s to give up at the default limit
    return mesh, jtet.improve(mesh, seed=0, perturb=2)


def test_integer_arrays_keep_their_pieces(carried_run):
    """Every material keeps its volume to rounding (its interfaces stayed in place, so
    no tet of the result straddles two), and the density, a function of the material,
    follows it exactly: each new tet took its values from one input tet it overlaps."""
    mesh, r = carried_run
    out = r.mesh
    assert out.tets.shape != mesh.tets.shape or not np.array_equal(out.tets, mesh.tets)
    mat = out.cell_data["mat"]
    assert mat.dtype == np.int32 and out.cell_data["density"].shape == (out.n_tets, 2)
    vin, vout = _volumes(mesh), _volumes(out)
    for k in range(4):
        # sums of ~200 volumes of O(1e-3): rounding far below 1e-12
        assert abs(vin[mesh.cell_data["mat"] == k].sum() - vout[mat == k].sum()) < 1e-12
    expected = np.column_stack([1.0 + 0.25 * mat, -mat.astype(np.float64)])
    np.testing.assert_array_equal(out.cell_data["density"], expected)
    # the run's interface faces are not in the result's protected faces
    assert len(out.protected_faces) == len(mesh.protected_faces) == 0
    notes = " | ".join(r.notes)
    assert "cell data (mat, density, x): the " in notes
    assert (
        f"({len(interface_faces(mesh, id_arrays(mesh)))} in the input) were kept in place" in notes
    )


def test_unchanged_tets_keep_their_rows(carried_run):
    """A tet of the result with the vertices of an input tet, none of them moved, keeps
    that tet's row bit for bit; every other tet's value is that of an input tet holding
    a point inside it (checked by barycentric coordinates, brute force)."""
    mesh, r = carried_run
    out = r.mesh
    same = _same_tets(mesh, out)
    same[moved_vertices(mesh, out)[out.tets].any(axis=1)] = -1  # kept only if none moved
    kept = np.flatnonzero(same >= 0)
    assert 0 < len(kept) < out.n_tets
    # brute-force match of the kept tets by their sorted vertex rows
    rows_in = {tuple(t): i for i, t in enumerate(np.sort(mesh.tets, axis=1).tolist())}
    for i in kept:
        assert rows_in[tuple(sorted(out.tets[i].tolist()))] == same[i]
    np.testing.assert_array_equal(out.cell_data["x"][kept], mesh.cell_data["x"][same[kept]])
    new = np.flatnonzero(same < 0)
    p = mesh.points[mesh.tets]
    inv = np.linalg.inv(np.transpose(p[:, 1:] - p[:, :1], (0, 2, 1)))
    corners = out.points[out.tets[new]]
    for q, c in zip(new, corners, strict=True):
        # the tets of ``mesh`` that hold the new tet's centroid or one of the points
        # nearer one corner that the carrying also tries (barycentric coordinates; the
        # tolerance admits both tets of a point on a face)
        holders = []
        for w in _SAMPLE_WEIGHTS:
            lam = np.einsum("tij,tj->ti", inv, w @ c - p[:, 0])
            bary = np.column_stack([1 - lam.sum(axis=1), lam])
            holders += np.flatnonzero((bary > -1e-12).all(axis=1)).tolist()
        assert out.cell_data["x"][q] in mesh.cell_data["x"][holders]


def test_floats_and_ids_change_nothing_of_the_run():
    """Float arrays and arrays of distinct ids add no interface: the run is the run
    without them, and the ids become provenance (a note says so)."""
    mesh = delaunay_mesh(120, seed=4)
    c = mesh.points[mesh.tets].mean(axis=1)
    ids = np.arange(100, 100 + mesh.n_tets, dtype=np.int64)
    with_data = mesh.replace(cell_data={"x": c[:, 0].astype(np.float32), "id": ids})
    assert id_arrays(with_data) == ["id"] and not len(interface_faces(with_data, ["id"]))
    r = jtet.improve(with_data, seed=0, perturb=1)
    plain = jtet.improve(mesh, seed=0, perturb=1)
    np.testing.assert_array_equal(r.mesh.points, plain.mesh.points)
    np.testing.assert_array_equal(r.mesh.tets, plain.mesh.tets)
    assert r.mesh.cell_data["x"].dtype == np.float32
    assert set(r.mesh.cell_data["id"]) <= set(ids)
    assert any(n.startswith("id: a distinct integer in every input tet") for n in r.notes)


def _holders(mesh: jtet.TetMesh, x: np.ndarray, tol: float) -> list[np.ndarray]:
    """For each point of ``x`` (q, 3), the tets of ``mesh`` whose barycentric coordinates
    of it are all > ``tol`` (brute force over every tet)."""
    return [np.flatnonzero((w > tol).all(axis=1)) for w in barycentric_in_every_tet(mesh, x)]


@pytest.mark.parametrize("scale", [0.002, 0.05])
def test_moved_tets_take_the_input_tet_holding_their_centroid(scale):
    """Every tet keeps its vertex ids and the interior vertices move at random, by up to
    ``scale`` of the unit cube (moves that would invert a tet are undone). A moved tet
    whose centroid is still inside its own input tet (brute-force barycentric
    coordinates above 1e-9) takes that tet's row; any other takes the row of an input
    tet holding its centroid or one of the points nearer a corner (coordinates above
    -1e-9: a point on a face may go to either side); unmoved tets keep their rows."""
    mesh = delaunay_mesh(200, seed=5)
    mesh = mesh.replace(cell_data={"tet": np.arange(mesh.n_tets)})
    rng = np.random.default_rng(7)
    inner = np.flatnonzero((np.abs(mesh.points - 0.5) < 0.5 - 1e-9).all(axis=1))
    moved_pts = mesh.points.copy()
    moved_pts[inner] += rng.uniform(-scale, scale, (len(inner), 3))
    after = mesh.replace(points=moved_pts, cell_data=None)
    for _ in range(50):  # the vertices of tets the moves inverted go back
        flat = after.volumes <= 0
        if not flat.any():
            break
        moved_pts[mesh.tets[flat]] = mesh.points[mesh.tets[flat]]
        after = mesh.replace(points=moved_pts, cell_data=None)
    assert (after.volumes > 0).all()  # still a valid mesh
    data, n_new, n_unconfirmed = carried_cell_data(mesh, after)
    unmoved = ~moved_vertices(mesh, after)[mesh.tets].any(axis=1)
    assert (~unmoved).sum() > 300  # most of the mesh, or a good part of it, moved
    assert n_new == int((~unmoved).sum()) and n_unconfirmed == 0
    took = data["tet"]  # the input tet each tet took its row from
    np.testing.assert_array_equal(took[unmoved], np.flatnonzero(unmoved))
    moved = np.flatnonzero(~unmoved)
    corners = after.points[after.tets[moved]]
    p = mesh.points[mesh.tets[moved]]
    inv = np.linalg.inv(np.transpose(p[:, 1:] - p[:, :1], (0, 2, 1)))
    lam = np.einsum("qij,qj->qi", inv, corners.mean(axis=1) - p[:, 0])
    in_own = (np.column_stack([1 - lam.sum(axis=1), lam]) > 1e-9).all(axis=1)
    np.testing.assert_array_equal(took[moved[in_own]], moved[in_own])
    samples = [_holders(mesh, w @ corners[~in_own], -1e-9) for w in _SAMPLE_WEIGHTS]
    for k, q in enumerate(moved[~in_own]):
        assert any(took[q] in held[k] for held in samples)
    if scale > 0.01:  # the far moves took some centroids out of their own tets
        assert (~in_own).sum() > 10
    assert in_own.sum() > 0.5 * len(moved)


def test_carried_cell_data_of_an_unchanged_mesh_is_exact():
    mesh = _labelled(delaunay_mesh(60, seed=2))
    data, n_new, n_unconfirmed = carried_cell_data(mesh, mesh)
    assert (n_new, n_unconfirmed) == (0, 0)
    for name, a in mesh.cell_data.items():
        np.testing.assert_array_equal(data[name], a)


def test_cell_data_is_checked():
    mesh = delaunay_mesh(40, seed=3)
    m = mesh.n_tets
    with_data = mesh.replace(cell_data={"flag": np.ones(m, bool)})
    assert with_data.cell_data["flag"].dtype == np.int8
    assert not with_data.cell_data["flag"].flags.writeable
    assert "cell data flag" in repr(with_data)
    bad = [
        ({"a": np.ones(m + 1)}, r"cell_data\['a'\] has shape \(\d+,\); it needs one value"),
        ({"a": np.ones((m, 2, 2))}, "one row of values per tet"),
        ({"a": np.array(["x"] * m)}, "not numbers"),
        ({"region": np.ones(m)}, "may not hold 'region'"),
        ({"": np.ones(m)}, "non-empty strings"),
        ([1, 2], "must be a mapping"),
    ]
    for value, message in bad:
        with pytest.raises(MeshInputError, match=message):
            mesh.replace(cell_data=value)
    fewer = {"tets": with_data.tets[:-1], "region": with_data.region[:-1]}
    with pytest.raises(MeshInputError, match="pass cell_data for the new tets too"):
        with_data.replace(**fewer)
    assert with_data.replace(**fewer, cell_data=None).n_tets == m - 1
    # new cell data alone keeps the mesh's topology
    topo = with_data.topology
    assert with_data.replace(cell_data={"b": np.zeros(m)}).topology is topo


@pytest.mark.parametrize("ext", ["vtu", "vtk", "xdmf"])
def test_formats_keep_cell_data(tmp_path, ext):
    mesh = _labelled(delaunay_mesh(40, seed=3))
    path = tmp_path / f"m.{ext}"
    jtet.save(mesh, path)
    back = jtet.load(path)
    assert list(back.cell_data) == list(mesh.cell_data)
    for name, a in mesh.cell_data.items():
        assert back.cell_data[name].dtype == a.dtype
        np.testing.assert_array_equal(back.cell_data[name], a)


@pytest.mark.parametrize("ext", ["mesh", "node"])
def test_other_formats_say_they_leave_cell_data_out(tmp_path, ext):
    mesh = _labelled(delaunay_mesh(40, seed=3))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        jtet.save(mesh, tmp_path / f"m.{ext}")
    said = [str(w.message) for w in caught if "cell array(s)" in str(w.message)]
    assert said and "not saved: 3 cell array(s) (mat, density, x)" in said[0]


def test_cli_carries_cell_data_and_lists_it(tmp_path):
    from jtet.cli import main

    mesh = _labelled(delaunay_mesh(60, seed=5))
    jtet.save(mesh, tmp_path / "in.vtu")
    assert (
        main(["improve", str(tmp_path / "in.vtu"), str(tmp_path / "out.vtu"), "--perturb", "0"])
        == 0
    )
    out = jtet.load(tmp_path / "out.vtu")
    assert list(out.cell_data) == ["mat", "density", "x"]
    vin, vout = _volumes(mesh), _volumes(out)
    for k in range(4):
        assert (
            abs(vin[mesh.cell_data["mat"] == k].sum() - vout[out.cell_data["mat"] == k].sum())
            < 1e-12
        )
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["stats", "--groups", str(tmp_path / "out.vtu")]) == 0
    text = buf.getvalue()
    assert "cell data" in text and "density" in text and f"{out.n_tets} x 2 values" in text


def test_cli_drop_leaves_arrays_out(tmp_path, capsys):
    """``--drop`` leaves named point or cell arrays of the input out (the run is then
    the run without them); a name the file does not have is a one-line error."""
    from jtet.cli import main

    mesh = _labelled(delaunay_mesh(60, seed=5))
    mesh = mesh.replace(point_data={"T": np.zeros(mesh.n_points)})
    jtet.save(mesh, tmp_path / "in.vtu")
    args = ["improve", str(tmp_path / "in.vtu"), str(tmp_path / "out.vtu"), "--perturb", "0"]
    assert main([*args, "--drop", "mat,T", "-q"]) == 0
    out = jtet.load(tmp_path / "out.vtu")
    assert list(out.cell_data) == ["density", "x"] and not out.point_data
    plain = jtet.improve(mesh.replace(cell_data=None, point_data=None), perturb=0)
    np.testing.assert_array_equal(out.tets, plain.mesh.tets)
    capsys.readouterr()
    assert main([*args, "--drop", "nope", "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert "--drop: no point or cell data array 'nope' (the file has: T, mat, density, x)" in err
    convert = ["convert", str(tmp_path / "in.vtu"), str(tmp_path / "c.vtu"), "--drop", "x"]
    assert main(convert) == 0
    assert list(jtet.load(tmp_path / "c.vtu").cell_data) == ["mat", "density"]


def test_a_tet_outside_the_input_takes_the_nearest_centroid():
    """A new tet that overlaps no input tet (here wholly outside the input mesh, as a
    tet slid off a curved boundary may be in part) takes the values of the input tet
    whose centroid is nearest to its own (brute force), and is counted."""
    mesh = _labelled(delaunay_mesh(60, seed=2))
    outside = np.array([[1.5, 0.2, 0.2], [1.9, 0.2, 0.2], [1.5, 0.6, 0.2], [1.5, 0.2, 0.6]])
    n = mesh.n_points
    after = jtet.TetMesh(
        np.concatenate([mesh.points, outside]),
        np.concatenate([mesh.tets, [[n, n + 1, n + 2, n + 3]]]),
    )
    data, n_new, n_unconfirmed = carried_cell_data(mesh, after)
    assert (n_new, n_unconfirmed) == (1, 1)
    centroids = mesh.points[mesh.tets].mean(axis=1)
    nearest = np.argmin(((centroids - outside.mean(axis=0)) ** 2).sum(axis=1))
    np.testing.assert_array_equal(data["x"][-1], mesh.cell_data["x"][nearest])
    np.testing.assert_array_equal(data["x"][:-1], mesh.cell_data["x"])
