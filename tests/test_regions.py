"""Options.regions: improving some regions of a mesh and leaving the others exactly as
they are (tets, vertex coordinates, the faces between)."""

import json

import numpy as np
import pytest

import jtet
from jtet._invariants import InvariantChecker
from jtet._topology import TET_FACES
from jtet.cli import main


@pytest.fixture(scope="module")
def mesh():
    # regions 1 (910 tets) and 2 (1018 tets) meet at the plane z = 0.45
    return jtet.demo_mesh("two_regions")


def _faces(tets: np.ndarray) -> set:
    return {tuple(f) for f in np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1).tolist()}


@pytest.mark.parametrize("boundary", ["fixed", "slide"])
@pytest.mark.parametrize("selected", [1, 2])
def test_other_regions_stay_exactly(mesh, selected, boundary):
    r = jtet.improve(mesh, regions=[selected], boundary=boundary, check=True)
    assert r.status == "converged"
    out = r.mesh
    assert out.is_valid().ok
    frozen = mesh.region != selected
    k = int(frozen.sum())
    # the other region's tets come first, as they were, and none of their vertices moved
    # (the interface is flat: with boundary "slide" its vertices would otherwise slide)
    assert np.array_equal(out.tets[:k], mesh.tets[frozen])
    assert np.array_equal(out.region[:k], mesh.region[frozen])
    verts = np.unique(mesh.tets[frozen])
    assert np.array_equal(out.points[verts], mesh.points[verts])
    assert (out.region[k:] == selected).all()
    # the selected region was improved: its worst tet (demo: ~0.015) rose
    before = mesh.quality("biased_min_sine")[~frozen].min()
    after = out.quality("biased_min_sine")[k:].min()
    assert after > before + 0.2
    # boundary, interface, region volumes: raises InvariantError if any changed
    InvariantChecker(mesh).check(out, 0, "regions")
    # the cut's protections were the run's own: none is left in the output
    assert len(out.protected_edges) == len(out.protected_vertices) == 0
    # the whole-mesh statistics, and a note that the worst tet is in the other region
    assert r.stats_before.n_tets == mesh.n_tets and r.stats_after.n_tets == out.n_tets
    assert r.stats_after.min_dihedral == pytest.approx(jtet.stats(out).min_dihedral)
    assert any("left alone" in n for n in r.notes)
    # and the selected tets' own statistics, in a column of their own
    sel_before, sel_after = r.selected_stats
    assert sel_before.n_tets == (~frozen).sum() and sel_after.n_tets == out.n_tets - k
    assert sel_after.quality_min["biased_min_sine"] == pytest.approx(after)
    assert f"after (regions {selected})" in r.summary().splitlines()[0]
    d = r.as_dict()
    assert d["selected_stats_after"]["n_tets"] == sel_after.n_tets


def test_all_regions_is_a_plain_run(mesh):
    a = jtet.improve(mesh, ops=("edge", "face"), regions=(1, 2))
    b = jtet.improve(mesh, ops=("edge", "face"))
    assert np.array_equal(a.mesh.tets, b.mesh.tets)
    assert np.array_equal(a.mesh.points, b.mesh.points)
    assert a.options.regions == (1, 2)
    assert a.selected_stats is None and "selected_stats_after" not in a.as_dict()


def test_protected_faces_on_the_cut_keep_their_labels(mesh):
    # the interface faces, protected with label 7, and a protected vertex in region 2
    faces1, faces2 = _faces(mesh.tets[mesh.region == 1]), _faces(mesh.tets[mesh.region == 2])
    interface = np.array(sorted(faces1 & faces2))
    inner2 = np.setdiff1d(np.unique(mesh.tets[mesh.region == 2]), interface)
    tagged = mesh.replace(
        protected_faces=interface,
        protected_face_labels=np.full(len(interface), 7),
        protected_vertices=inner2[:1],
        protected_vertex_labels=[5],
    )
    r = jtet.improve(tagged, regions=[2], ops=("edge", "face", "smooth"), check=True)
    out = r.mesh
    assert r.status == "converged"
    assert np.array_equal(out.protected_faces, tagged.protected_faces)
    assert (out.protected_face_labels == 7).all()
    assert out.protected_vertices.tolist() == inner2[:1].tolist()
    assert out.protected_vertex_labels.tolist() == [5]
    assert np.array_equal(out.points[inner2[0]], mesh.points[inner2[0]])


