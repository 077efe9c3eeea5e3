"""Point data (``TetMesh.point_data``): checked on construction, carried through
``improve`` onto moved and inserted vertices, read and written by the VTK and XDMF
formats (TetGen: as point attributes)."""

import re
import warnings

import numpy as np
import pytest
from helpers import brute_force_interpolation, delaunay_mesh

import jtet
from jtet import MeshInputError
from jtet._point_data import carried_point_data, moved_vertices

# a linear field f(x) = A . x + B and a linear vector field x -> M x: interpolation that
# is linear in a tet reproduces both exactly, to rounding
A, B = np.array([1.3, -0.7, 2.1]), 0.5
M = np.array([[1.0, 2.0, 0.0], [0.0, -1.0, 3.0], [0.5, 0.0, 1.0]])
# rounding of a barycentric combination of O(1) values: a few ulps (weights in [0, 1]
# summing to 1, or slightly outside within VTK's locator tolerance)
ATOL = 1e-12


def _fields(points: np.ndarray, marker: np.ndarray) -> dict:
    return {"f": points @ A + B, "v": (points @ M.T).astype(np.float32), "marker": marker}


def _nearest(points: np.ndarray, where: np.ndarray) -> np.ndarray:
    """Brute-force nearest point of ``points`` to each of ``where``."""
    return np.argmin(((where[:, None, :] - points[None, :, :]) ** 2).sum(axis=2), axis=1)


def test_improve_carries_point_data():
    """After a run with smoothing and flips (appended vertices: the next test) the
    linear fields hold at every vertex, the vertices left in place keep their values bit
    for bit, and the integer marker of a moved vertex is that of the input vertex
    nearest to it."""
    mesh = delaunay_mesh(150, seed=1)
    rng = np.random.default_rng(0)
    marker = rng.integers(0, 1000, mesh.n_points).astype(np.int32)
    with_data = mesh.replace(point_data=_fields(mesh.points, marker))
    # two rounds: this mesh's worst tets are pinned to the cube's faces, and its rounds
    # take ~10 s to give up at the default limit
    r = jtet.improve(with_data, seed=0, perturb=2)
    plain = jtet.improve(mesh, seed=0, perturb=2)  # the data changes nothing of the run
    np.testing.assert_array_equal(r.mesh.points, plain.mesh.points)
    np.testing.assert_array_equal(r.mesh.tets, plain.mesh.tets)
    out = r.mesh
    data = out.point_data
    assert list(data) == ["f", "v", "marker"]
    assert [a.dtype for a in data.values()] == [np.float64, np.float32, np.int32]
    np.testing.assert_allclose(data["f"], out.points @ A + B, rtol=0, atol=ATOL)
    # float32 storage: its own rounding (values of O(1))
    np.testing.assert_allclose(data["v"], out.points @ M.T, rtol=0, atol=1e-6)
    moved = moved_vertices(with_data, out)
    assert moved.any()  # smoothing moved some
    said = f"point data (f, v, marker): read off the input mesh at the {moved.sum()} vertices"
    assert any(n.startswith(said) for n in r.notes), r.notes
    still = np.flatnonzero(~moved)
    for name, a in with_data.point_data.items():
        np.testing.assert_array_equal(data[name][still], a[still])
    near = _nearest(mesh.points, out.points[moved])
    np.testing.assert_array_equal(data["marker"][moved], marker[near])
    assert out.is_valid().ok


