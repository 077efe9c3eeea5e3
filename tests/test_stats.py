"""mesh_stats / format_table on meshes with known angles and qualities."""

import json
import math

import numpy as np
import pytest
from helpers import REGULAR_TET, delaunay_mesh, grid_mesh

import jtet
from jtet._stats import LARGE_ANGLES, SMALL_ANGLES, format_table, mesh_stats

REG = REGULAR_TET[[1, 0, 2, 3]]  # positively oriented


def test_single_regular_tet():
    s = mesh_stats(jtet.TetMesh(REG, [[0, 1, 2, 3]]))
    a = math.degrees(math.acos(1 / 3))
    assert s.n_tets == 1 and s.n_points == 4
    assert s.min_dihedral == pytest.approx(a, abs=1e-10)
    assert s.max_dihedral == pytest.approx(a, abs=1e-10)
    assert all(v == 0 for v in s.small_dihedral.values())
    assert all(v == 0 for v in s.large_dihedral.values())
    assert set(s.quality_min) == set(jtet.MEASURES)
    for name in jtet.MEASURES:
        assert s.quality_min[name] == pytest.approx(1.0, abs=1e-12)
        assert s.quality_mean[name] == pytest.approx(1.0, abs=1e-12)
        assert s.quality_hist[name].sum() == 1 and s.quality_hist[name][-1] == 1
    # edge 2 sqrt 2: V = a^3 / (6 sqrt 2) = 8/3
    assert s.volume == pytest.approx(8 / 3, rel=1e-14)
    assert s.n_inverted == 0 and s.n_degenerate == 0
    assert s.dihedral_hist.shape == (180,) and s.dihedral_hist[70] == 6
    assert s.dihedral_hist.sum() == 6


def test_kuhn_grid():
    # every Kuhn/Freudenthal tet of a cube: dihedral angles 45, 45, 60, 90, 90, 90;
    # edges 1, 1, 1, sqrt2, sqrt2, sqrt3; V = 1/6; faces 1/2, 1/2, sqrt2/2, sqrt2/2;
    # circumradius sqrt3/2 (the cube's). All tets are congruent up to a reflection.
    n = 3
    mesh = grid_mesh(n)
    m = 6 * n**3
    s = mesh_stats(mesh)
    assert s.n_tets == m and s.n_points == (n + 1) ** 3
    assert s.min_dihedral == pytest.approx(45, abs=1e-9)
    assert s.max_dihedral == pytest.approx(90, abs=1e-9)
    assert s.small_dihedral == {a: 0 for a in SMALL_ANGLES}
    assert s.large_dihedral == {a: 0 for a in LARGE_ANGLES}
    h = s.dihedral_hist
    # exact angles can land on either side of a bin edge through round-off
    assert h[44:46].sum() == 2 * m and h[59:61].sum() == m and h[89:91].sum() == 3 * m
    assert h.sum() == 6 * m
    expected = {
        "min_sine": math.sin(math.radians(45)) / (2 * math.sqrt(2) / 3),  # = 3/4
        "radius_ratio": 3 * (0.5 / (1 + math.sqrt(2))) / (math.sqrt(3) / 2),
        "vol_length": math.sqrt(2) / (10 / 6) ** 1.5,
        "mean_ratio": 12 * 0.5 ** (2 / 3) / 10,
    }
    for name, q in expected.items():
        assert s.quality_min[name] == pytest.approx(q, rel=1e-12), name
        assert s.quality_mean[name] == pytest.approx(q, rel=1e-12), name
    assert s.volume == pytest.approx(1.0, rel=1e-13)
    assert s.n_inverted == 0 and s.n_degenerate == 0


def test_counts_match_numpy(rng):
    mesh = delaunay_mesh(300, seed=4)
    s = mesh_stats(mesh, measures=["vol_length"])
    angles, lo, hi = jtet._quality.tet_dihedrals(mesh.points, mesh.tets)
    for a in SMALL_ANGLES:
        assert s.small_dihedral[a] == int((lo < a).sum())
    for a in LARGE_ANGLES:
        assert s.large_dihedral[a] == int((hi > a).sum())
    assert s.small_dihedral[5] > 0  # random Delaunay meshes have slivers
    q = mesh.quality("vol_length")
    assert s.quality_min == {"vol_length": q.min()}
    assert s.quality_mean["vol_length"] == pytest.approx(q.mean(), rel=1e-14)
    assert s.quality_hist["vol_length"].sum() == mesh.n_tets
    assert s.dihedral_hist.sum() == 6 * mesh.n_tets
    assert s.volume == pytest.approx(1.0, rel=1e-12)