def test_unknown_regions_are_refused(mesh):
    with pytest.raises(jtet.MeshInputError, match=r"no region 3, 9 .*its regions are 1, 2"):
        jtet.improve(mesh, regions=[1, 3, 9])


@pytest.mark.parametrize("bad", [[], [1.5], [True], [""], b"1", [None]])
def test_regions_option_is_checked(bad):
    with pytest.raises(jtet.JtetError, match="regions must be"):
        jtet.Options(regions=bad)


def test_regions_option_forms(tmp_path):
    assert jtet.Options(regions=[3, 1, 3]).regions == (1, 3)
    # names (of Gmsh physical volumes, resolved by improve) after the labels, in order
    assert jtet.Options(regions=["solid", 2, "fluid", "solid"]).regions == (2, "solid", "fluid")
    assert jtet.Options(regions="fluid").regions == ("fluid",)
    assert jtet.Options(regions=np.int64(2)).regions == (2,)
    assert jtet.Options().as_dict()["regions"] is None
    path = tmp_path / "o.yaml"
    path.write_text("regions: [2, 1]\n")
    assert jtet.load_options(path).regions == (1, 2)


def test_cli_regions(tmp_path, mesh):
    src, out, report = tmp_path / "in.vtu", tmp_path / "out.vtu", tmp_path / "r.json"
    jtet.save(mesh, src)
    code = main(["improve", str(src), str(out), "--regions", "2", "--ops", "edge,face",
                 "--report", str(report), "-q"])  # fmt: skip
    assert code == 0
    assert json.loads(report.read_text())["options"]["regions"] == [2]
    written = jtet.load(out)
    frozen = mesh.region == 1
    assert np.array_equal(written.tets[: int(frozen.sum())], mesh.tets[frozen])
    # the report runs again with the same regions: the same output
    again = tmp_path / "again.vtu"
    assert main(["improve", str(src), str(again), "--options", str(report), "-q"]) == 0
    assert np.array_equal(jtet.load(again).tets, written.tets)


@pytest.mark.parametrize("flag", ["1,,a", "", "2,"])
def test_cli_bad_regions(tmp_path, mesh, flag, capsys):
    src = tmp_path / "in.vtu"
    jtet.save(mesh, src)
    with pytest.raises(SystemExit) as e:
        main(["improve", str(src), str(tmp_path / "o.vtu"), "--regions", flag])
    assert e.value.code == 2
    assert "--regions" in capsys.readouterr().err


def test_cli_unknown_region(tmp_path, mesh, capsys):
    src = tmp_path / "in.vtu"
    jtet.save(mesh, src)
    assert main(["improve", str(src), str(tmp_path / "o.vtu"), "--regions", "4"]) == 2
    err = capsys.readouterr().err
    assert "no region 4" in err and not (tmp_path / "o.vtu").exists()
    # a word is a region name (Gmsh physical names): this mesh names none
    assert main(["improve", str(src), str(tmp_path / "o.vtu"), "--regions", "x"]) == 2
    err = capsys.readouterr().err
    assert "no region named 'x'" in err and not (tmp_path / "o.vtu").exists()


def test_regions_of_a_mesh_with_inverted_tets_are_refused(mesh):
    # fuzz (seed 3106): the part's run sees nothing of the tets around it; where tets
    # overlap, a flip made a face that an outside tet has (a face in three tets)
    from jtet._predicates import orient3d_tets

    t = mesh.tets[0]
    points = mesh.points.copy()
    p = points[t]
    points[t[0]] = p[0] + 2.2 * ((p[1] + p[2] + p[3]) / 3 - p[0])  # through its opposite face
    bent = mesh.replace(points=points)
    assert (orient3d_tets(bent.points, bent.tets) <= 0).any()
    with pytest.raises(jtet.MeshInputError, match="inverted or degenerate tet"):
        jtet.improve(bent, regions=[1])
    assert jtet.improve(bent, regions=[1, 2], ops=("edge",)).status == "converged"


def test_batch_table_shows_the_part(tmp_path, mesh, capsys):
    src, outdir = tmp_path / "two.vtu", tmp_path / "out"
    outdir.mkdir()
    jtet.save(mesh, src)
    assert main(["improve", str(src), "--out-dir", str(outdir), "--regions", "2",
                 "--ops", "edge,face"]) == 0  # fmt: skip
    out = capsys.readouterr().out.splitlines()
    row = next(line for line in out if line.startswith(f"{src} *"))
    assert row.split()[2] == str((mesh.region == 2).sum())  # the part's tets before
    assert out[-1].startswith("* the tets the run could change")
