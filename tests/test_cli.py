"""The ``jtet`` command through ``jtet.cli.main``: improve, stats, demo, --help.

The full ``jtet improve IN OUT --report --plot`` run on the two-region demo mesh (1,928
tets) is made once (module fixture); other runs use one operation and one pass.
"""

import contextlib
import io
import json
import os
import re

import numpy as np
import pytest
import pyvista as pv

import jtet
from jtet.cli import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
CELL_ARRAYS = [f"quality_{m}" for m in jtet.MEASURES] + ["min_dihedral", "max_dihedral", "volume"]


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """The two-region demo mesh saved as .vtu (never modified by the tests)."""
    path = tmp_path_factory.mktemp("in") / "two_regions.vtu"
    jtet.save(jtet.demo_mesh("two_regions"), path)
    return path


@pytest.fixture(scope="module")
def improved(small, tmp_path_factory):
    """``jtet improve IN OUT --report R --plot H`` with default options, run once."""
    d = tmp_path_factory.mktemp("out")
    out, report, plot = d / "out.vtu", d / "report.json", d / "hist.png"
    before = small.read_bytes()
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main(["improve", str(small), str(out), "--report", str(report), "--plot", str(plot)])
    return dict(
        code=code,
        out=out,
        report=report,
        plot=plot,
        stdout=stdout.getvalue(),
        stderr=stderr.getvalue(),
        input_before=before,
    )


def _improve(*args) -> int:
    return main(["improve", *map(str, args)])


# --- jtet improve -----------------------------------------------------------------------


def test_improve_exit_code_and_input_untouched(improved, small):
    assert improved["code"] == 0, improved["stderr"]
    assert small.read_bytes() == improved["input_before"]


def test_improve_output_mesh(improved, small):
    src = jtet.load(small)
    out = jtet.load(improved["out"])
    assert src.n_tets == 1928
    assert out.is_valid().ok
    # no vertex is deleted; perturbation rounds may insert some (1-4 splits)
    assert out.n_points >= src.n_points
    assert set(np.unique(out.region)) == set(np.unique(src.region)) == {1, 2}
    # measured: worst min_sine 0.015 -> 0.56; the bound only asks for a real improvement
    assert out.quality().min() > src.quality().min()
    assert out.quality().min() > 0.3


def test_improve_output_cell_arrays(improved):
    grid = pv.read(improved["out"])
    for name in CELL_ARRAYS:
        assert name in grid.cell_data, name
        assert len(grid.cell_data[name]) == grid.n_cells
    mesh = jtet.load(improved["out"])
    assert grid.n_cells == mesh.n_tets
    # the arrays describe the tets as written (.vtu keeps float64: 1e-12 is round-off of
    # recomputing the same quantities)
    for m in jtet.MEASURES:
        np.testing.assert_allclose(
            grid.cell_data[f"quality_{m}"], jtet.quality(mesh, m), rtol=0, atol=1e-12
        )
    np.testing.assert_allclose(grid.cell_data["volume"], mesh.volumes, rtol=1e-12, atol=1e-15)
    s = jtet.stats(mesh)
    assert grid.cell_data["min_dihedral"].min() == pytest.approx(s.min_dihedral, abs=1e-9)
    assert grid.cell_data["max_dihedral"].max() == pytest.approx(s.max_dihedral, abs=1e-9)
    lo, hi = grid.cell_data["min_dihedral"], grid.cell_data["max_dihedral"]
    assert (lo > 0).all() and (lo <= hi).all() and (hi < 180).all()


def test_improve_report(improved, small):
    rep = json.loads(improved["report"].read_text())
    assert {"status", "history", "stats_before", "stats_after", "options"} <= set(rep)
    assert rep["status"] in ("converged", "max passes")
    assert rep["options"] == jtet.Options().as_dict()  # the CLI defaults are Options()
    assert rep["stats_before"] == jtet.stats(jtet.load(small)).as_dict()
    out = jtet.load(improved["out"])
    assert rep["stats_after"]["n_tets"] == out.n_tets
    # quality is recomputed from the written file: equal up to float64 round-off
    assert rep["stats_after"]["min_dihedral"] == pytest.approx(
        jtet.stats(out).min_dihedral, abs=1e-9
    )
    h = rep["history"]
    assert h and [e["op"] for e in h[:3]] == ["edge", "face", "smooth"]
    measure = rep["options"]["quality"]
    assert h[-1]["worst_quality"] == pytest.approx(out.quality(measure).min(), abs=1e-12)
    assert rep["stats_after"]["min_dihedral"] > rep["stats_before"]["min_dihedral"]


