"""The experiment harness: Hydra configs validated against jtet.Options, mesh generators,
sweeps end to end (run.py + aggregate.py), and the peer-comparison helpers.

Needs the ``experiments`` extra (hydra-core, hydra-joblib-launcher, pandas, gmsh); skips
cleanly without it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

hydra = pytest.importorskip("hydra")
pytest.importorskip("pandas")
pytest.importorskip("gmsh")

from helpers import shared_mesh_path  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from hydra.errors import ConfigCompositionException, MissingConfigException  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

import jtet  # noqa: E402
from jtet import _config  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
EXPERIMENTS = ROOT / "experiments"
sys.path.insert(0, str(EXPERIMENTS))

import config_schema  # noqa: E402
import meshgen  # noqa: E402
import peers  # noqa: E402

config_schema.register()

GROUPS = ("mesh", "optimizer", "quality", "smoothing", "experiment")
# metrics that legitimately differ between two identical runs
TIMING_KEYS = {"seconds", "mesh_seconds", "job", "overrides"}


@pytest.fixture(scope="module", autouse=True)
def _hydra():
    """Hydra initialized once for the module (composing is then cheap)."""
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        yield


def _compose(overrides=(), hydra_config: bool = False):
    return compose("config", overrides=list(overrides), return_hydra_config=hydra_config)


def _options(name: str) -> list[str]:
    return sorted(p.stem for p in (CONFIGS / name).glob("*.yaml"))


def _validate(cfg) -> jtet.Options:
    opts = config_schema.to_options(cfg.optimizer)
    params = OmegaConf.to_container(cfg.mesh.params, resolve=True)
    meshgen.check(cfg.mesh.generator, params)
    return opts


# ---------------------------------------------------------------------------------------
# configs


def test_schema_is_jtet_options():
    """The structured schema has exactly jtet.Options' fields, with the same defaults."""
    fields = {f.name: f for f in dataclasses.fields(config_schema.OptimizerConfig)}
    defaults = jtet.Options()
    assert list(fields) == [f.name for f in dataclasses.fields(jtet.Options)]
    schema_defaults = OmegaConf.to_container(OmegaConf.structured(config_schema.OptimizerConfig))
    assert config_schema.to_options(schema_defaults) == defaults


@pytest.mark.parametrize("group", ["optimizer", "quality", "smoothing"])
def test_options_files_read_as_hydra_composes_them(group):
    """``jtet.load_options`` on one file of the option groups (what ``jtet improve
    --options`` reads) gives the options Hydra composes with that group choice."""
    for name in _options(group):
        cfg = _compose([f"{group}={name}"])
        composed = config_schema.to_options(cfg.optimizer)
        assert jtet.load_options(CONFIGS / group / f"{name}.yaml") == composed, name


def test_default_config_is_jtet_defaults():
    """configs/config.yaml with no override reproduces jtet's own defaults."""
    cfg = _compose()
    assert config_schema.to_options(cfg.optimizer) == jtet.Options()
    assert cfg.mesh.name == "cube"


@pytest.mark.parametrize("group", GROUPS)
def test_every_group_option_composes_and_validates(group):
    names = _options(group)
    assert names, f"configs/{group}/ is empty"
    for name in names:
        paths = {"file": "some_mesh.vtu", "surface": "some_surface.stl"}
        extra = [f"mesh.params.path={paths[name]}"] if group == "mesh" and name in paths else []
        cfg = _compose([f"{group}={name}", *extra], hydra_config=True)
        opts = _validate(cfg)
        if group == "quality":
            assert opts.quality == name
        if group == "mesh":
            assert cfg.mesh.name == name
        # an experiment's sweep values are options of groups (each validated above)
        for key, values in (cfg.hydra.sweeper.params or {}).items():
            assert key in GROUPS, (name, key)
            for value in str(values).split(","):
                assert value in _options(key), (name, key, value)


def test_no_perturb_is_the_default_without_perturbation_rounds():
    cfg = _compose(["optimizer=no_perturb"])
    assert config_schema.to_options(cfg.optimizer) == jtet.Options(perturb=0)
    assert jtet.Options().perturb_rounds(10_000) > 0


