"""Benchmark of the whole optimizer (issue 6 targets) on the reference Gmsh meshes.

Prints one table row per mesh: worst / max dihedral before and after, tets below 30
degrees, wall time of a first run (compiles for the batch shapes of that mesh) and of a
second (steady state), each on a newly loaded mesh, microseconds per input tet, smoothing
share, peak RSS, status; and, with
``--compile``, the compile overhead of a first run in a fresh process with an empty cache
(cold) and with the cache that run filled (warm), against the steady state, with import
times and the kernel builds (experiments/results/compile.md).

    python experiments/bench_improve.py                       # the four reference meshes
    python experiments/bench_improve.py --meshes gmsh_cube --ops edge,face
    python experiments/bench_improve.py --boundary slide      # flat facets' vertices slide
    python experiments/bench_improve.py --perturb 0           # without perturbation rounds
    python experiments/bench_improve.py --no-insert --seeds 3  # rounds without new vertices
    python experiments/bench_improve.py --seeds 5             # quality over seeds 0-4
    python experiments/bench_improve.py --compile --meshes gmsh_cube   # compile overhead
    python experiments/bench_improve.py --cli --repeat 5      # the jtet command, end to end
    python experiments/bench_improve.py --big 165000          # + a ~1M-tet Delaunay mesh
    python experiments/bench_improve.py --meshes gmsh:cube:0.03   # Gmsh cube, h = 0.03 (~200k)
    python experiments/bench_improve.py --meshes tetwild:holeplate:0.06   # fTetWild output
    python experiments/bench_improve.py --smooth-effort 15x6,8x3,4x4   # smoothing effort table
    python experiments/bench_improve.py --settings min_sine:0.7,biased_min_sine:0.6

Mesh names: a file of ../shared/meshes, ``demo``, ``delaunay:N`` (random points in a cube,
worst quality limited by its fixed flat-hull boundary), ``gmsh:SHAPE:H`` (an unoptimized
Gmsh Delaunay mesh like the reference ones, any size) or ``tetwild:SHAPE:H`` (fTetWild's
optimized output on the Gmsh surface of SHAPE, target edge length H); both are cached
under $TMPDIR; or the path of any mesh file ``jtet.load`` reads (a TetGen ``.ele``).

Reference points (../shared/meshes/README.md, same kind of machine, one core): Stellar
(flips + smoothing) 29-34 / 138-145 degrees at ~0.3 ms CPU per tet; Gmsh ~13 / 157;
Gmsh Netgen 20-24 / 139-142; MMG3D -optim 14-21 / 143-159.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import jtet
from jtet.cli import _perturb as perturb_count  # --perturb N|auto, as jtet improve reads it

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"
MESHES = ("gmsh_cube", "gmsh_sphere", "gmsh_torus", "gmsh_holeplate")


def load_mesh(name: str) -> jtet.TetMesh:
    if name == "demo":
        return jtet.demo_mesh()
    if name.startswith("delaunay"):
        from scipy.spatial import Delaunay

        n = int(name.split(":")[1])
        rng = np.random.default_rng(0)
        pts = np.vstack(
            [np.array(np.meshgrid([0, 1], [0, 1], [0, 1])).reshape(3, -1).T, rng.random((n, 3))]
        )
        tets = Delaunay(pts).simplices.astype(np.int64)
        mesh = jtet.TetMesh(pts, tets)
        vol = mesh.volumes
        tets = np.where((vol < 0)[:, None], tets[:, [1, 0, 2, 3]], tets)[np.abs(vol) > 1e-15]
        return jtet.TetMesh(pts, tets)
    if name.startswith(("gmsh:", "tetwild:")):
        kind, shape, h = name.split(":")
        cache = Path(tempfile.gettempdir()) / f"jtet_bench_{kind}_{shape}_{h}.vtu"
        if not cache.exists():
            sys.path.insert(0, str(Path(__file__).parent))
            import meshgen

            if kind == "gmsh":
                made = meshgen.gmsh_shape(shape, float(h))
            else:  # fTetWild's normal (optimized) output
                made = meshgen.tetwild(shape, float(h), optimize=True)
            jtet.save(made, cache)
        return jtet.load(cache)
    if Path(name).suffix and Path(name).exists():  # a mesh file of the user's
        return jtet.load(name)
    return jtet.load(SHARED / f"{name}.vtu")


def run_one(name: str, ops: tuple[str, ...], time_limit: float | None, **options) -> dict:
    """One ``improve`` on a newly loaded mesh (its topology, cached on the mesh object,
    is built inside the timed call, as in a user's run; loading is not timed)."""
    mesh = load_mesh(name)
    climb_ends = []  # when each climb entry was made: the last one is where the rounds start

    def stamp(entry):
        if entry["op"] != "perturb":
            climb_ends.append(time.perf_counter())

    t0 = time.perf_counter()
    r = jtet.improve(mesh, ops=ops, time_limit=time_limit, callback=stamp, **options)
    t1 = time.perf_counter()
    wall = t1 - t0
    smooth_s = sum(h["seconds"] for h in r.history if h["op"] == "smooth")
    rounds = [h for h in r.history if h["op"] == "perturb"]
    climb = [h for h in r.history if h["op"] != "perturb"]
    b, a = r.stats_before, r.stats_after
    return {
        "mesh": name,
        "tets": mesh.n_tets,
        "before": f"{b.min_dihedral:.2f} / {b.max_dihedral:.2f}",
        "after": f"{a.min_dihedral:.2f} / {a.max_dihedral:.2f}",
        "min_dihedral": a.min_dihedral,
        "max_dihedral": a.max_dihedral,
        "below30": a.small_dihedral[30],
        "seconds": wall,
        "us_per_tet": 1e6 * wall / mesh.n_tets,
        "passes": 1 + max((h["pass"] for h in climb), default=-1),
        "smooth_share": smooth_s / wall,
        # perturbation: kept rounds / attempts, and their share of the wall time (from the
        # climb's last entry to the end of the run: the attempts' own seconds add up the
        # helper process's, which run beside this one's, and passed 100 %)
        "perturb": f"{sum(h['successes'] for h in rounds)}/{len(rounds)}",
        "perturb_share": (t1 - climb_ends[-1]) / wall if rounds and climb_ends else 0.0,
        # peak resident set of this process so far (rows run in order of size: the peak of
        # the largest mesh is its own)
        "peak_rss_gb": _peak_rss_gb(),
        "status": r.status,
    }


def _peak_rss_gb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def smooth_effort(names: list[str], ops: tuple[str, ...], efforts: list[str]) -> None:
    """The same improve runs with smoothing at several (iterations x trial steps) per pass,
    each after a warm-up run of the same setting on the same mesh (steady state)."""
    import functools

    import jtet._smooth as smooth

    original = smooth.smooth_pass
    rows = []
    try:
        for name in names:
            for effort in efforts:
                iters, trials = (int(x) for x in effort.split("x"))
                smooth.smooth_pass = functools.partial(original, max_iters=iters, n_trials=trials)
                run_one(name, ops, None)
                row = run_one(name, ops, None)
                row["mesh"] = f"{name} {effort}"
                rows.append(row)
    finally:
        smooth.smooth_pass = original
    print_table(rows, f"smoothing effort (iterations x trial steps per pass), ops={ops}")


def quality_settings(names: list[str], ops: tuple[str, ...], settings: list[str]) -> None:
    """The same improve runs under several (quality measure, good_quality) settings, each
    after a warm-up run of the same setting on the same mesh (steady state)."""
    rows = []
    for name in names:
        for setting in settings:
            measure, good = setting.split(":")
            options = {"quality": measure, "good_quality": None if good == "none" else float(good)}
            run_one(name, ops, None, **options)
            row = run_one(name, ops, None, **options)
            row["mesh"] = f"{name} {setting}"
            rows.append(row)
    print_table(rows, f"quality measure : good_quality, ops={ops}")


def seed_spread(names: list[str], ops: tuple[str, ...], n_seeds: int, **options) -> None:
    """Worst / largest dihedral angle of ``improve`` with seeds 0 .. n_seeds - 1 on each
    mesh (the seed breaks ties in the smoothing colouring, so each seed climbs a different
    path), and how many seeds meet the quality target (worst >= 32, max <= 138 degrees)."""
    print(f"\nquality over seeds 0-{n_seeds - 1}, ops={ops}, {options}")
    print(
        f"{'mesh':16s} {'worst / max per seed':{15 * n_seeds}s} {'worst min / median':20s} target  mean s"
    )
    for name in names:
        run_one(name, ops, None, **options)  # warm-up: the shapes of this mesh
        rows = [run_one(name, ops, None, seed=seed, **options) for seed in range(n_seeds)]
        worst = np.array([r["min_dihedral"] for r in rows])
        met = sum(r["min_dihedral"] >= 32 and r["max_dihedral"] <= 138 for r in rows)
        cells = "".join(f"{r['after']:15s}" for r in rows)
        spread = f"{worst.min():.2f} / {np.median(worst):.2f}"
        mean_s = np.mean([r["seconds"] for r in rows])
        print(f"{name:16s} {cells} {spread:20s} {met}/{n_seeds}     {mean_s:.1f}")


def print_table(rows: list[dict], title: str) -> None:
    print(f"\n{title}")
    head = [
        "mesh",
        "tets",
        "before (min/max)",
        "after (min/max)",
        "<30 after",
        "1st run s",
        "wall s",
        "us/tet",
        "passes",
        "smooth %",
        "perturb kept/tried",
        "perturb %",
        "peak RSS GB",
        "status",
    ]
    body = [
        [
            r["mesh"],
            str(r["tets"]),
            r["before"],
            r["after"],
            str(r["below30"]),
            f"{r.get('first_s', float('nan')):.1f}",
            f"{r['seconds']:.1f}",
            f"{r['us_per_tet']:.0f}",
            str(r["passes"]),
            f"{100 * r['smooth_share']:.0f}",
            r["perturb"],
            f"{100 * r['perturb_share']:.0f}",
            f"{r['peak_rss_gb']:.2f}",
            r["status"],
        ]
        for r in rows
    ]
    widths = [max(len(x) for x in col) for col in zip(head, *body)]
    for line in [head, ["-" * w for w in widths], *body]:
        print("  ".join(x.ljust(w) for x, w in zip(line, widths)))


def compile_worker(name: str, ops: tuple[str, ...]) -> None:
    """One fresh process of the compile table: a first and a second improve, each on a
    newly loaded mesh (the second is the steady state), wall and CPU seconds, and the
    kernel builds of the first; JSON on stdout. The first run
    includes the imports improve does itself (jtet._smooth and optimistix)."""
    from jtet import _aot

    times, cpu = [], []
    for _ in range(2):
        # a new mesh object each run: the second run pays the mesh's own set-up (topology,
        # cached on the object) too, so the difference is the kernels' first-use cost
        mesh = load_mesh(name)
        t, c = time.perf_counter(), _cpu_seconds()
        jtet.improve(mesh, ops=ops)
        times.append(time.perf_counter() - t)
        cpu.append(_cpu_seconds() - c)
        if len(times) == 1:
            builds = dict(getattr(_aot, "STATS", {}))  # (older jtet: no build counts)
    row = {"first": times[0], "steady": times[1], "cpu_first": cpu[0], "cpu_steady": cpu[1]}
    print(json.dumps(row | builds))


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process, all threads: on a shared machine the
    CPU an overhead costs is steadier than its wall time (other jobs' load stretches
    the wall time, and concurrent builds only shorten it when a core is free)."""
    t = os.times()
    return t.user + t.system


def _compile_run(name: str, ops: str, cache: str) -> dict:
    env = dict(os.environ, JTET_COMPILATION_CACHE=cache)
    t = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-X", "importtime", __file__, "--compile-worker", name, "--ops", ops],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    row = json.loads(out.stdout.strip().splitlines()[-1])
    row["process"] = time.perf_counter() - t
    # -X importtime: cumulative microseconds of the top-level imports (jtet, jax, ...)
    imports = {}
    for line in out.stderr.splitlines():
        parts = line.split("|")
        if len(parts) == 3 and parts[2].strip() in ("jtet", "jax", "optimistix", "jtet._smooth"):
            imports[parts[2].strip()] = int(parts[1]) / 1e6
    row["import_jtet"] = imports.get("jtet", float("nan"))
    row["import_smooth"] = imports.get("jtet._smooth", float("nan"))
    return row


def cli_wall_time(names: list[str], repeat: int) -> None:
    """Wall time of the ``jtet improve IN OUT`` command as a user runs it (a new process:
    interpreter start, imports, reading, the run with its kernels loaded from the warm
    cache, the summary, writing the output, exit), after one untimed run per mesh that
    fills the cache; min and median of ``repeat`` runs. Then the batch command
    ``jtet improve IN1 IN2 ... --out-dir DIR`` on all the meshes against the sum of the
    separate commands' medians, and whether the outputs are the same files."""
    import shutil

    command = shutil.which("jtet")
    if command is None:
        sys.exit("--cli: the jtet command is not installed (pip install -e .)")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        (tmp / "single").mkdir()
        (tmp / "batch").mkdir()
        inputs = []
        for i, name in enumerate(names):
            path = tmp / f"{i}_{name.replace(':', '_')}.vtu"
            jtet.save(load_mesh(name), path)
            inputs.append(path)
            args = [command, "improve", str(path), str(tmp / "single" / path.name), "--quiet"]
            subprocess.run(args, check=True, capture_output=True)  # fills the cache
            walls = []
            for _ in range(repeat):
                t = time.perf_counter()
                subprocess.run(args, check=True, capture_output=True)
                walls.append(time.perf_counter() - t)
            rows.append((name, jtet.load(path).n_tets, min(walls), float(np.median(walls))))
        batch = [command, "improve", *map(str, inputs), "--out-dir", str(tmp / "batch"), "-q"]
        walls = []
        for _ in range(repeat):
            t = time.perf_counter()
            subprocess.run(batch, check=True, capture_output=True)
            walls.append(time.perf_counter() - t)
        same = all(
            (tmp / "single" / p.name).read_bytes() == (tmp / "batch" / p.name).read_bytes()
            for p in inputs
        )
    print(f"\njtet improve IN OUT (new process, warm cache), {repeat} runs\n")
    print("| mesh | tets | min s | median s |\n|---|---|---|---|")
    for name, m, lo, med in rows:
        print(f"| {name} | {m:,} | {lo:.2f} | {med:.2f} |")
    separate = sum(r[3] for r in rows)
    print(f"\n{len(rows)} meshes, one command each (sum of medians): {separate:.2f} s")
    print(
        f"one batch command (--out-dir), min / median of {repeat}: {min(walls):.2f} / "
        f"{np.median(walls):.2f} s, {separate / np.median(walls):.2f}x; "
        f"outputs {'identical' if same else 'DIFFERENT'}"
    )


def compile_overhead(name: str, ops: str, repeat: int) -> None:
    """First improve with an empty cache (cold) and in a second process with the cache
    the first one filled (warm), each against the steady state (the second improve in
    the same process). Minimum over ``repeat`` pairs of fresh processes."""
    cold, warm = [], []
    for _ in range(repeat):
        with tempfile.TemporaryDirectory() as cache:
            cold.append(_compile_run(name, ops, cache))
            warm.append(_compile_run(name, ops, cache))

    def best(rows, k):
        return min(r[k] for r in rows)

    steady = min(best(cold, "steady"), best(warm, "steady"))
    cpu_steady = min(r.get("cpu_steady", float("nan")) for r in cold + warm)

    def cpu_overhead(rows):  # CPU seconds of the first run beyond a steady run's
        return min(r.get("cpu_first", float("nan")) for r in rows) - cpu_steady

    head = [
        "mesh",
        "ops",
        "cold 1st s",
        "warm 1st s",
        "steady s",
        "cold overhead s",
        "warm overhead s",
        "cold / warm overhead CPU s",
        "import jtet s",
        "import _smooth s (in 1st run)",
        "kernels exported / loaded",
        "export s (cold)",
        "compile s (cold)",
        "load s (warm)",
    ]
    nan = float("nan")
    c = {"exported": nan, "export_s": nan, "compile_s": nan} | min(cold, key=lambda r: r["first"])
    w = {"loaded": nan, "export_s": nan, "compile_s": nan} | min(warm, key=lambda r: r["first"])
    row = [
        name,
        ops,
        f"{c['first']:.1f}",
        f"{w['first']:.2f}",
        f"{steady:.2f}",
        f"{c['first'] - steady:.1f}",
        f"{w['first'] - steady:.2f}",
        f"{cpu_overhead(cold):.1f} / {cpu_overhead(warm):.2f}",
        f"{best(cold + warm, 'import_jtet'):.2f}",
        f"{best(cold + warm, 'import_smooth'):.2f}",
        f"{c['exported']} / {w['loaded']}",
        f"{c['export_s']:.1f}",
        f"{c['compile_s']:.1f}",
        f"{w['export_s'] + w['compile_s']:.2f}",
    ]
    lines = [
        f"compile overhead (fresh processes, min of {repeat}; export / compile / load seconds "
        "are summed over the worker threads)",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join("---" for _ in head) + "|",
        "| " + " | ".join(row) + " |",
    ]
    print("\n".join(lines))


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--meshes", default=",".join(MESHES))
    p.add_argument("--ops", default="edge,face,smooth")
    p.add_argument("--time-limit", type=float, default=None)
    p.add_argument(
        "--boundary",
        choices=("fixed", "slide"),
        default="fixed",
        help="improve's boundary option (slide: vertices move inside flat facets and "
        "along straight subsegments, the domain's shape unchanged)",
    )
    p.add_argument(
        "--perturb",
        type=perturb_count,
        default=jtet.Options().perturb,
        metavar="N",
        help="improve's perturb option: up to N kept perturbation rounds after the climb, "
        "or auto (default: jtet's)",
    )
    p.add_argument(
        "--no-insert",
        dest="insert",
        action="store_false",
        help="improve's insert=False: the perturbation rounds add no vertex",
    )
    for end in ("min", "max"):
        p.add_argument(
            f"--goal-{end}-dihedral",
            type=float,
            default=None,
            metavar="DEG",
            help=f"improve's goal_{end}_dihedral option: stop once the mesh meets it",
        )
    p.add_argument(
        "--big", type=int, default=0, help="also run a Delaunay mesh of this many random points"
    )
    p.add_argument(
        "--compile", action="store_true", help="measure compile overhead (cold vs warm cache)"
    )
    p.add_argument(
        "--cli", action="store_true", help="wall time of the jtet improve command (new processes)"
    )
    p.add_argument(
        "--repeat", type=int, default=2, help="--compile: pairs of processes; --cli: runs"
    )
    p.add_argument("--compile-worker", default=None, help=argparse.SUPPRESS)
    p.add_argument(
        "--settings",
        default="",
        help="comma list of MEASURE:GOOD_QUALITY settings to compare, "
        "e.g. min_sine:0.7,biased_min_sine:0.6",
    )
    p.add_argument(
        "--smooth-effort",
        default="",
        help="comma list of ITERSxTRIALS smoothing settings to compare, e.g. 15x6,8x3",
    )
    p.add_argument(
        "--seeds",
        type=int,
        default=0,
        help="quality spread over improve's seeds 0 .. N-1 (and how many meet the target)",
    )
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    ops = tuple(args.ops.split(","))
    names = [m for m in args.meshes.split(",") if m]
    if args.big:
        names.append(f"delaunay:{args.big}")
    if args.compile_worker:
        compile_worker(args.compile_worker, ops)
        return
    if args.cli:
        cli_wall_time(names, args.repeat)
        return
    if args.compile:
        for name in names:
            compile_overhead(name, args.ops, args.repeat)
        return
    if args.smooth_effort:
        smooth_effort(names, ops, args.smooth_effort.split(","))
        return
    if args.settings:
        quality_settings(names, ops, args.settings.split(","))
        return
    options = {"boundary": args.boundary, "perturb": args.perturb, "insert": args.insert}
    goals = {
        f"goal_{end}_dihedral": getattr(args, f"goal_{end}_dihedral") for end in ("min", "max")
    }
    goals = {k: v for k, v in goals.items() if v is not None}
    options.update(goals)
    if args.seeds:
        seed_spread(names, ops, args.seeds, **options)
        return
    rows = []
    for name in names:
        if args.json:  # one run, as a user's (the compile-overhead table times it)
            rows.append(run_one(name, ops, args.time_limit, **options))
            continue
        # the first run compiles the kernels for this mesh's batch shapes (from the
        # persistent cache when warm); the row reports the second, steady-state run
        first = run_one(name, ops, args.time_limit, **options)
        row = run_one(name, ops, args.time_limit, **options)
        row["first_s"] = first["seconds"]
        rows.append(row)
    if args.json:
        print(json.dumps(rows))
        return
    print_table(
        rows,
        f"jtet.improve(ops={ops}), boundary {args.boundary}, perturb {args.perturb}"
        + ("" if args.insert else ", no insertion")
        + "".join(f", {k} {v:g}" for k, v in goals.items())
        + ": wall time of a second run on each mesh "
        "(steady state) and of the first (with compilation)",
    )


if __name__ == "__main__":
    main()