def test_carried_onto_moved_new_and_outside_vertices():
    """``carried_point_data`` on a hand-made result: interior vertices moved, vertices
    appended inside the mesh and one outside it, against the closed form (inside) and
    the brute-force nearest input vertex (outside, and integers)."""
    before = delaunay_mesh(120, seed=2)
    marker = np.arange(before.n_points) * 3
    before = before.replace(point_data=_fields(before.points, marker))
    rng = np.random.default_rng(1)
    free = before.topology.vertex_kind == 0
    points = before.points.copy()
    points[free] += rng.uniform(-0.01, 0.01, (int(free.sum()), 3))
    new = np.vstack([rng.uniform(0.1, 0.9, (5, 3)), [[1.5, 0.5, 0.5]]])
    after = jtet.TetMesh(np.vstack([points, new]), before.tets)
    data, n_outside = carried_point_data(before, after)
    assert n_outside == 1
    inside = np.ones(after.n_points, bool)
    inside[-1] = False
    np.testing.assert_allclose(data["f"][inside], after.points[inside] @ A + B, atol=ATOL)
    far = before.point_data["f"][_nearest(before.points, new[-1:])]
    np.testing.assert_array_equal(data["f"][-1:], far)
    moved = moved_vertices(before, after)
    np.testing.assert_array_equal(moved, np.concatenate([free, np.ones(len(new), bool)]))
    near = _nearest(before.points, after.points[moved])
    np.testing.assert_array_equal(data["marker"][moved], marker[near])
    still = np.flatnonzero(~moved)  # all among the input's vertices
    np.testing.assert_array_equal(data["marker"][still], marker[still])


@pytest.mark.parametrize("step", [0.002, 0.05, 0.3])
def test_carried_values_match_brute_force_on_a_curved_field(step):
    """A curved field (no interpolation reproduces it) carried onto interior vertices
    moved at random, against the brute-force interpolation in the tet holding each new
    position: vertices found in their own input star, and (steps of 0.3, about the mean
    edge length) many that left it, found around their new star or by the probe. On a
    face shared by two tets both give one value, to rounding."""
    from jtet._point_data import _holding_tets, _star_pairs

    before = delaunay_mesh(300, seed=5)
    x, y, z = before.points.T
    g = np.sin(3 * x) * np.exp(y) + z**2
    before = before.replace(point_data={"g": g, "gv": np.column_stack([g, -2 * g])})
    rng = np.random.default_rng(7)
    free = np.flatnonzero(before.topology.vertex_kind == 0)
    points = before.points.copy()
    points[free] = np.clip(points[free] + rng.uniform(-step, step, (len(free), 3)), 0.01, 0.99)
    after = jtet.TetMesh(points, before.tets)  # tets may invert: only positions matter
    data, n_outside = carried_point_data(before, after)
    moved = moved_vertices(before, after)
    ref, inside = brute_force_interpolation(before, g, after.points[moved])
    assert n_outside == 0 and (inside > -1e-12).all()  # clipped into the unit cube
    np.testing.assert_allclose(data["g"][moved], ref, rtol=0, atol=ATOL)
    np.testing.assert_allclose(data["gv"][moved][:, 1], -2 * ref, rtol=0, atol=2 * ATOL)
    # which path held them: the own input star, or (far moves) the tets around the new
    # star's vertices
    ids = np.flatnonzero(moved)
    own = np.full(before.n_points, -1)
    own[ids] = np.arange(len(ids))
    in_star = np.zeros(len(ids), bool)
    pairs = _star_pairs(before.tets, own)
    corners, weights = np.zeros((len(ids), 4), np.int64), np.zeros((len(ids), 4))
    _holding_tets(before, after.points[ids], *pairs, in_star, corners, weights)
    if step <= 0.002:
        assert in_star.all()
    if step >= 0.3:
        assert (~in_star).sum() > 10


def test_vertices_slid_within_a_boundary_face_take_their_holding_tets_values():
    """Vertices of the cube's bottom face slid within it (z stays 0): a position in the
    plane of a boundary face has a weight ~1e-17 either side of 0 towards the apex off
    that face, in every tet at it; the carried curved field is still the interpolation
    in the tet holding the point (VTK's probe took a tet beyond within its tolerance)."""
    before = delaunay_mesh(150, seed=0, surface_points=300)
    x, y, z = before.points.T
    g = np.sin(3 * x) * np.exp(y) + z**2 + x * y
    before = before.replace(point_data={"g": g})
    bottom = np.flatnonzero((z == 0) & (np.minimum(x, y) > 0.05) & (np.maximum(x, y) < 0.95))
    assert len(bottom) >= 5
    rng = np.random.default_rng(4)
    points = before.points.copy()
    points[bottom, :2] += rng.uniform(-0.01, 0.01, (len(bottom), 2))
    after = jtet.TetMesh(points, before.tets)
    data, n_outside = carried_point_data(before, after)
    ref, weight = brute_force_interpolation(before, g, points[bottom])
    assert n_outside == 0 and (weight > -1e-12).all()
    np.testing.assert_allclose(data["g"][bottom], ref, rtol=0, atol=ATOL)