def test_experiments_are_global_deltas():
    for path in (CONFIGS / "experiment").glob("*.yaml"):
        assert path.read_text().startswith("# @package _global_"), path.name


def test_smoke_experiment_is_2x2_tiny_edge_only():
    cfg = _compose(["experiment=smoke"], hydra_config=True)
    params = cfg.hydra.sweeper.params
    assert params.mesh == "tiny_cube,tiny_two_regions"
    assert params.quality == "min_sine,radius_ratio"
    assert list(cfg.optimizer.ops) == ["edge"] and cfg.optimizer.max_passes <= 5


def test_default_launcher_is_local_parallel():
    cfg = _compose(hydra_config=True)
    assert "joblib" in cfg.hydra.launcher._target_.lower()
    assert cfg.hydra.launcher.n_jobs == 2


@pytest.mark.parametrize(
    ("overrides", "side_by_side"),
    [
        ([], True),  # configs/hydra/launcher/local.yaml: joblib, 2 jobs
        (["hydra.launcher.n_jobs=1"], False),
        (["hydra/launcher=joblib"], True),  # Hydra's n_jobs=-1: a job per core
        (["hydra/launcher=submitit_local"], True),
        (["hydra/launcher=slurm"], False),  # each job on cores of its own
        (["hydra/launcher=basic"], False),
    ],
)
def test_jobs_side_by_side_per_launcher(overrides, side_by_side):
    """Which sweeps run.py turns the perturbation helper process off for."""
    import run

    cfg = _compose(overrides, hydra_config=True)
    assert run.jobs_side_by_side(cfg.hydra.launcher) is side_by_side


@pytest.mark.parametrize(
    "override",
    [
        "optimizer.max_rng=5",  # typo of a jtet.Options field
        "optimizer.max_ring=seven",  # wrong type
        "optimizer.check=maybe",
        "mesh.nme=cube",  # typo in the mesh schema
        "sav_mesh=false",  # typo at the top level
    ],
)
def test_typo_override_fails_at_composition(override):
    with pytest.raises(ConfigCompositionException):
        _compose([override])


def test_unknown_group_option_fails():
    with pytest.raises(MissingConfigException):
        _compose(["quality=min_sin"])


def test_forced_unknown_key_fails_at_conversion():
    """``+key=value`` bypasses the closed schema; jtet.Options(**...) still refuses it."""
    cfg = _compose(["+optimizer.max_rng=5"])
    with pytest.raises(TypeError, match="max_rng"):
        config_schema.to_options(cfg.optimizer)


def test_bad_values_fail_at_conversion():
    for override in ("optimizer.max_ring=99", "optimizer.ops=[edge,flip]"):
        cfg = _compose([override])
        with pytest.raises(jtet.JtetError):
            config_schema.to_options(cfg.optimizer)


def test_mesh_param_typo_fails():
    with pytest.raises(ConfigCompositionException):
        _compose(["mesh.params.hh=0.1"])
    cfg = _compose(["+mesh.params.hh=0.1"])  # forced in: the generator's signature refuses it
    with pytest.raises(ValueError, match="hh"):
        meshgen.check(cfg.mesh.generator, dict(cfg.mesh.params))
    with pytest.raises(ValueError, match="shape"):
        meshgen.check("gmsh_shape", {"shape": "cuboid", "h": 0.1})
    with pytest.raises(ValueError, match="generator"):
        meshgen.check("gmsh", {})


# ---------------------------------------------------------------------------------------
# mesh generators


def _boundary_points(mesh: jtet.TetMesh) -> np.ndarray:
    faces, _, outside = peers.surface_faces(mesh)
    return np.unique(faces[outside < 0])


@pytest.mark.parametrize("shape", meshgen.SHAPES)
def test_gmsh_shapes_are_valid_and_reproducible(shape):
    a = meshgen.gmsh_shape(shape, h=0.4)
    b = meshgen.gmsh_shape(shape, h=0.4)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.tets, b.tets)
    assert (a.volumes > 0).all() and a.is_valid().ok


def test_gmsh_cube_matches_reference_mesh():
    ref = shared_mesh_path("gmsh_cube.vtu")
    mesh = meshgen.gmsh_shape("cube", h=0.08)
    expected = jtet.load(ref)
    assert np.array_equal(mesh.tets, expected.tets)
    np.testing.assert_allclose(mesh.points, expected.points, rtol=0, atol=1e-14)


