"""Peak memory of jtet on large meshes: a table of peak RSS per step.

    python experiments/bench_memory.py                     # 1M-tet improve + 5M-tet load
    python experiments/bench_memory.py --ops edge --max-passes 2   # the quick 1M run
    python experiments/bench_memory.py --only load5m       # one measurement

Every measurement runs in its own subprocess, so its peak resident set size
(``resource.getrusage(RUSAGE_SELF).ru_maxrss``, which includes JAX/XLA buffers) belongs to
that step alone; the table also lists the peak of Python-heap allocations (NumPy arrays
register with ``tracemalloc``; XLA's own allocator does not) and the RSS of a bare
``import jtet`` as the baseline. Meshes are generated once into ``--cache`` (default
``$TMPDIR/jtet-bench-memory``):

* ``mesh1m.vtu``: scipy Delaunay of 165,000 random points in the unit cube (~1.1M tets,
  ~40 s to generate);
* ``mesh5m.vtu``: a 95^3 grid of cubes, 6 Kuhn tets each (5.14M tets, 0.88M points), interior
  points perturbed by 25 % of the spacing.

Target (issue 8): improving ~1M tets within 4 GB.
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

# ------------------------------------------------------------------------- workers
# Each worker runs in a fresh interpreter: ``python bench_memory.py --worker NAME ...``
# and prints one JSON line {"seconds", "rss_mb", "py_peak_mb", ...}.


def _save_positive(pts, tets, path) -> int:
    """Reorder the negatively oriented tets (swap two vertices), save the mesh, return the
    number of tets. Generated tets come in either orientation (scipy, the grid's paths)."""
    import numpy as np

    import jtet

    p = pts[tets]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets[vol < 0] = tets[vol < 0][:, [1, 0, 2, 3]]
    mesh = jtet.TetMesh(pts, tets)
    jtet.save(mesh, path)
    return mesh.n_tets


def _rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _worker(name: str, args) -> dict:
    import tracemalloc

    import numpy as np

    cache = Path(args.cache)
    info: dict = {}
    if name == "baseline":
        import jtet  # noqa: F401

        return {"seconds": 0.0, "rss_mb": _rss_mb(), "py_peak_mb": 0.0}
    import jtet

    tracemalloc.start()
    t0 = time.perf_counter()
    if name == "make1m":
        from scipy.spatial import Delaunay

        rng = np.random.default_rng(0)
        pts = rng.random((args.points1m, 3))
        tets = Delaunay(pts).simplices.astype(np.int64)
        info["n_tets"] = _save_positive(pts, tets, cache / "mesh1m.vtu")
    elif name == "make5m":
        n = args.grid5m
        ax = np.linspace(0.0, 1.0, n + 1)
        idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
        pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
        interior = ((pts > 0) & (pts < 1)).all(axis=1)
        rng = np.random.default_rng(0)
        pts[interior] += rng.uniform(-0.25, 0.25, (interior.sum(), 3)) / n
        c = [
            idx[i : i + n, j : j + n, k : k + n].ravel()
            for i in (0, 1)
            for j in (0, 1)
            for k in (0, 1)
        ]
        paths = [(4, 6), (4, 5), (2, 6), (2, 3), (1, 5), (1, 3)]
        tets = np.concatenate([np.stack([c[0], c[a], c[b], c[7]], axis=1) for a, b in paths])
        info["n_tets"] = _save_positive(pts, tets, cache / "mesh5m.vtu")
    elif name in ("load1m", "load5m"):
        mesh = jtet.load(cache / f"mesh{name[4:]}.vtu")
        info["n_tets"] = mesh.n_tets
    elif name == "topology5m":
        mesh = jtet.load(cache / "mesh5m.vtu")
        mesh.topology  # noqa: B018
        info["n_tets"] = mesh.n_tets
    elif name == "improve1m":
        mesh = jtet.load(cache / "mesh1m.vtu")
        opts = jtet.Options(ops=tuple(args.ops.split(",")), max_passes=args.max_passes)
        result = jtet.improve(mesh, opts)
        info.update(
            n_tets=result.mesh.n_tets,
            status=result.status,
            passes=len({h["pass"] for h in result.history}),
            successes=sum(h["successes"] for h in result.history),
            worst_min_sine=(
                result.stats_before.quality_min["min_sine"],
                result.stats_after.quality_min["min_sine"],
            ),
            min_dihedral=(result.stats_before.min_dihedral, result.stats_after.min_dihedral),
        )
    else:
        raise SystemExit(f"unknown worker {name}")
    seconds = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    return {"seconds": seconds, "rss_mb": _rss_mb(), "py_peak_mb": peak / 2**20, **info}


# ---------------------------------------------------------------------------- driver

STEPS = {
    "baseline": "import jtet (baseline)",
    "make1m": "generate 1M (scipy Delaunay) + save",
    "load1m": "load 1M .vtu",
    "improve1m": "load + improve 1M",
    "make5m": "generate 5M (grid) + save",
    "load5m": "load 5M .vtu",
    "topology5m": "load 5M + topology",
}


def _run(name: str, args) -> dict:
    cmd = [sys.executable, __file__, "--worker", name, "--cache", args.cache]
    cmd += ["--ops", args.ops, "--max-passes", str(args.max_passes)]
    cmd += ["--points1m", str(args.points1m), "--grid5m", str(args.grid5m)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr else "failed"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "jtet-bench-memory"))
    ap.add_argument("--ops", default="edge,face,smooth", help="operations of the 1M improve")
    ap.add_argument("--max-passes", type=int, default=50, help="passes of the 1M improve")
    ap.add_argument("--points1m", type=int, default=165_000)
    ap.add_argument("--grid5m", type=int, default=95)
    ap.add_argument("--only", default=None, help="comma-separated steps: " + ",".join(STEPS))
    ap.add_argument("--json", default=None, help="also write the rows to this JSON file")
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(_worker(args.worker, args)))
        return 0

    Path(args.cache).mkdir(parents=True, exist_ok=True)
    steps = list(STEPS) if args.only is None else args.only.split(",")
    rows = {}
    for name in steps:
        if name == "make1m" and (Path(args.cache) / "mesh1m.vtu").exists() and args.only is None:
            continue
        if name == "make5m" and (Path(args.cache) / "mesh5m.vtu").exists() and args.only is None:
            continue
        rows[name] = _run(name, args)
        print(f"{STEPS[name]:36s} {json.dumps(rows[name])}", file=sys.stderr, flush=True)

    print(
        f"\n{'step':36s} {'tets':>10s} {'seconds':>9s} {'peak RSS MB':>12s} {'NumPy peak MB':>14s}"
    )
    for name, r in rows.items():
        if "error" in r:
            print(f"{STEPS[name]:36s} error: {r['error']}")
            continue
        print(
            f"{STEPS[name]:36s} {r.get('n_tets', 0):10d} {r['seconds']:9.1f} "
            f"{r['rss_mb']:12.0f} {r['py_peak_mb']:14.0f}"
        )
    if "improve1m" in rows and "error" not in rows["improve1m"]:
        r = rows["improve1m"]
        print(
            f"\nimprove 1M: ops={args.ops} max_passes={args.max_passes}: status {r['status']}, "
            f"{r['passes']} passes, {r['successes']} successes, worst min-sine "
            f"{r['worst_min_sine'][0]:.4f} -> {r['worst_min_sine'][1]:.4f}, min dihedral "
            f"{r['min_dihedral'][0]:.2f} -> {r['min_dihedral'][1]:.2f} deg; target peak RSS "
            f"<= 4096 MB: {'met' if r['rss_mb'] <= 4096 else 'NOT met'}"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