def test_nothing_moved_keeps_the_arrays():
    mesh = delaunay_mesh(60, seed=3)
    mesh = mesh.replace(point_data={"t": np.arange(mesh.n_points, dtype=float)})
    data, n_outside = carried_point_data(mesh, mesh.replace(point_data=None))
    assert n_outside == 0 and data["t"] is mesh.point_data["t"]


def test_point_data_checked():
    mesh = delaunay_mesh(40, seed=4)
    n = mesh.n_points
    with pytest.raises(MeshInputError, match=r"point_data\['t'\] has shape \(3,\)"):
        mesh.replace(point_data={"t": np.zeros(3)})
    with pytest.raises(MeshInputError, match=r"has shape \(\d+, 2, 2\)"):
        mesh.replace(point_data={"t": np.zeros((n, 2, 2))})
    with pytest.raises(MeshInputError, match="not numbers"):
        mesh.replace(point_data={"t": np.array(["a"] * n)})
    with pytest.raises(MeshInputError, match="non-empty strings"):
        mesh.replace(point_data={"": np.zeros(n)})
    with pytest.raises(MeshInputError, match="mapping name -> array"):
        mesh.replace(point_data=[np.zeros(n)])
    with_data = mesh.replace(point_data={"b": np.ones(n, bool)})
    assert with_data.point_data["b"].dtype == np.int8
    assert not with_data.point_data["b"].flags.writeable
    with pytest.raises(TypeError):
        with_data.point_data["c"] = np.zeros(n)
    # new points of another count need their own point data
    more = np.vstack([mesh.points, [[0.5, 0.5, 0.5]]])
    with pytest.raises(MeshInputError, match="pass point_data for the new points"):
        with_data.replace(points=more)
    assert not with_data.replace(points=more, point_data=None).point_data
    assert "point data b" in repr(with_data)


@pytest.mark.parametrize("ext", ["vtu", "vtk", "xdmf", "exo", "med"])
def test_point_data_round_trip(tmp_path, ext):
    """The formats that store point data give back every array exactly, dtype and all
    (Exodus, MED: their variables / fields are float64)."""
    mesh = delaunay_mesh(80, seed=5)
    marker = (np.arange(mesh.n_points) % 7).astype(np.int64)
    mesh = mesh.replace(point_data={**_fields(mesh.points, marker), "on": marker > 3})
    path = jtet.save(mesh, tmp_path / f"m.{ext}")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = jtet.load(path)
    assert list(back.point_data) == list(mesh.point_data)
    for name, a in mesh.point_data.items():
        dtype = np.float64 if ext in ("exo", "med") else a.dtype
        assert back.point_data[name].dtype == dtype, name
        np.testing.assert_array_equal(back.point_data[name], a)


