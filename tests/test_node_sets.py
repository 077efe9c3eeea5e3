"""``TetMesh.node_sets``: named vertex sets a solver's input refers to (Abaqus ``*NSET``,
Exodus node sets), kept through ``improve`` and the formats that hold them."""

import warnings

import numpy as np
import pytest
from helpers import delaunay_mesh

import jtet
from jtet._errors import MeshInputError


@pytest.fixture(scope="module")
def mesh():
    return delaunay_mesh(150, seed=12)


def _interior(mesh) -> np.ndarray:
    T = mesh.topology
    return np.setdiff1d(np.arange(mesh.n_points), np.unique(T.faces[T.boundary_face]))


def test_sets_are_checked_and_normalized(mesh):
    m = mesh.replace(node_sets=[("a", [5, 2, 5]), jtet.NodeSet("b", np.array([1]), 7)])
    assert [(s.name, s.ids.tolist(), s.label) for s in m.node_sets] == [
        ("a", [2, 5], None),
        ("b", [1], 7),
    ]
    assert not m.node_sets[0].ids.flags.writeable
    assert "2 node set(s)" in repr(m)
    for bad, match in [
        ([("a", [mesh.n_points])], "out of range"),
        ([("a", [-1])], "out of range"),
        ([("a", [0.5])], "integer"),
        ([(3, [1])], "names must be strings"),
        ([("a",)], "name, vertex ids"),
    ]:
        with pytest.raises(MeshInputError, match=match):
            mesh.replace(node_sets=bad)


def test_improve_never_moves_their_vertices(mesh):
    """Interior vertices that the run moves when free stay put in a set, overlapping
    sets included; a set of every vertex constrains nothing (the run moves as many
    vertices as with no set). The result keeps the sets as they were."""
    free = jtet.improve(mesh, max_passes=3, perturb=0).mesh
    moved = np.flatnonzero((free.points != mesh.points).any(axis=1))
    chosen = np.intersect1d(moved, _interior(mesh))[:6]
    assert len(chosen) == 6
    sets = [("a", chosen[:4]), ("b", chosen[2:]), ("all", np.arange(mesh.n_points))]
    result = jtet.improve(mesh.replace(node_sets=sets), max_passes=3, perturb=0)
    np.testing.assert_array_equal(result.mesh.points[chosen], mesh.points[chosen])
    assert [(s.name, s.ids.tolist()) for s in result.mesh.node_sets] == [
        (n, np.sort(i).tolist()) for n, i in sets
    ]
    assert len(result.mesh.protected_vertices) == 0  # the pins were the run's only
    only_all = jtet.improve(mesh.replace(node_sets=sets[2:]), max_passes=3, perturb=0)
    np.testing.assert_array_equal(only_all.mesh.points, free.points)


@pytest.mark.parametrize("ext", ["vtu", "vtk", "inp", "exo", "med"])
def test_formats_that_hold_them(tmp_path, mesh, ext):
    sets = [("a b", [1, 4, 9], 3), ("c", [4, 5])]
    m = mesh.replace(region=np.ones(mesh.n_tets, np.int64), node_sets=sets)
    path = tmp_path / f"m.{ext}"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jtet.save(m, path)
    back = jtet.load(path)
    got = [(s.name, s.ids.tolist()) for s in back.node_sets]
    # Abaqus names: letters, digits, underscores
    assert got == [("a_b" if ext == "inp" else "a b", [1, 4, 9]), ("c", [4, 5])]
    if ext == "exo":
        assert [s.label for s in back.node_sets] == [3, 4]  # the second takes a free id
    if ext == "med":
        assert [s.label for s in back.node_sets] == [None, None]  # MED groups have names only


def test_long_node_set_names_come_back_whole(tmp_path, mesh):
    """Exodus names are 32 characters unless the file says more: a longer node-set name
    widens them (it was cut to 32, as no other name was that long)."""
    name = "nodes of the inlet pressure boundary condition"  # 46 characters
    m = mesh.replace(node_sets=[(name, [1, 2])])
    for ext in ("exo", "vtu"):
        jtet.save(m, tmp_path / f"m.{ext}")
        assert jtet.load(tmp_path / f"m.{ext}").node_sets[0].name == name


@pytest.mark.parametrize("ext", ["msh", "mesh", "xdmf", "node", "vol"])
def test_other_formats_say_they_drop_them(tmp_path, mesh, ext):
    m = mesh.replace(region=np.ones(mesh.n_tets, np.int64), node_sets=[("probe", [1, 2])])
    with pytest.warns(UserWarning, match=r"no node sets; not saved: 1 node set\(s\) \(probe\)"):
        jtet.save(m, tmp_path / f"m.{ext}")


def test_stats_lists_the_groups(capsys):
    """``jtet stats --groups``: what each group of the file became, with its size (the
    Exodus fixture: two blocks, a side set, a node set; counted here with NumPy)."""
    import json
    from pathlib import Path

    from jtet.cli import main

    path = Path(__file__).parent / "data" / "exodus_classic.exo"
    mesh = jtet.load(path)
    assert main(["stats", str(path), "--groups", "--json"]) == 0
    groups = json.loads(capsys.readouterr().out)["groups"]
    x = mesh.points[mesh.tets].mean(axis=1)[:, 0]
    assert groups == [
        {"kind": "region", "label": 10, "name": "left", "count": int((x < 0.5).sum())},
        {"kind": "region", "label": 20, "name": "right", "count": int((x >= 0.5).sum())},
        {"kind": "surface", "label": 7, "name": "wall", "count": len(mesh.protected_faces)},
        {"kind": "node set", "label": 4, "name": "probe", "count": 2},
    ]
    assert main(["stats", str(path), "--groups"]) == 0
    text = capsys.readouterr().out
    assert "node set  4      probe  2 vertices" in text