def test_precomputed_per_tet_values_give_the_same_stats():
    # improve hands mesh_stats the per-tet values it computed anyway; a given tuple must
    # be what the statistics read (a doctored one shows), and an honest one changes nothing
    mesh = delaunay_mesh(300, seed=4)
    per_tet = jtet._quality.tet_all_measures(mesh.points, mesh.tets)
    assert mesh_stats(mesh, per_tet=per_tet).as_dict() == mesh_stats(mesh).as_dict()
    angles, lo, hi, qs = per_tet
    doctored = (angles, lo + 90.0, hi, qs)
    assert mesh_stats(mesh, per_tet=doctored).min_dihedral == pytest.approx(lo.min() + 90.0)


def test_inverted_and_degenerate_counts():
    mesh = grid_mesh(2)
    tets = mesh.tets.copy()
    tets[[3, 7]] = tets[[3, 7]][:, [1, 0, 2, 3]]
    s = mesh_stats(jtet.TetMesh(mesh.points, tets))
    assert s.n_inverted == 2 and s.n_degenerate == 0
    assert all(v < 0 for v in s.quality_min.values())
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1]])
    s = mesh_stats(jtet.TetMesh(pts, [[0, 1, 2, 3], [0, 1, 2, 4]]))
    assert s.n_degenerate == 1 and s.quality_min["min_sine"] == 0.0


def test_unknown_measure():
    with pytest.raises(jtet.JtetError, match="unknown quality measure"):
        mesh_stats(grid_mesh(1), measures=["nope"])


def test_as_dict_and_table():
    before = mesh_stats(delaunay_mesh(100, seed=5))
    after = mesh_stats(grid_mesh(2))
    d = json.loads(json.dumps(before.as_dict()))
    assert d["n_tets"] == before.n_tets and len(d["dihedral_hist"]) == 180
    assert d["small_dihedral"]["10"] == before.small_dihedral[10]
    assert len(d["quality_hist"]["min_sine"]) == 100
    table = format_table(before, after, time_s=1.5)
    lines = table.splitlines()
    assert "before" in lines[0] and "after" in lines[0]
    for row in ("tets", "min dihedral", "max dihedral", "< 10", "> 170", "worst min_sine",
                "mean mean_ratio", "inverted", "time (s)"):  # fmt: skip
        assert any(row in line for line in lines), row
    tets_row = next(line for line in lines if line.startswith("tets "))
    assert tets_row.split()[1:] == [str(before.n_tets), str(after.n_tets)]
    assert "1.500" in lines[-1]
    single = format_table(before)
    assert "after" not in single and "time" not in single


def test_table_of_several_meshes():
    meshes = [grid_mesh(1), grid_mesh(2), delaunay_mesh(60, seed=3)]
    stats = [mesh_stats(m) for m in meshes]
    lines = format_table(*stats).splitlines()
    assert lines[0].split() == ["mesh", "1", "mesh", "2", "mesh", "3"]
    tets_row = next(line for line in lines if line.startswith("tets "))
    assert tets_row.split()[1:] == [str(m.n_tets) for m in meshes]
    named = format_table(*stats, labels=("gmsh", "tetgen", "jtet")).splitlines()
    assert named[0].split() == ["gmsh", "tetgen", "jtet"]
    # a None column is left out (a run without an "after")
    assert format_table(stats[0], None) == format_table(stats[0])
    with pytest.raises(ValueError, match="at least one"):
        format_table()


def test_plot_of_a_measure_the_stats_lack(tmp_path):
    from jtet._report import plot_stats

    s = mesh_stats(grid_mesh(1), measures=["min_sine"])
    with pytest.raises(ValueError, match="radius_ratio"):
        plot_stats([s], tmp_path / "h.png", ["grid"], "radius_ratio")
    assert list(tmp_path.iterdir()) == []
    plot_stats([s, s, s], tmp_path / "h.png", measure="min_sine")
    assert (tmp_path / "h.png").read_bytes()[:4] == b"\x89PNG"


def test_worst_tets_against_numpy():
    from jtet._quality import tet_dihedrals
    from jtet._stats import worst_tets

    mesh = delaunay_mesh(300, seed=11)
    rows = worst_tets(mesh, 7, "min_sine")
    q = mesh.quality("min_sine")
    # the 7 lowest qualities, worst first (a stable sort keeps ties in tet order)
    assert [r["tet"] for r in rows] == np.argsort(q, kind="stable")[:7].tolist()
    _, lo, hi = tet_dihedrals(mesh.points, mesh.tets)
    # a vertex on a face of one tet is on the boundary: it never moves (boundary fixed)
    faces = np.sort(mesh.tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), 1)
    uniq, count = np.unique(faces, axis=0, return_counts=True)
    on_boundary = np.zeros(mesh.n_points, bool)
    on_boundary[uniq[count == 1].reshape(-1)] = True
    for r in rows:
        t = r["tet"]
        assert r["quality"] == q[t] and r["min_dihedral"] == lo[t] and r["max_dihedral"] == hi[t]
        np.testing.assert_allclose(r["centroid"], mesh.points[mesh.tets[t]].mean(axis=0))
        assert r["fixed_vertices"] == int(on_boundary[mesh.tets[t]].sum())
        assert r["region"] == mesh.region[t]
    assert len(worst_tets(mesh, 10**6)) == mesh.n_tets and worst_tets(mesh, 0) == []
    json.dumps(rows)  # plain Python values