def test_improve_plot(improved):
    data = improved["plot"].read_bytes()
    assert data.startswith(PNG_MAGIC)
    assert len(data) > 10_000  # two histograms with axes and titles, not an empty image


def test_improve_outputs_have_a_new_files_mode(improved):
    # every output is written to a temporary file and renamed; the mesh, the report and
    # the plot must all get the mode any new file gets (umask), not mkstemp's 0600
    umask = os.umask(0)
    os.umask(umask)
    for name in ("out", "report", "plot"):
        assert improved[name].stat().st_mode & 0o777 == 0o666 & ~umask, name
    assert sorted(p.name for p in improved["out"].parent.iterdir()) == [
        "hist.png",
        "out.vtu",
        "report.json",
    ]


def test_improve_prints_summary(improved, small):
    rep = json.loads(improved["report"].read_text())
    out = improved["stdout"]
    assert f"{small} -> {improved['out']}" in out
    assert rep["status"] in out
    assert "before" in out and "after" in out
    assert "min dihedral (deg)" in out
    assert f"{rep['stats_before']['min_dihedral']:.3f}" in out
    assert f"{rep['stats_after']['min_dihedral']:.3f}" in out
    assert f"wrote {improved['report']}" in out and f"wrote {improved['plot']}" in out
    # progress lines go to stderr, never to stdout
    assert "pass 1 edge" in improved["stderr"]
    assert "[" not in out.splitlines()[0]
    # one line per perturbation attempt, with its kick and whether it was kept
    rounds = [e for e in rep["history"] if e["op"] == "perturb"]
    assert rounds, "the small mesh leaves work for the perturbation rounds"
    lines = [ln for ln in improved["stderr"].splitlines() if "] perturb " in ln]
    verdicts = [
        "kept" if e["successes"] else "gave up" if e["gave_up"] else "undone" for e in rounds
    ]
    expected = [f"perturb {e['kick']:7s} {v}" for e, v in zip(rounds, verdicts, strict=True)]
    assert len(lines) == len(expected)
    assert all(want in line for want, line in zip(expected, lines, strict=True))


def test_improve_options_reach_options(small, tmp_path, capsys):
    out, report = tmp_path / "o.vtu", tmp_path / "r.json"
    code = _improve(
        small,
        out,
        "--ops",
        "edge",
        "--max-ring",
        "5",
        "--quality",
        "radius_ratio",
        "--max-passes",
        "1",
        "--good-quality",
        "none",
        "--smooth-threshold",
        "0.4",
        "--min-improvement",
        "1e-6",
        "--report",
        report,
        "-q",
    )
    cap = capsys.readouterr()
    assert code == 0, cap.err
    assert cap.out == ""  # -q: nothing on stdout
    opts = json.loads(report.read_text())["options"]
    assert opts["ops"] == ["edge"]
    assert opts["max_ring"] == 5
    assert opts["quality"] == "radius_ratio"
    assert opts["max_passes"] == 1
    assert opts["good_quality"] is None
    assert opts["smooth_threshold"] == 0.4 and opts["min_improvement"] == 1e-6
    # the other options keep their defaults
    defaults = jtet.Options().as_dict()
    changed = {"ops", "max_ring", "quality", "max_passes", "good_quality"}
    changed |= {"smooth_threshold", "min_improvement"}
    assert {k: v for k, v in opts.items() if k not in changed} == {
        k: v for k, v in defaults.items() if k not in changed
    }
    h = json.loads(report.read_text())["history"]
    assert [(e["pass"], e["op"]) for e in h] == [(0, "edge")]
    assert h[0]["worst_quality"] == pytest.approx(
        jtet.quality(jtet.load(out), "radius_ratio").min(), abs=1e-12
    )