def test_bracket_has_the_volume_of_its_solid():
    """The bracket against its volume in closed form: base 2 x 1 x 0.2 and wall
    0.25 x 1 x 1, plus the fillet's (r^2 - pi r^2 / 4) x 1 (r = 0.15), minus the
    through-holes pi r^2 x length (r 0.15 and 0.1 through the base, 0.2 through the
    wall). The mesh's polygonal holes and fillet are inscribed in the circles: within
    1 % at h = 0.1."""
    mesh = meshgen.gmsh_shape("bracket", h=0.1)
    assert mesh.is_valid().ok and (mesh.volumes > 0).all()
    r = 0.15
    solid = (
        0.4
        + 0.25
        + (r**2 - np.pi * r**2 / 4)
        - np.pi * (0.15**2 * 0.2 + 0.1**2 * 0.2 + 0.2**2 * 0.25)
    )
    np.testing.assert_allclose(mesh.volumes.sum(), solid, rtol=1e-2)


def test_two_regions_has_a_closed_interface():
    mesh = meshgen.gmsh_two_regions(h=0.25)
    assert set(np.unique(mesh.region).tolist()) == {1, 2}
    assert mesh.is_valid().ok
    # the ball's volume: the inner region is a polyhedron inscribed in the sphere
    inner = mesh.volumes[mesh.region == 2].sum()
    assert 0.8 * (4 / 3) * np.pi * 0.3**3 < inner < (4 / 3) * np.pi * 0.3**3
    np.testing.assert_allclose(mesh.volumes.sum(), 1.0, rtol=1e-12)


def test_perturbed_moves_only_interior_points():
    good = meshgen.gmsh_shape("cube", h=0.3, seed=3, optimize=True)  # same base mesh
    bad = meshgen.perturbed("cube", h=0.3, amplitude=0.3, seed=3)
    again = meshgen.perturbed("cube", h=0.3, amplitude=0.3, seed=3)
    other = meshgen.perturbed("cube", h=0.3, amplitude=0.3, seed=4)
    assert np.array_equal(bad.points, again.points)
    assert not np.array_equal(bad.points, other.points)
    assert np.array_equal(good.tets, bad.tets)
    boundary = _boundary_points(good)
    assert np.array_equal(good.points[boundary], bad.points[boundary])
    assert not np.allclose(good.points, bad.points)
    assert (bad.volumes > 0).all()
    assert jtet.stats(bad).min_dihedral < jtet.stats(good).min_dihedral


def test_tetwild_generator():
    pytest.importorskip("pytetwild")
    mesh = meshgen.tetwild("sphere", h=0.4, optimize=False)
    assert mesh.is_valid().ok and (mesh.volumes > 0).all()
    np.testing.assert_allclose(mesh.volumes.sum(), 4 / 3 * np.pi, rtol=0.1)


def test_bench_mesh_names_generate_once_then_load(tmp_path, monkeypatch):
    pytest.importorskip("pytetwild")
    import tempfile

    import bench_improve

    monkeypatch.setattr(tempfile, "gettempdir", lambda: str(tmp_path))
    for name, generator in (("gmsh:sphere:0.4", "gmsh"), ("tetwild:sphere:0.4", "tetwild")):
        first = bench_improve.load_mesh(name)
        cached = tmp_path / f"jtet_bench_{generator}_sphere_0.4.vtu"
        assert cached.exists() and first.is_valid().ok
        np.testing.assert_allclose(first.volumes.sum(), 4 / 3 * np.pi, rtol=0.1)
        # the second call reads the file (fTetWild is not deterministic from run to run)
        again = bench_improve.load_mesh(name)
        np.testing.assert_array_equal(again.tets, first.tets)
        np.testing.assert_array_equal(again.points, first.points)


def test_file_generator(tmp_path):
    path = tmp_path / "m.vtu"
    jtet.save(jtet.demo_mesh("two_regions"), path)
    mesh = meshgen.generate("file", {"path": str(path)})
    assert np.array_equal(mesh.tets, jtet.demo_mesh("two_regions").tets)