def test_tetgen_point_attributes(tmp_path):
    """TetGen ``.node`` files hold point attributes, reals without names: jtet writes
    its arrays as attribute columns (an (n, k) array as k columns) named in a comment
    line, and reads them back as float64 arrays of those names; a file without the
    names line gives ``attr1``, ``attr2``, ..."""
    mesh = delaunay_mesh(60, seed=7)
    marker = np.arange(mesh.n_points) % 5
    mesh = mesh.replace(point_data=_fields(mesh.points, marker))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = jtet.load(jtet.save(mesh, tmp_path / "m.node"))
    assert list(back.point_data) == ["f", "v", "marker"]
    for name, a in mesh.point_data.items():
        assert back.point_data[name].dtype == np.float64
        np.testing.assert_array_equal(back.point_data[name], a.astype(np.float64))
    # TetGen's own layout: no names, attributes then a boundary marker
    lines = [f"{mesh.n_points} 3 2 1"]
    for i, (x, y, z) in enumerate(mesh.points.tolist()):
        lines.append(f"{i} {x!r} {y!r} {z!r} {x + y!r} {2.5 * i!r} 0")
    (tmp_path / "m.node").write_text("\n".join(lines) + "\n")
    plain = jtet.load(tmp_path / "m.node")
    assert list(plain.point_data) == ["attr1", "attr2"]
    np.testing.assert_array_equal(plain.point_data["attr1"], mesh.points[:, 0] + mesh.points[:, 1])
    np.testing.assert_array_equal(plain.point_data["attr2"], 2.5 * np.arange(mesh.n_points))


@pytest.mark.parametrize("ext", ["inp", "vol"])
def test_formats_without_point_data_say_so(tmp_path, ext):
    mesh = delaunay_mesh(40, seed=6).relabel({0: 1})
    mesh = mesh.replace(point_data={"T": np.zeros(mesh.n_points)})
    with pytest.warns(UserWarning, match=r"not saved: 1 point array\(s\) \(T\)"):
        jtet.save(mesh, tmp_path / f"m.{ext}")


def _mmg_sol(n: int, types: str, rows: list[str]) -> str:
    """A solution file as MMG writes it: no names, a comment, blank lines."""
    body = "\n".join(rows)
    return (
        "# written by a test\nMeshVersionFormatted 2\n\nDimension 3\n\n"
        f"SolAtVertices\n{n}\n{types}\n{body}\n\nEnd\n"
    )


@pytest.mark.parametrize("ext", ["mesh", "meshb"])
def test_medit_solution_file(tmp_path, ext):
    """Point data of a Medit mesh lives in the ``.sol`` file beside it, as MMG reads
    and writes it: jtet writes its arrays there (scalars, vectors, symmetric 3 x 3
    matrices as MMG's types 1-3, other widths as scalar columns) and reads them back,
    names from its comment line; an MMG file without names gives ``sol``, ``sol1``,
    ...; a file for another vertex count is ignored with a warning; saving a mesh
    without point data removes the old ``.sol`` of that name."""
    mesh = delaunay_mesh(50, seed=8)
    n = mesh.n_points
    metric = np.tile([1.0, 0.0, 2.0, 0.0, 0.0, 3.0], (n, 1))
    data = {"T": mesh.points @ A, "u": mesh.points, "metric": metric, "w": np.ones((n, 2))}
    path = tmp_path / f"m.{ext}"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jtet.save(mesh.replace(point_data=data), path)
        back = jtet.load(path)
    text = (tmp_path / "m.sol").read_text()
    assert "SolAtVertices" in text and "4 1 2 3 1 1" not in text  # w: two scalars
    assert f"{n}\n5 1 2 3 1 1\n" in text
    assert list(back.point_data) == ["T", "u", "metric", "w"]
    for name, a in data.items():
        np.testing.assert_array_equal(back.point_data[name], a)
    # MMG's own file: two solutions, no names
    rows = [f"{i}.5 {x!r} {y!r} {z!r}" for i, (x, y, z) in enumerate(mesh.points.tolist())]
    (tmp_path / "m.sol").write_text(_mmg_sol(n, "2 1 2", rows))
    mmg = jtet.load(path)
    assert list(mmg.point_data) == ["sol1", "sol2"]
    np.testing.assert_array_equal(mmg.point_data["sol1"], np.arange(n) + 0.5)
    np.testing.assert_array_equal(mmg.point_data["sol2"], mesh.points)
    (tmp_path / "m.sol").write_text(_mmg_sol(n - 1, "1 1", ["1.0"] * (n - 1)))
    with pytest.warns(UserWarning, match=f"values at {n - 1} vertices, the mesh has {n}"):
        assert not jtet.load(path).point_data
    jtet.save(mesh, path)
    assert not (tmp_path / "m.sol").exists()


