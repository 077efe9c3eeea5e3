"""Tet meshes of surfaces made by fTetWild (``jtet.tetrahedralize``, ``jtet tetrahedralize``):
the volume a surface bounds, surface files of every format read back as written, and bad
surfaces, settings and crashes turned into clear errors."""

import re

import numpy as np
import pytest

import jtet
from jtet._tetrahedralize import open_edges
from jtet.cli import main

pv = pytest.importorskip("pyvista")


def _enclosed_volume(points, triangles) -> float:
    """Volume a closed, outward-oriented triangle surface bounds (divergence theorem)."""
    a, b, c = (points[triangles[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _ball(res: int = 16):
    return pv.Sphere(theta_resolution=res, phi_resolution=res).triangulate()


def _arrays(surface):
    return np.asarray(surface.points, np.float64), surface.faces.reshape(-1, 4)[:, 1:]


def test_cube_surface_gives_a_valid_mesh_of_the_cube():
    points, triangles = _arrays(pv.Cube().triangulate())
    mesh = jtet.tetrahedralize((points, triangles), edge_length_fac=0.2)
    assert mesh.n_tets > 100 and mesh.is_valid().ok
    assert (mesh.region == 1).all()  # a Gmsh physical volume, unlike 0
    assert (mesh.volumes > 0).all()
    # fTetWild's boundary lies within its envelope, 1e-3 of the diagonal (1.73), of the
    # faces (often exactly on them, not always: its output varies from run to run), so
    # the volume is within 6 faces x 1.7e-3 of 1
    assert mesh.volumes.sum() == pytest.approx(_enclosed_volume(points, triangles), abs=0.011)
    lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    np.testing.assert_allclose(lo, points.min(axis=0), atol=1.8e-3)
    np.testing.assert_allclose(hi, points.max(axis=0), atol=1.8e-3)


def test_ball_volume_and_improvement():
    surface = _ball()
    points, triangles = _arrays(surface)
    mesh = jtet.tetrahedralize(surface, edge_length_fac=0.1)
    assert mesh.is_valid().ok
    # the boundary stays within the envelope: 1e-3 of the diagonal (1.73) over an area
    # of ~3.1 moves the volume by at most ~0.005 of 0.51: 2 % is loose and still fails
    # a mesh of the wrong volume (a half or a hull)
    assert mesh.volumes.sum() == pytest.approx(_enclosed_volume(points, triangles), rel=0.02)
    # a mesh jtet takes as it is: every invariant checked after every operation, and
    # the measure it maximizes never lower
    result = jtet.improve(mesh, check=True)
    assert not result.status.startswith("invariant")
    assert (
        jtet.quality(result.mesh, "biased_min_sine").min()
        >= jtet.quality(mesh, "biased_min_sine").min()
    )


@pytest.mark.parametrize("ext", [".stl", ".obj", ".ply", ".vtp", ".vtk", ".off"])
def test_surface_files_read_back_as_written(tmp_path, ext):
    surface = _ball(8)
    points, triangles = _arrays(surface)
    path = tmp_path / f"ball{ext}"
    if ext == ".off":
        import meshio

        meshio.write(str(path), meshio.Mesh(points, [("triangle", triangles)]))
    else:
        surface.save(str(path))
    got_points, got_triangles = jtet.read_surface(path)
    # formats may merge, reorder or (STL: none of its own) repeat points, and may turn
    # a triangle's corners: compare the triangles as sets of corner coordinates, to the
    # float32 precision of STL
    assert got_triangles.shape == triangles.shape
    np.testing.assert_allclose(
        _triangle_corners(got_points, got_triangles),
        _triangle_corners(points, triangles),
        atol=1e-6,
    )


def _triangle_corners(points, triangles) -> np.ndarray:
    """(k, 9) rows: each triangle's corner coordinates, corners sorted, rows sorted."""
    corners = points[triangles]  # (k, 3, 3)
    order = np.lexsort(corners.transpose(2, 0, 1)[::-1])  # sorts each triangle's corners
    corners = np.take_along_axis(corners, order[..., None], axis=1).reshape(len(triangles), 9)
    return corners[np.lexsort(corners.T[::-1])]


def test_open_edges_counts_border_and_non_manifold_edges():
    points, triangles = _arrays(_ball(8))
    assert open_edges(triangles) == 0
    assert open_edges(triangles[1:]) == 3  # one hole: its 3 border edges
    assert open_edges(np.concatenate([triangles, triangles[:1]])) == 3  # 3 edges in 3 triangles


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda p, t: (np.where(np.arange(len(p))[:, None] == 3, np.nan, p), t), "NaN"),
        (lambda p, t: (p, np.where(t == t.max(), len(p), t)), "vertex ids"),
        (lambda p, t: (p, t[:3]), "at least 4"),
        (lambda p, t: (p * np.array([1.0, 1.0, 0.0]), t), "one plane"),
        (lambda p, t: (p * 1e300, t), "spans 1e\\+300 length units"),
        (lambda p, t: (p * 0.0, t), "spans 0 length units"),
        (lambda p, t: (p[:, :2], t), r"\(n, 3\)"),
        (lambda p, t: (p, t.astype(float)), "integer"),
    ],
)
def test_bad_surfaces_are_refused_before_ftetwild(change, match):
    points, triangles = change(*_arrays(_ball(8)))
    with pytest.raises(jtet.MeshInputError, match=match):
        jtet.tetrahedralize((points, triangles))