def test_worst_tets_of_a_mesh_without_topology():
    from jtet._stats import worst_tets

    # a face in three tets: no topology, but the worst tets are still listed
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [1, 1, 1]])
    mesh = jtet.TetMesh(pts, [[0, 1, 2, 3], [0, 2, 1, 4], [0, 1, 2, 5]])
    rows = worst_tets(mesh, 2)
    assert len(rows) == 2 and all(r["fixed_vertices"] is None for r in rows)


def test_region_stats_against_each_region_alone():
    # reference: each region as a mesh of its own, built from plain arrays
    from jtet._stats import MAX_REGION_COLUMNS, region_stats

    mesh = grid_mesh(4, perturb=0.5, seed=3, two_regions=True)
    by_region = region_stats(mesh)
    assert sorted(by_region) == sorted(set(mesh.region.tolist())) == [0, 1]
    for label, got in by_region.items():
        tets = mesh.tets[mesh.region == label]
        used, local = np.unique(tets, return_inverse=True)
        alone = jtet.TetMesh(mesh.points[used], local.reshape(-1, 4))
        want = mesh_stats(alone)
        assert got.as_dict() == want.as_dict()
    assert sum(s.n_tets for s in by_region.values()) == mesh.n_tets
    many = mesh.replace(region=np.arange(mesh.n_tets) % (MAX_REGION_COLUMNS + 1))
    with pytest.raises(jtet.JtetError, match="17 regions"):
        region_stats(many)


def test_cli_stats_by_region(tmp_path, capsys):
    from jtet.cli import main

    mesh = jtet.demo_mesh("two_regions")
    path = tmp_path / "two.vtu"
    jtet.save(mesh, path)
    assert main(["stats", str(path), "--by-region"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split() == ["whole", "mesh", "region", "1", "region", "2"]
    tets = next(line for line in lines if line.startswith("tets "))
    assert tets.split()[1:] == ["1928", "910", "1018"]
    assert main(["stats", str(path), "--by-region", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["regions"]["2"]["n_tets"] == 1018 and d["n_tets"] == 1928
    # several files: a column per file, then one per region of it
    assert main(["stats", str(path), str(path), "--by-region"]) == 0
    head = capsys.readouterr().out.splitlines()[2]
    # (the same name twice: the paths as given are the labels)
    assert head.count(f"{path}: region 1") == 2 and head.count(": region 2") == 2


def test_history_curve_follows_the_run(tmp_path):
    """The run panel's points are the history's: cumulative seconds (NumPy's cumsum),
    the input's angles first and the output's last (the history tracks the measures the
    statistics recompute: equal to rounding)."""
    from jtet._report import history_curve

    mesh = delaunay_mesh(120, seed=3)
    result = jtet.improve(mesh, max_passes=3, perturb=1)
    curve = history_curve(result.history, result.stats_before)
    n = len(result.history)
    assert n > 0 and all(len(curve[k]) == n + 1 for k in ("seconds", "min_dihedral"))
    np.testing.assert_allclose(
        curve["seconds"][1:], np.cumsum([e["seconds"] for e in result.history])
    )
    assert curve["min_dihedral"][0] == result.stats_before.min_dihedral
    assert curve["max_dihedral"][0] == result.stats_before.max_dihedral
    assert curve["min_dihedral"][-1] == pytest.approx(result.stats_after.min_dihedral, abs=1e-9)
    assert curve["max_dihedral"][-1] == pytest.approx(result.stats_after.max_dihedral, abs=1e-9)
    assert list(curve["op"]) == [e["op"] for e in result.history]
    assert list(curve["kept"]) == [e["successes"] > 0 for e in result.history]
    result.plot(tmp_path / "run.png")
    assert (tmp_path / "run.png").read_bytes()[:4] == b"\x89PNG"


def test_figure_of_a_run_without_operations(tmp_path):
    """A goal that holds from the start runs no operation: the figure has the
    histograms alone."""
    from jtet._report import history_curve, plot_run

    result = jtet.improve(grid_mesh(2), goal_min_dihedral=1.0)
    assert result.status == "goal reached" and result.history == []
    assert history_curve(result.history, result.stats_before) is None
    plot_run(result, tmp_path / "run.svg")
    assert b"<svg" in (tmp_path / "run.svg").read_bytes()[:400]
    assert [p.name for p in tmp_path.iterdir()] == ["run.svg"]