def test_improve_goals_stop_the_run(small, tmp_path, capsys):
    """--goal-min/max-dihedral reach the options; a goal the input already meets stops
    the run before its first pass (OUT is the input, exit 0); a bad goal exits 2."""
    out, report = tmp_path / "goal.vtu", tmp_path / "goal.json"
    args = ("--goal-min-dihedral", "0.001", "--goal-max-dihedral", "179.999")
    code = _improve(small, out, *args, "--report", report)
    cap = capsys.readouterr()
    assert code == 0, cap.err
    assert "(goal reached," in cap.out
    rep = json.loads(report.read_text())
    assert rep["status"] == "goal reached" and rep["history"] == []
    assert rep["options"]["goal_min_dihedral"] == 0.001
    assert rep["options"]["goal_max_dihedral"] == 179.999
    before, after = jtet.load(small), jtet.load(out)
    assert np.array_equal(before.tets, after.tets)
    assert np.array_equal(before.points, after.points)
    bad = tmp_path / "bad.vtu"
    assert _improve(small, bad, "--goal-max-dihedral", "200", "-q") == 2
    err = capsys.readouterr().err
    assert err.startswith("jtet: error:") and "goal_max_dihedral" in err
    assert not bad.exists()


def test_improve_feature_angle_reaches_the_flips(tmp_path, capsys):
    # two tets under a roof folded by 11.4 degrees along the boundary edge 0-1
    points = [[-1, 0, 0], [1, 0, 0], [0, -0.3, 0.03], [0, 0.3, 0.03], [0, 0, -0.6]]
    roof = jtet.TetMesh.from_arrays(np.array(points, float), [[0, 1, 2, 4], [0, 1, 3, 4]])
    src = tmp_path / "roof.vtu"
    jtet.save(roof, src)
    for angle, flipped in (("0", False), ("15", True)):
        out = tmp_path / f"out{angle}.vtu"
        code = _improve(src, out, "--ops", "edge", "--feature-angle", angle, "--check", "-q")
        assert code == 0, capsys.readouterr().err
        edges = {tuple(e) for e in jtet.load(out).topology.edges.tolist()}
        assert ((2, 3) in edges) == flipped and ((0, 1) in edges) != flipped


def test_improve_bad_option_exits_2(small, tmp_path, capsys):
    out = tmp_path / "o.vtu"
    # out of range for Options: JtetError -> exit 2 with one line naming the option
    assert _improve(small, out, "--max-ring", "20") == 2
    err = capsys.readouterr().err
    assert err.startswith("jtet: error:") and "max_ring" in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()
    # unknown operation: argparse rejects it (exit 2 through SystemExit)
    with pytest.raises(SystemExit) as e:
        _improve(small, out, "--ops", "edge,flip")
    assert e.value.code == 2
    assert "flip" in capsys.readouterr().err
    assert not out.exists()
    # --perturb takes a count or auto
    for bad in ("-1", "many", "1.5"):
        with pytest.raises(SystemExit) as e:
            _improve(small, out, "--perturb", bad)
        assert e.value.code == 2
        assert "expected a count >= 0 or 'auto'" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("value, expected", [("auto", "auto"), ("AUTO", "auto"), ("3", 3)])
def test_improve_perturb_flag(small, tmp_path, capsys, value, expected):
    report = tmp_path / "r.json"
    args = ("--ops", "edge", "--max-passes", "1", "--report", report, "-q")
    assert _improve(small, tmp_path / "o.vtu", "--perturb", value, *args) == 0
    rep = json.loads(report.read_text())
    assert rep["options"]["perturb"] == expected
    assert rep["perturb_rounds"] == (8 if expected == "auto" else 3)
    capsys.readouterr()


