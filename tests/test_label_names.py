"""Gmsh physical names (``TetMesh.label_names``): read from .msh files, kept by every
operation, written back to Gmsh and VTK files, read again by Gmsh itself."""

import pickle

import numpy as np
import pytest
from helpers import gmsh_model, named_ball_in_box

import jtet
from jtet.cli import main

gmsh = pytest.importorskip("gmsh")


def _gmsh_names(path):
    with gmsh_model():
        gmsh.open(str(path))
        return {(d, t): gmsh.model.getPhysicalName(d, t) for d, t in gmsh.model.getPhysicalGroups()}


NAMES = {(2, 10): "walls", (3, 1): "ball", (3, 2): "box"}


def test_names_round_trip_through_improve_and_formats(tmp_path):
    src = tmp_path / "in.msh"
    named_ball_in_box(src)
    mesh = jtet.load(src)
    assert dict(mesh.label_names) == NAMES
    assert sorted(set(mesh.region.tolist())) == [1, 2]
    # every operation keeps them: a run, a regions run, a pickle
    for out in (jtet.improve(mesh).mesh, jtet.improve(mesh, regions=[1]).mesh):
        assert dict(out.label_names) == NAMES
    assert dict(pickle.loads(pickle.dumps(mesh)).label_names) == NAMES
    # Gmsh reads jtet's .msh with the names; VTK files keep them as field data
    out = tmp_path / "out.msh"
    assert main(["improve", str(src), str(out), "-q"]) == 0
    assert _gmsh_names(out) == NAMES
    for ext in (".vtu", ".vtk"):
        assert main(["convert", str(out), str(tmp_path / f"c{ext}"), "-q"]) == 0
        assert dict(jtet.load(tmp_path / f"c{ext}").label_names) == NAMES
    assert main(["convert", str(tmp_path / "c.vtu"), str(tmp_path / "back.msh"), "-q"]) == 0
    assert _gmsh_names(tmp_path / "back.msh") == NAMES


def test_names_of_entity_tags_are_not_taken(tmp_path):
    # Mesh.SaveAll without physical volumes: the regions are the volume entities, which
    # the names of physical groups do not name; the surfaces' physical names stay
    src = tmp_path / "all.msh"
    named_ball_in_box(src, save_all_entities=True)
    mesh = jtet.load(src)
    assert all(dim == 2 for dim, _ in mesh.label_names)


def test_medit_and_tetgen_outputs_warn_that_names_are_dropped(tmp_path):
    src = tmp_path / "in.msh"
    named_ball_in_box(src)
    mesh = jtet.load(src)
    for name in ("o.mesh", "o.node"):
        with pytest.warns(UserWarning, match=r"3 label name\(s\)"):
            jtet.save(mesh, tmp_path / name)


def test_stats_by_region_shows_the_names(tmp_path, capsys):
    src = tmp_path / "in.msh"
    named_ball_in_box(src)
    assert main(["stats", str(src), "--by-region"]) == 0
    head = capsys.readouterr().out.splitlines()[1]
    assert "region 1 (ball)" in head and "region 2 (box)" in head


def test_label_names_are_checked():
    mesh = jtet.demo_mesh("two_regions")
    assert dict(mesh.replace(label_names={(3, 1): "a"}).label_names) == {(3, 1): "a"}
    for bad in ({(4, 1): "a"}, {(3,): "a"}, {(3, 1): ""}, {(3, 1): 5}, {(3, True): "a"}, [1]):
        with pytest.raises(jtet.MeshInputError, match="label_names"):
            mesh.replace(label_names=bad)
    names = mesh.replace(label_names={(3, 2): "b", (3, 1): "a"}).label_names
    assert list(names) == [(3, 1), (3, 2)]  # sorted
    with pytest.raises(TypeError):
        names[(3, 3)] = "c"  # read-only