def test_surface_generator(tmp_path):
    pv = pytest.importorskip("pyvista")
    path = tmp_path / "ball.stl"
    pv.Sphere(theta_resolution=12, phi_resolution=12).save(str(path))
    mesh = meshgen.generate("surface", {"path": str(path), "edge_length_fac": 0.15})
    assert mesh.n_tets > 100 and mesh.is_valid().ok
    with pytest.raises(ValueError, match="edge_lenght"):
        meshgen.check("surface", {"path": str(path), "edge_lenght": 0.1})


# ---------------------------------------------------------------------------------------
# sweeps end to end


def _run(
    args: list[str], cwd: Path, timeout: float = 600, env: dict | None = None
) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


def _metrics(sweep: Path) -> dict[str, dict]:
    out = {}
    for path in sorted(sweep.rglob("metrics.json")):
        row = json.loads(path.read_text())
        out[f"{row['mesh']}/{row['quality']}"] = row
    return out


def _check_sweep(sweep: Path, n_runs: int) -> dict[str, dict]:
    rows = _metrics(sweep)
    assert len(rows) == n_runs, sorted(p.name for p in sweep.iterdir())
    for key, row in rows.items():
        assert row["status"] in ("converged", "max passes"), (key, row["status"])
        assert row["valid"] is True
        assert row["min_dihedral_after"] >= row["min_dihedral_before"]
        assert row["worst_quality_after"] >= row["worst_quality_before"]
        report = json.loads((sweep / str(row["job"]) / "report.json").read_text())
        assert row["perturb_rounds"] == report["perturb_rounds"] >= 0
        kicks = [e for e in report["history"] if e["op"] == "perturb"]
        assert row["perturb_tried"] == len(kicks)
        assert row["perturb_kept"] == sum(e["successes"] for e in kicks)
        kept_rounds = len({e["round"] for e in kicks if e["successes"]})
        assert row["perturb_kept_rounds"] == kept_rounds <= row["perturb_rounds"]
        assert row["perturb_gave_up"] == sum(e["gave_up"] for e in kicks)
        run_dir = sweep / str(row["job"])
        for name in ("improved.vtu", "report.json", "history.csv", "metrics.json"):
            assert (run_dir / name).is_file(), (run_dir, name)
        assert (run_dir / ".hydra" / "config.yaml").is_file()
        history = (run_dir / "history.csv").read_text().splitlines()
        assert history[0].startswith("pass,") and len(history) >= 2
    return rows


def _aggregate(sweep: Path, n_runs: int) -> None:
    import pandas as pd

    _run([str(EXPERIMENTS / "aggregate.py"), str(sweep)], cwd=sweep)
    table = pd.read_csv(sweep / "results.csv")
    assert len(table) == n_runs
    assert {"label", "min_dihedral_after", "seconds", "valid"} <= set(table.columns)
    summary = (sweep / "summary.md").read_text()
    assert summary.count("\n| mesh=") == n_runs
    assert (sweep / "worst_vs_time.png").stat().st_size > 0
    assert (sweep / "histograms.png").stat().st_size > 0