def test_improve_refuses_to_overwrite_input(tmp_path, capsys):
    path = tmp_path / "m.vtu"
    jtet.save(jtet.demo_mesh("two_regions"), path)
    original = path.read_bytes()
    (tmp_path / "sub").mkdir()
    link = tmp_path / "hard.vtu"
    link.hardlink_to(path)
    # the same file spelled three ways: same path, through "..", a hard link
    for out in (path, tmp_path / "sub" / ".." / "m.vtu", link):
        assert _improve(path, out, "--ops", "edge", "--max-passes", "1") == 2
        err = capsys.readouterr().err
        assert "--overwrite" in err and "is the input file" in err
        assert path.read_bytes() == original
    # with --overwrite the input is replaced by the improved mesh
    assert _improve(path, path, "--ops", "edge", "--max-passes", "1", "--overwrite", "-q") == 0
    assert path.read_bytes() != original
    m = jtet.load(path)
    assert m.quality().min() > jtet.demo_mesh("two_regions").quality().min()
    assert "quality_min_sine" in pv.read(path).cell_data


# --- jtet stats ---------------------------------------------------------------------------


def test_stats_prints_counts(small, capsys):
    assert main(["stats", str(small)]) == 0
    out = capsys.readouterr().out
    s = jtet.stats(jtet.load(small))
    assert s.n_tets == 1928
    lines = out.splitlines()
    assert lines[0].startswith(f"{small}: TetMesh(")
    assert "1928 tets" in lines[0]
    rows = {ln.split("  ")[0].strip(): ln.split()[-1] for ln in lines[1:] if "  " in ln}
    assert rows["tets"] == "1928"
    assert rows["points"] == str(s.n_points)
    assert rows["min dihedral (deg)"] == f"{s.min_dihedral:.3f}"
    assert rows["inverted tets"] == "0"
    assert lines[-1] == "valid"