@pytest.mark.parametrize(
    "settings, match",
    [
        ({"edge_length": 0.0}, "edge_length"),
        ({"edge_length": float("nan")}, "edge_length"),
        ({"edge_length_fac": 1.5}, "edge_length_fac"),
        ({"epsilon": -1e-3}, "epsilon"),
        ({"threads": -1}, "threads"),
    ],
)
def test_bad_settings_are_refused(settings, match):
    with pytest.raises(jtet.MeshInputError, match=match):
        jtet.tetrahedralize(_ball(8), **settings)


def test_unreadable_surface_files(tmp_path):
    with pytest.raises(jtet.MeshFileError, match="no such file"):
        jtet.read_surface(tmp_path / "missing.stl")
    with pytest.raises(jtet.MeshFileError, match="unknown surface file extension"):
        jtet.read_surface(tmp_path / "ball.step")
    damaged = tmp_path / "damaged.vtp"
    _ball(8).save(str(damaged))
    data = bytearray(damaged.read_bytes())
    damaged.write_bytes(bytes(data[: len(data) // 3]))
    with pytest.raises(jtet.MeshFileError, match="damaged.vtp"):
        jtet.read_surface(damaged)


@pytest.mark.parametrize(
    "program, match",
    [
        ("import os; os.abort()", "fTetWild crashed with SIGABRT on this surface"),
        ("raise RuntimeError('no envelope')", r"fTetWild failed \(RuntimeError: no envelope\)"),
    ],
)
def test_a_crash_of_ftetwild_is_an_error_and_the_process_lives(monkeypatch, program, match):
    from jtet import _tetrahedralize

    monkeypatch.setattr(_tetrahedralize, "_FTETWILD_CHILD", program)
    with pytest.raises(jtet.MeshInputError, match=match):
        jtet.tetrahedralize(_ball(8))


def test_ftetwild_called_in_this_process_before_does_not_hang_it(tmp_path):
    """fTetWild's thread pool, started here by a direct pytetwild call (as the
    experiments' generators do), once made a forked child wait forever."""
    import subprocess
    import sys

    program = (
        "import numpy as np, pyvista as pv, pytetwild, jtet\n"
        "s = pv.Sphere(theta_resolution=8, phi_resolution=8).triangulate()\n"
        "p, f = np.asarray(s.points), s.faces.reshape(-1, 4)[:, 1:].astype(np.int32)\n"
        "pytetwild.tetrahedralize(p, f, edge_length_fac=0.2, quiet=True)\n"
        "print(jtet.tetrahedralize((p, f), edge_length_fac=0.2).n_tets > 50)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", program], capture_output=True, text=True, timeout=300, cwd=tmp_path
    )
    assert done.stdout.strip() == "True", done.stderr


def test_command_writes_a_mesh_ready_to_improve(tmp_path, capsys):
    src, out = tmp_path / "ball.stl", tmp_path / "ball.vtu"
    _ball().save(str(src))
    assert main(["tetrahedralize", str(src), str(out), "--edge-length", "0.15"]) == 0
    printed = capsys.readouterr()
    assert "(closed)" in printed.err and "jtet improve" in printed.out
    grid = pv.read(str(out))
    assert {"min_dihedral", "max_dihedral", "volume"} <= set(grid.cell_data)
    mesh = jtet.load(out)
    assert mesh.is_valid().ok and mesh.n_tets == grid.n_cells
    # the input is never overwritten, an unknown output format fails before the work
    assert main(["tetrahedralize", str(src), str(src)]) == 2
    assert main(["tetrahedralize", str(src), str(tmp_path / "ball.step")]) == 2
    assert "unknown mesh file extension" in capsys.readouterr().err
    # a surface given where a tet mesh is expected says what to do
    assert main(["stats", str(src)]) == 2
    assert "jtet tetrahedralize" in capsys.readouterr().err


def test_command_improves_with_improve(tmp_path, capsys):
    """--improve: one command from a surface to an improved mesh, with the optimizer's
    summary (fTetWild's mesh before, jtet's after: the worst angle never drops)."""
    src, out = tmp_path / "ball.stl", tmp_path / "ball.msh"
    _ball().save(str(src))
    opts = tmp_path / "opts.yaml"
    opts.write_text("perturb: 0\nmax_passes: 3\n")
    args = ["tetrahedralize", str(src), str(out), "--edge-length", "0.15", "-q"]
    assert main([*args[:-1], "--improve", "--options", str(opts)]) == 0
    printed = capsys.readouterr().out
    row = next(line for line in printed.splitlines() if line.startswith("min dihedral"))
    before, after = map(float, row.split()[-2:])
    assert after >= before
    mesh = jtet.load(out)
    assert mesh.is_valid().ok and (mesh.region == 1).all()
    assert jtet.stats(mesh).min_dihedral == pytest.approx(after, abs=1e-3)
    # options without --improve, and bad options, fail before fTetWild's work
    assert main([*args, "--options", str(opts)]) == 2
    assert "needs --improve" in capsys.readouterr().err
    opts.write_text("perturb: -1\n")
    assert main([*args, "--improve", "--options", str(opts)]) == 2
    assert "perturb must be >= 0" in capsys.readouterr().err


def test_no_tets_from_ftetwild_is_an_error(monkeypatch):
    from jtet import _tetrahedralize

    empty = (np.zeros((0, 3)), np.zeros((0, 4), np.int64))
    monkeypatch.setattr(_tetrahedralize, "_ftetwild", lambda *a: empty)
    points, triangles = _arrays(_ball(8))
    with pytest.raises(jtet.MeshInputError, match=r"no tets.*\(3 open edge"):
        jtet.tetrahedralize((points, triangles[1:]))


def test_off_files_with_polygons_comments_and_damage(tmp_path):
    """A unit cube as an OFF file of 6 quads, with comments and its counts on the header
    line, reads as the 12 triangles of the cube; files cut short are refused (meshio's
    reader looped forever on one cut after its header)."""
    cube = pv.Cube()
    quads = cube.faces.reshape(-1, 5)[:, 1:]
    text = "OFF 8 6 0 # counts on the header line\n# a comment\n"
    text += "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in cube.points.tolist())
    text += "".join(f"4 {a} {b} {c} {d} 0.5 0.5 0.5\n" for a, b, c, d in quads.tolist())
    path = tmp_path / "cube.off"
    path.write_text(text)
    points, triangles = jtet.read_surface(path)
    np.testing.assert_array_equal(points, cube.points)
    assert triangles.shape == (12, 3) and open_edges(triangles) == 0
    assert _enclosed_volume(points, triangles) == pytest.approx(1.0, rel=1e-12)
    for cut in ("OFF\n# Creat", "OFF\n8 6 0\n0 0 0\n", "COFF\n", "OFF\n8 6\n" + "1 2\n" * 14):
        path.write_text(cut)
        with pytest.raises(jtet.MeshFileError, match="OFF"):
            jtet.read_surface(path)


def test_long_work_shows_its_seconds(monkeypatch):
    """fTetWild reports no progress: on a terminal the command shows the seconds spent
    (rewritten in place, ended by a newline); elsewhere one line; -q nothing."""
    import io
    import sys

    from jtet.cli import _ticking

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    for stream, quiet, want in (
        (Terminal(), False, r"^(\rfTetWild +\d+\.\ds)+\n$"),
        (io.StringIO(), False, r"^fTetWild \.\.\.\n$"),
        (Terminal(), True, r"^$"),
    ):
        monkeypatch.setattr(sys, "stderr", stream)
        with _ticking("fTetWild", quiet):
            pass
        assert re.match(want, stream.getvalue()), repr(stream.getvalue())