def test_damaged_vtk_names_are_ignored_with_a_warning(tmp_path):
    import json

    named = {(3, 1): "Fluß 流体", (2, 7): "a b"}  # Gmsh names are UTF-8
    mesh = jtet.demo_mesh("two_regions").replace(label_names=named)
    for ext in (".vtu", ".vtk"):
        jtet.save(mesh, tmp_path / f"u{ext}")
        assert dict(jtet.load(tmp_path / f"u{ext}").label_names) == named
    grid = mesh.to_pyvista()
    assert dict(jtet.TetMesh.from_pyvista(grid).label_names) == named

    def with_names(value):
        grid.field_data["jtet:label_names"] = value
        return jtet.TetMesh.from_pyvista(grid)

    entries = [[3, 1, "ok"], [4, 1, "dim"], [3, "1", "label"], [3, 2, ""], [3, 3], "x"]
    text = json.dumps(entries).encode()
    with pytest.warns(UserWarning, match="5 entr"):
        assert dict(with_names(np.frombuffer(text, np.uint8)).label_names) == {(3, 1): "ok"}
    for damaged in (np.frombuffer(b"\xc8[", np.uint8), np.frombuffer(b"[1,", np.uint8),
                    np.frombuffer(b"{}", np.uint8), np.array([1.5, 2.0])):  # fmt: skip
        with pytest.warns(UserWarning, match="unreadable"):
            assert len(with_names(damaged).label_names) == 0


def test_cli_regions_by_name(tmp_path, capsys):
    src = tmp_path / "in.msh"
    named_ball_in_box(src)
    by_name, by_label = tmp_path / "a.vtu", tmp_path / "b.vtu"
    assert (
        main(["improve", str(src), str(by_name), "--regions", "ball", "--ops", "edge", "-q"]) == 0
    )
    assert main(["improve", str(src), str(by_label), "--regions", "1", "--ops", "edge", "-q"]) == 0
    a, b = jtet.load(by_name), jtet.load(by_label)
    assert np.array_equal(a.tets, b.tets) and np.array_equal(a.points, b.points)
    # the API and options files take the names too
    api = jtet.improve(jtet.load(src), regions=["ball"], ops=("edge",)).mesh
    assert np.array_equal(api.tets, b.tets)
    (tmp_path / "o.yaml").write_text("regions: [ball]\nops: [edge]\n")
    assert jtet.load_options(tmp_path / "o.yaml").regions == ("ball",)
    by_file = tmp_path / "d.vtu"
    assert (
        main(["improve", str(src), str(by_file), "--options", str(tmp_path / "o.yaml"), "-q"]) == 0
    )
    assert np.array_equal(jtet.load(by_file).tets, b.tets)
    capsys.readouterr()
    assert main(["improve", str(src), str(tmp_path / "c.vtu"), "--regions", "fluid,2"]) == 2
    err = capsys.readouterr().err
    assert "no region named 'fluid'" in err and "ball (1), box (2)" in err
    assert not (tmp_path / "c.vtu").exists()


def test_relabel_moves_regions_and_their_names(tmp_path, capsys):
    """``TetMesh.relabel`` / ``--relabel``: an unlabelled mesh (region 0, which Gmsh files
    cannot hold as a physical volume) gets a label Gmsh itself then reads as a physical
    volume; regions merge, names follow their labels, unknown labels are refused."""
    path = tmp_path / "named.msh"
    named_ball_in_box(path)
    mesh = jtet.load(path)
    merged = mesh.relabel({1: 2})
    assert set(np.unique(merged.region).tolist()) == {2}
    assert merged.label_names[(3, 2)] == "box" and (3, 1) not in merged.label_names
    moved = mesh.relabel({1: 5, 2: 1})
    np.testing.assert_array_equal(moved.region, np.where(mesh.region == 1, 5, 1))
    assert moved.label_names[(3, 5)] == "ball" and moved.label_names[(3, 1)] == "box"
    assert moved.label_names[(2, 10)] == "walls"  # other dimensions keep their names
    with pytest.raises(jtet.MeshInputError, match="no tet has region 9"):
        mesh.relabel({9: 1})
    plain = jtet.demo_mesh()
    src, out = tmp_path / "plain.vtu", tmp_path / "plain.msh"
    jtet.save(plain, src)
    assert main(["convert", str(src), str(out), "--relabel", "0:3", "-q"]) == 0
    with gmsh_model():  # Gmsh finds every tet in physical volume 3
        gmsh.open(str(out))
        tags = gmsh.model.getEntitiesForPhysicalGroup(3, 3)
        n = sum(len(gmsh.model.mesh.getElements(3, t)[1][0]) for t in tags)
    assert n == plain.n_tets
    assert main(["convert", str(src), str(out), "--relabel", "4:3", "-q"]) == 2
    assert "--relabel: no tet has region 4" in capsys.readouterr().err
    out2 = tmp_path / "improved.vtu"
    args = ["improve", str(src), str(out2), "--relabel", "0:2", "--max-passes", "1", "-q"]
    assert main([*args, "--perturb", "0"]) == 0
    assert (jtet.load(out2).region == 2).all()