def test_stats_json(small, capsys):
    assert main(["stats", str(small), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d == jtet.stats(jtet.load(small)).as_dict()


def test_stats_missing_file_exits_2(tmp_path, capsys):
    assert main(["stats", str(tmp_path / "nope.vtu")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jtet: error:") and "nope.vtu" in err


def _table_rows(out: str) -> dict[str, list[str]]:
    """Rows of a ``format_table`` in ``out``: name -> the columns' values."""
    rows = {}
    for ln in out.splitlines():
        if "  " in ln and not ln.startswith("-"):
            name, *values = [part.strip() for part in ln.split("  ") if part.strip()]
            rows[name] = values
    return rows


def test_stats_compares_meshes_side_by_side(small, improved, tmp_path, capsys):
    plot = tmp_path / "cmp.png"
    assert main(["stats", str(small), str(improved["out"]), "--plot", str(plot)]) == 0
    out = capsys.readouterr().out
    before, after = jtet.stats(jtet.load(small)), jtet.stats(jtet.load(improved["out"]))
    lines = out.splitlines()
    assert lines[0].startswith(f"{small}: TetMesh(")
    assert lines[1].startswith(f"{improved['out']}: TetMesh(")
    # the columns are named by the files, in the order given
    assert lines[2].split() == ["two_regions.vtu", "out.vtu"]
    rows = _table_rows(out)
    assert rows["tets"] == [str(before.n_tets), str(after.n_tets)]
    assert rows["min dihedral (deg)"] == [f"{before.min_dihedral:.3f}", f"{after.min_dihedral:.3f}"]
    assert f"{small}: valid" in lines and f"{improved['out']}: valid" in lines
    assert plot.read_bytes().startswith(PNG_MAGIC)
    assert lines[-1] == f"wrote {plot}"


def test_stats_json_of_several_meshes(small, improved, capsys):
    assert main(["stats", str(small), str(improved["out"]), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["file"] for r in rows] == [str(small), str(improved["out"])]
    for r, path in zip(rows, (small, improved["out"]), strict=True):
        assert r.pop("valid") is True
        assert r.pop("file") == str(path)
        assert r == jtet.stats(jtet.load(path)).as_dict()


def test_stats_columns_of_files_with_one_name(small, tmp_path, capsys):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a, b = tmp_path / "a" / "m.vtu", tmp_path / "b" / "m.vtu"
    for path in (a, b):
        path.write_bytes(small.read_bytes())
    assert main(["stats", str(a), str(b)]) == 0
    header = capsys.readouterr().out.splitlines()[2]
    assert header.split() == [str(a), str(b)]


def test_stats_one_bad_file_of_several(small, tmp_path, capsys):
    bad = tmp_path / "bad.vtu"
    bad.write_text("not a mesh")
    plot = tmp_path / "cmp.png"
    assert main(["stats", str(small), str(bad), "--plot", str(plot)]) == 2
    captured = capsys.readouterr()
    # the bad file is named, and nothing else is printed or written
    assert captured.out == ""
    assert captured.err.startswith("jtet: error:") and "bad.vtu" in captured.err
    assert not plot.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["bad.vtu"]


def test_stats_plot_of_one_mesh(small, tmp_path, capsys):
    plot = tmp_path / "one.svg"
    assert main(["stats", str(small), "--plot", str(plot), "--quality", "radius_ratio"]) == 0
    text = plot.read_text()
    # the legend names the file and the worst value of the chosen measure
    worst = jtet.stats(jtet.load(small)).quality_min["radius_ratio"]
    assert "radius_ratio" in text and f"worst {worst:.3f}" in text
    assert capsys.readouterr().out.splitlines()[-2] == "valid"


def test_stats_worst_tets(small, capsys):
    from jtet._stats import worst_tets

    assert main(["stats", str(small), "--worst", "3", "--quality", "min_sine"]) == 0
    lines = capsys.readouterr().out.splitlines()
    at = lines.index(f"{small}: the 3 worst tets by min_sine")
    expected = worst_tets(jtet.load(small), 3, "min_sine")
    body = lines[at + 3 : at + 6]
    assert [int(ln.split()[0]) for ln in body] == [r["tet"] for r in expected]
    assert body[0].split()[2] == f"{expected[0]['min_dihedral']:.2f}"
    assert main(["stats", str(small), "--worst", "2", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d.pop("worst") == worst_tets(jtet.load(small), 2)
    assert d == jtet.stats(jtet.load(small)).as_dict()
    assert main(["stats", str(small), "--worst", "-1"]) == 2
    assert "--worst must be >= 0" in capsys.readouterr().err


# --- jtet convert -------------------------------------------------------------------------


def test_convert_keeps_labels_through_formats(tmp_path, capsys):
    """Gmsh -> Medit -> VTK: the mesh, its regions and its labelled protected faces,
    edges and vertices arrive as they left (Medit keeps every one of them but the
    vertices' labels, VTK all)."""
    from helpers import delaunay_mesh

    m = delaunay_mesh(60, seed=3)
    mesh = m.replace(
        region=np.digitize(m.points[m.tets].mean(axis=1)[:, 0], [0.5]) + 1,
        protected_faces=m.tets[:5, :3],
        protected_face_labels=[11, 11, 12, 12, 13],
        protected_edges=m.tets[:4, [0, 3]],
        protected_edge_labels=[21, 22, 23, 24],
        protected_vertices=[3, 7],
    )
    src, mid, out = tmp_path / "a.msh", tmp_path / "b.mesh", tmp_path / "c.vtu"
    jtet.save(mesh, src)
    assert main(["convert", str(src), str(mid)]) == 0
    assert main(["convert", str(mid), str(out), "--quality-arrays"]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith(f"jtet: {mid} -> {out}  (TetMesh(")
    back = jtet.load(out)
    for name in ("points", "tets", "region", "protected_faces", "protected_face_labels",
                 "protected_edges", "protected_edge_labels", "protected_vertices"):  # fmt: skip
        np.testing.assert_array_equal(getattr(back, name), getattr(mesh, name), err_msg=name)
    assert set(CELL_ARRAYS) <= set(pv.read(out).cell_data)


def test_convert_refusals(small, tmp_path, capsys):
    out = tmp_path / "o.stl"
    assert main(["convert", str(tmp_path / "missing.vtu"), str(out)]) == 2
    # the output format is checked before the input is read
    assert "unknown mesh file extension '.stl'" in capsys.readouterr().err
    assert main(["convert", str(small), str(small)]) == 2
    assert "is the input file" in capsys.readouterr().err
    assert main(["convert", str(tmp_path / "missing.vtu"), str(tmp_path / "o.vtu")]) == 2
    assert "missing.vtu" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


# --- jtet demo ------------------------------------------------------------------------------

DEMO_FILES = ("demo_improved.vtu", "demo_report.json", "demo_histograms.png")


def _check_demo_dir(d):
    for name in DEMO_FILES:
        assert (d / name).is_file(), name
    rep = json.loads((d / "demo_report.json").read_text())
    assert rep["stats_before"]["n_tets"] == 6209
    assert rep["options"]["ops"] == ["edge"] and rep["options"]["max_passes"] == 1
    m = jtet.load(d / "demo_improved.vtu")
    assert m.n_tets == rep["stats_after"]["n_tets"]
    assert m.quality().min() > jtet.demo_mesh().quality().min()
    assert (d / "demo_histograms.png").read_bytes().startswith(PNG_MAGIC)


def test_demo_default_directory(tmp_path, monkeypatch, capsys):
    # one edge-removal pass: the outputs, not the full optimization, are tested here
    monkeypatch.chdir(tmp_path)
    assert main(["demo", "--ops", "edge", "--max-passes", "1"]) == 0
    out = capsys.readouterr().out
    assert "embedded demo mesh -> jtet-demo-out" in out
    assert "min dihedral (deg)" in out
    _check_demo_dir(tmp_path / "jtet-demo-out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["jtet-demo-out"]


def test_demo_out_option(tmp_path, capsys):
    d = tmp_path / "a" / "b"  # created with its parents
    assert main(["demo", "--out", str(d), "--ops", "edge", "--max-passes", "1", "-q"]) == 0
    assert capsys.readouterr().out == ""
    _check_demo_dir(d)
    assert sorted(p.name for p in d.iterdir()) == sorted(DEMO_FILES)


# --- --help ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv, expect",
    [
        ([], ["improve", "stats", "convert", "demo"]),
        (["improve"], ["--overwrite", "--report", "--plot", "--good-quality", "--ops"]),
        (["stats"], ["--json"]),
        (["demo"], ["--out", "--ops", "--max-passes"]),
    ],
)
def test_help(argv, expect, capsys):
    with pytest.raises(SystemExit) as e:
        main([*argv, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: jtet")
    for word in expect:
        assert word in out, word


def test_version(capsys, monkeypatch):
    # one line even on a narrow terminal (argparse's own version action wraps it); the
    # package's version is the installed distribution's
    from importlib import metadata

    monkeypatch.setenv("COLUMNS", "40")
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1
    assert out.startswith(f"jtet {jtet.__version__} (Python ")
    assert jtet.__version__ == metadata.version("jtet")
    for name in ("jax", "numpy", "meshio", "pytetwild"):
        assert f"{name} {metadata.version(name)}" in out


def test_console_command_ends_with_complete_outputs_and_its_code(small, tmp_path):
    # the installed ``jtet`` command runs cli.run(): main(), then os._exit without the
    # interpreter's teardown; everything main wrote must be there and complete
    import subprocess
    import sys

    out, report, plot = tmp_path / "o.vtu", tmp_path / "r.json", tmp_path / "h.png"
    args = ["improve", str(small), str(out), "--report", str(report), "--plot", str(plot),
            "--ops", "edge", "--max-passes", "1"]  # fmt: skip
    cmd = [
        sys.executable,
        "-c",
        "import sys; from jtet.cli import run; sys.argv[0] = 'jtet'; run()",
    ]
    done = subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "time (s)" in done.stdout  # the summary table, flushed before the exit
    assert json.loads(report.read_text())["stats_after"]
    assert plot.read_bytes().startswith(PNG_MAGIC)
    assert jtet.load(out).n_tets > 0
    bad = subprocess.run([*cmd, "stats", str(tmp_path / "missing.vtu")], capture_output=True,
                         text=True, timeout=600)  # fmt: skip
    assert bad.returncode == 2 and bad.stderr.startswith("jtet: error:")


def test_options_file_and_flags_over_it(small, tmp_path, capsys):
    first, again, report = tmp_path / "a.vtu", tmp_path / "b.vtu", tmp_path / "r.json"
    opts = tmp_path / "o.yaml"
    opts.write_text(
        "# a sweep's settings\nops: [edge, smooth]\nmax_ring: 5\nmax_passes: 1\nseed: 3\n"
    )
    # a flag given on the command line wins over the file
    assert (
        _improve(small, first, "--options", opts, "--max-ring", "6", "--report", report, "-q") == 0
    )
    used = json.loads(report.read_text())["options"]
    assert used["ops"] == ["edge", "smooth"] and used["max_passes"] == 1 and used["seed"] == 3
    assert used["max_ring"] == 6
    assert used["perturb"] == jtet.Options().perturb  # left out of the file: the default
    assert used["insert"] is True
    # a report runs again with exactly its options, to the same mesh
    again_report = tmp_path / "r2.json"
    assert _improve(small, again, "--options", report, "--report", again_report, "-q") == 0
    assert json.loads(again_report.read_text())["options"] == used
    a, b = jtet.load(first), jtet.load(again)
    np.testing.assert_array_equal(a.tets, b.tets)
    np.testing.assert_array_equal(a.points, b.points)
    capsys.readouterr()


def test_no_insert_flag_and_over_a_file(small, tmp_path, capsys):
    """``--no-insert`` reaches ``Options.insert`` and keeps the input's points;
    ``--insert`` wins over ``insert: false`` in an options file."""
    out, report = tmp_path / "o.vtu", tmp_path / "r.json"
    assert _improve(small, out, "--no-insert", "--perturb", "2", "--report", report, "-q") == 0
    assert json.loads(report.read_text())["options"]["insert"] is False
    assert jtet.load(out).n_points == jtet.load(small).n_points
    opts = tmp_path / "o.yaml"
    opts.write_text("insert: false\nmax_passes: 1\nperturb: 0\n")
    assert _improve(small, out, "--options", opts, "--report", report, "-q") == 0
    assert json.loads(report.read_text())["options"]["insert"] is False
    assert _improve(small, out, "--options", opts, "--insert", "--report", report, "-q") == 0
    assert json.loads(report.read_text())["options"]["insert"] is True
    capsys.readouterr()


@pytest.mark.parametrize(
    "name, text, reason",
    [
        ("o.yaml", "max_rings: 5\n", r"o\.yaml: unknown option\(s\) \['max_rings'\]"),
        ("o.yaml", "max_ring: 99\n", r"o\.yaml: max_ring must be in 3\.\.16"),
        ("o.yaml", "max_ring: [5\n", r"o\.yaml: not a readable options file"),
        ("o.json", '{"seed": 1,}', r"o\.json: not a readable options file"),
        ("o.yaml", "- edge\n", r"o\.yaml: expected a mapping"),
        ("o.txt", "seed: 1\n", r"o\.txt: options files are \.json, \.yaml or \.yml"),
        ("o.yaml", "defaults: [o]\n", r"o\.yaml: the defaults lists include each other"),
        ("o.yaml", "defaults: [{override /x: y}]\n", r"only names of files beside it"),
        ("o.yaml", "defaults: [missing]\n", r"missing\.yaml: cannot read options"),
        (None, "", r"nope\.yaml: cannot read options"),
    ],
)
def test_bad_options_file_exits_2(small, tmp_path, capsys, name, text, reason):
    path = tmp_path / (name or "nope.yaml")
    if name:
        path.write_text(text)
    out = tmp_path / "out.vtu"
    assert _improve(small, out, "--options", path) == 2
    err = capsys.readouterr().err
    assert err.startswith("jtet: error:") and len(err.strip().splitlines()) == 1, err
    assert re.search(reason, err), err
    assert not out.exists()


QUICK = ("--ops", "edge", "--max-passes", "1", "--perturb", "0")


def test_batch_improves_every_input_as_one_run_would(small, tmp_path, capsys):
    """``--out-dir``: each output is the file a single ``jtet improve IN OUT`` writes
    (same mesh), the report is a list, a table sums the batch up."""
    other = tmp_path / "in" / "second.msh"
    other.parent.mkdir()
    jtet.save(jtet.demo_mesh("two_regions").replace(region=[7] * 1928), other)
    outdir, report = tmp_path / "out", tmp_path / "all.json"
    outdir.mkdir()
    plot = outdir / "h.png"
    code = _improve(
        small, other, "--out-dir", outdir, "--out-ext", "vtu", "--report", report, *QUICK,
        "--plot", plot,
    )  # fmt: skip
    cap = capsys.readouterr()
    assert code == 0, cap.err
    names = ["h_second.png", "h_two_regions.png", "second.vtu", "two_regions.vtu"]
    assert sorted(p.name for p in outdir.iterdir()) == names
    assert (outdir / "h_second.png").read_bytes().startswith(PNG_MAGIC)
    assert f"-> {outdir / 'second.vtu'}; {outdir / 'h_second.png'}" in cap.out
    rows = json.loads(report.read_text())
    assert [r["input"] for r in rows] == [str(small), str(other)]
    for src, row in zip((small, other), rows, strict=True):
        single = tmp_path / f"single_{src.stem}.vtu"
        assert _improve(src, single, *QUICK, "-q") == 0
        a, b = jtet.load(row["output"]), jtet.load(single)
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.tets, b.tets)
        np.testing.assert_array_equal(a.region, b.region)
        assert row["status"] == "max passes" and row["stats_after"]["n_tets"] == a.n_tets
    assert "[1/2] [" in cap.err and "[2/2] [" in cap.err  # which file the progress is of
    table = cap.out.splitlines()
    head = next(i for i, ln in enumerate(table) if ln.startswith("input"))
    assert table[head + 2].startswith(str(small)) and table[head + 3].startswith(str(other))
    assert table[-1] == f"wrote {report}"


def test_batch_goes_on_after_a_bad_input(small, tmp_path, capsys):
    bad = tmp_path / "bad.vtu"
    bad.write_text("not a mesh")
    outdir, report = tmp_path / "out", tmp_path / "all.json"
    outdir.mkdir()
    assert _improve(bad, small, "--out-dir", outdir, "--report", report, *QUICK, "-q") == 2
    err = capsys.readouterr().err
    assert "jtet: error:" in err and "bad.vtu" in err
    assert [p.name for p in outdir.iterdir()] == ["two_regions.vtu"]
    rows = json.loads(report.read_text())
    assert rows[0]["output"] is None and "bad.vtu" in rows[0]["error"]
    assert rows[1]["output"] == str(outdir / "two_regions.vtu")


@pytest.mark.parametrize(
    "extra, reason",
    [
        (["--out-dir", "{d}/out", "--plot", "{d}/no/h.png"], "no existing directory"),
        (["--out-dir", "{d}/out", "--plot", "{d}/h.png"], "would both be plotted to"),
        (["--out-ext", "msh"], "--out-ext names the outputs of --out-dir"),
        (["{d}/x.vtu"], r"takes IN OUT, or several inputs with --out-dir DIR \(3 path"),
        (["--out-dir", "{d}/missing"], "not an existing directory"),
        (["--out-dir", "{d}/out", "--out-ext", "stl"], "unknown mesh file extension '.stl'"),
        (["--out-dir", "{d}/in"], "is the input file"),
        (["--out-dir", "{d}/out", "--out-ext", "vtu"], "would both be written to"),
    ],
)
def test_batch_refused_before_any_run(small, tmp_path, capsys, extra, reason):
    (tmp_path / "in").mkdir()
    (tmp_path / "out").mkdir()
    a, b = tmp_path / "in" / "m.vtu", tmp_path / "in" / "m.msh"
    jtet.save(jtet.load(small), a)
    jtet.save(jtet.load(small), b)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    args = [str(x).format(d=tmp_path) for x in extra]
    assert main(["improve", str(a), str(b), *args, *QUICK]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jtet: error:") and re.search(reason, err), err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_every_option_has_a_flag(capsys):
    # the CLI shares jtet.Options with the API: each field is settable from the shell
    # (progress is the progress bar, switched off by --quiet)
    import dataclasses

    with pytest.raises(SystemExit):
        main(["improve", "--help"])
    text = capsys.readouterr().out
    missing = [
        f.name
        for f in dataclasses.fields(jtet.Options)
        if f.name != "progress" and "--" + f.name.replace("_", "-") not in text
    ]
    assert missing == []