def test_sweep_2x2_basic_launcher_and_reproducible(tmp_path):
    """The smoke experiment (2 tiny meshes x 2 measures) in-process, then aggregate.py;
    one configuration run again on its own gives the same metrics (seeds are configs).
    Jobs one after the other may use a perturbation helper process."""
    sweep = tmp_path / "sweep"
    helper_on = dict(os.environ, JTET_HELPER="1")
    _run(
        [
            str(EXPERIMENTS / "run.py"),
            "-m",
            "experiment=smoke",
            "hydra/launcher=basic",
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=tmp_path,
        env=helper_on,
    )
    rows = _check_sweep(sweep, 4)
    assert {r["regions"] for r in rows.values()} == {1, 2}
    may_help = _config.CACHE_DIR is not None and _config.WORKERS > 1
    assert {r["perturb_helper"] for r in rows.values()} == {may_help}
    _aggregate(sweep, 4)

    single = tmp_path / "single"
    _run(
        [
            str(EXPERIMENTS / "run.py"),
            "experiment=smoke",
            "mesh=tiny_two_regions",
            "quality=radius_ratio",
            "hydra/launcher=basic",
            "mesh_format=xdmf",
            f"hydra.run.dir={single}",
        ],
        cwd=tmp_path,
        env=helper_on,
    )
    again = json.loads((single / "metrics.json").read_text())
    # the improved mesh in the format asked for: XDMF and its heavy data, for dolfinx
    improved = jtet.load(single / "improved.xdmf")
    assert (single / "improved.h5").is_file() and not (single / "improved.vtu").exists()
    assert jtet.stats(improved).min_dihedral == pytest.approx(again["min_dihedral_after"])
    first = rows["tiny_two_regions/radius_ratio"]
    same = {k: v for k, v in first.items() if k not in TIMING_KEYS}
    assert {k: v for k, v in again.items() if k not in TIMING_KEYS} == same
    assert again["job"] is None


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["joblib", "submitit_local"])
def test_sweep_parallel_launchers(tmp_path, launcher):
    """The same sweep through the parallel launchers (joblib: the default; submitit_local:
    the local mode of the SLURM launcher). Jobs side by side run no helper process."""
    if launcher == "submitit_local":
        pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    sweep = tmp_path / "sweep"
    _run(
        [
            str(EXPERIMENTS / "run.py"),
            "-m",
            "mesh=tiny_cube,tiny_two_regions",
            "quality=min_sine,radius_ratio",
            "optimizer=smoke",
            "plot=false",
            f"hydra/launcher={launcher}",
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=tmp_path,
        timeout=1200,
        env=dict(os.environ, JTET_HELPER="1"),
    )
    rows = _check_sweep(sweep, 4)
    assert not any(r["perturb_helper"] for r in rows.values())
    _aggregate(sweep, 4)


@pytest.mark.parametrize(
    "override, says",
    [("optimizer.max_rng=5", "max_rng"), ("mesh_format=stl", "unknown mesh file extension")],
)
def test_run_rejects_a_typo_before_working(tmp_path, override, says):
    proc = subprocess.run(
        [
            sys.executable,
            str(EXPERIMENTS / "run.py"),
            "mesh=tiny_cube",
            override,
            f"hydra.run.dir={tmp_path / 'run'}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode != 0
    assert says in proc.stderr
    assert not (tmp_path / "run" / "metrics.json").exists()


# ---------------------------------------------------------------------------------------
# peers


def test_surface_faces_of_two_regions():
    mesh = jtet.demo_mesh("two_regions")
    faces, inside, outside = peers.surface_faces(mesh)
    # brute-force reference: count every sorted face; once = boundary, twice = interior
    all_faces = np.sort(
        np.concatenate([mesh.tets[:, [1, 2, 3]], mesh.tets[:, [0, 2, 3]],
                        mesh.tets[:, [0, 1, 3]], mesh.tets[:, [0, 1, 2]]]),
        axis=1,
    )  # fmt: skip
    keys, counts = np.unique(all_faces, axis=0, return_counts=True)
    assert (outside < 0).sum() == (counts == 1).sum()
    # the interface z = 0.45 between regions 1 and 2
    iface = faces[outside >= 0]
    assert np.allclose(mesh.points[iface][..., 2], 0.45)
    assert set(zip(inside[outside >= 0].tolist(), outside[outside >= 0].tolist())) == {(1, 2)}
    # outward orientation: the boundary faces' normals point away from the centroid
    b = faces[outside < 0]
    p = mesh.points[b]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert (np.einsum("ij,ij->i", normal, p.mean(axis=1) - 0.5) > 0).all()


def test_boundary_status():
    mesh = jtet.demo_mesh("two_regions")
    assert peers.boundary_status(mesh, mesh) == "same faces"
    # renumbered points: still the same faces
    perm = np.random.default_rng(0).permutation(mesh.n_points)
    inv = np.argsort(perm)
    renumbered = jtet.TetMesh(mesh.points[perm], inv[mesh.tets], mesh.region)
    assert peers.boundary_status(mesh, renumbered) == "same faces"
    # a boundary point moved: changed
    moved = mesh.points.copy()
    moved[_boundary_points(mesh)[0]] += 1e-3
    assert peers.boundary_status(mesh, jtet.TetMesh(moved, mesh.tets, mesh.region)) == "changed"
    # region labels swapped on one tet: region volumes change
    region = mesh.region.copy()
    region[0] = 3 - region[0]
    assert peers.boundary_status(mesh, jtet.TetMesh(mesh.points, mesh.tets, region)) == "changed"


def test_gmsh_peers_keep_the_boundary():
    mesh = meshgen.gmsh_two_regions(h=0.25)
    for method in ("", "Netgen"):
        out = peers.run_gmsh(mesh, method)
        assert out.mesh.is_valid().ok
        assert peers.boundary_status(mesh, out.mesh) == "same faces"
        assert jtet.stats(out.mesh).min_dihedral >= jtet.stats(mesh).min_dihedral


def test_mmg3d_and_tetgen_peers():
    mesh = meshgen.gmsh_shape("cube", h=0.25)
    ran = 0
    if peers.mmg3d_binary() is not None:
        out = peers.run_mmg3d(mesh)
        assert out.mesh is not None, out.note
        assert out.mesh.is_valid().ok
        assert peers.boundary_status(mesh, out.mesh) in ("same faces", "same surface")
        ran += 1
    try:
        import tetgenpy  # noqa: F401
    except ImportError:
        pass
    else:
        out = peers.run_tetgen(mesh)
        assert out.mesh.is_valid().ok
        assert peers.boundary_status(mesh, out.mesh) in ("same faces", "same surface")
        ran += 1
    if not ran:
        pytest.skip("neither mmg3d (pymmg) nor tetgenpy is installed")


def test_peer_table_markdown(tmp_path):
    rows = [
        {"mesh": "m", "tool": "input", "tets": 10, "min_dihedral": 1.0, "seconds": float("nan")},
        {"mesh": "m", "tool": "x", "seconds": 1.5, "note": "x failed"},
    ]
    text = peers.markdown(rows, ["# title"])
    lines = text.splitlines()
    assert lines[0] == "# title"
    assert "| m | input | 10 | 1.00 |" in text
    assert text.strip().endswith("- m / x: x failed")


def test_worst_tets_ring_angles_close_around_edges():
    """worst_tets.ring_angle against closed forms on a cube: the dihedral angles around an
    interior edge sum to 360 degrees, around an edge inside a face to 180, around a cube
    edge (a subsegment) to 90; report() lists the smallest angle first."""
    import worst_tets

    from jtet._quality import tet_dihedrals

    mesh = meshgen.gmsh_shape("cube", h=0.4)
    topo = mesh.topology
    angles = tet_dihedrals(mesh.points, mesh.tets)[0]
    sums = np.array([worst_tets.ring_angle(mesh, angles, e)[0] for e in range(len(topo.edges))])
    interior = ~topo.edge_boundary
    # round-off of the atan2 angles: ~1e-13 degrees per tet, at most ~10 tets per ring
    np.testing.assert_allclose(sums[interior], 360.0, atol=1e-9)
    np.testing.assert_allclose(sums[topo.subsegment], 90.0, atol=1e-9)
    np.testing.assert_allclose(sums[topo.edge_boundary & ~topo.subsegment], 180.0, atol=1e-9)
    lines = worst_tets.report(mesh, 3, "fixed")
    worst = [float(line.split()[0]) for line in lines]
    smallest = tet_dihedrals(mesh.points, mesh.tets)[1].min()
    assert worst == sorted(worst)
    assert worst[0] == pytest.approx(smallest, abs=0.006)  # printed with two decimals


@pytest.mark.slow
def test_smoothing_call_table_times_the_pass_shapes():
    """bench_smooth's table 4 times every stars-per-call row, and its one-lane calls solve
    the same stars as the batched kernel: most new positions agree to the bit (they may
    round differently, measured 88-93 % identical on the holeplate)."""
    import bench_smooth

    rows = bench_smooth.call_table(jtet.demo_mesh(), reps=3)
    assert [r["stars"] for r in rows] == [1, 2, 3, 8, 16, 32, 128]
    assert all(r["batch_ms"] > 0 for r in rows)
    for r in rows:
        if r["stars"] <= 8:
            assert r["one_lane_ms"] > 0 and r["same"] > 0.5
        else:
            assert r["one_lane_ms"] is None