def test_damaged_solution_file_refused(tmp_path):
    mesh = delaunay_mesh(30, seed=9)
    path = jtet.save(mesh, tmp_path / "m.mesh")
    (tmp_path / "m.sol").write_text(_mmg_sol(mesh.n_points, "1 1", ["1.0"] * 3))
    with pytest.raises(
        MeshInputError, match=r"m.sol: SolAtVertices holds fewer than \d+ rows of 1 numbers"
    ):
        jtet.load(path)
    (tmp_path / "m.sol").write_text(_mmg_sol(mesh.n_points, "1 7", ["1.0"]))
    with pytest.raises(MeshInputError, match=r"solution types \[7\]"):
        jtet.load(path)
    (tmp_path / "m.sol").write_text("MeshVersionFormatted x\n")
    with pytest.raises(MeshInputError, match="not a readable Medit solution file"):
        jtet.load(path)


def test_cli_keeps_the_input_solution_file(tmp_path):
    """``jtet improve m.mesh m.meshb`` would replace m.sol, the input's point data: it
    is refused without --overwrite; to another name the .sol goes along."""
    from jtet.cli import main

    mesh = delaunay_mesh(40, seed=10)
    path = jtet.save(mesh.replace(point_data={"T": mesh.points[:, 0]}), tmp_path / "m.mesh")
    before = (tmp_path / "m.sol").read_bytes()
    assert main(["improve", str(path), str(tmp_path / "m.meshb"), "-q", "--perturb", "0"]) == 2
    assert (tmp_path / "m.sol").read_bytes() == before
    out = tmp_path / "out.mesh"
    assert main(["improve", str(path), str(out), "-q", "--perturb", "0"]) == 0
    carried = jtet.load(out).point_data["T"]
    np.testing.assert_allclose(carried, jtet.load(out).points[:, 0], rtol=0, atol=ATOL)


def test_point_data_change_keeps_the_cached_topology():
    """A change of point data alone keeps the topology and volumes a mesh computed
    (``improve`` strips the point data for its run); other changes and another feature
    angle do not."""
    mesh = delaunay_mesh(40, seed=11)
    topology, volumes = mesh.topology, mesh.volumes
    with_data = mesh.replace(point_data={"T": np.zeros(mesh.n_points)})
    assert with_data.topology is topology and with_data.volumes is volumes
    assert with_data.replace(point_data=None).topology is topology
    assert "topology" not in mesh._with_feature_angle(10.0).__dict__
    assert "topology" not in mesh.replace(region=np.ones(mesh.n_tets, int)).__dict__


def test_stats_groups_list_the_point_data(tmp_path, capsys):
    """``jtet stats --groups`` lists each point array with its components and the range
    of its finite values (NaN, a missing value in a field, left out)."""
    import json

    from jtet.cli import main

    mesh = delaunay_mesh(40, seed=12)
    t = mesh.points[:, 2] * 5.0
    t[3] = np.nan
    path = jtet.save(mesh.replace(point_data={"T": t, "u": mesh.points}), tmp_path / "m.vtu")
    assert main(["stats", str(path), "--groups", "--json"]) == 0
    groups = [g for g in json.loads(capsys.readouterr().out)["groups"] if g["label"] is None]
    n = mesh.n_points
    assert groups == [
        {"kind": "point data", "label": None, "name": "T", "count": n, "components": 1,
         "min": float(np.nanmin(t)), "max": float(np.nanmax(t))},
        {"kind": "point data", "label": None, "name": "u", "count": n, "components": 3,
         "min": float(mesh.points.min()), "max": float(mesh.points.max())},
    ]  # fmt: skip
    assert main(["stats", str(path), "--groups"]) == 0
    assert re.search(rf"point data +u +{n} x 3 values in \[", capsys.readouterr().out)
