"""What carrying point data through ``jtet.improve`` costs, and how exact it is.

For each mesh: runs without point data and with three linear fields (a float64 scalar,
a float32 vector, an int32 marker) and a curved one (``S``), alternating, in this process, after a warm-up run
that compiles; prints the median run times, their ratio, the seconds of the carrying itself
(barycentric weights in the input tets around each moved vertex, a k-d tree for the
integer array), how many vertices moved or were inserted, and the largest error of the
scalar field against its closed form at the output's vertices (the interpolation is
linear in a tet, so a linear field comes out exact to rounding). The baseline, in the
same process: VTK's probe filter over every input tet at the same positions (what
jtet used before), its seconds, and at how many positions the two differ on a curved
field (the probe's cells have a tolerance: near a face it may extrapolate from the tet
beyond). With ``--big N``: the carrying alone on a Delaunay mesh of N random points
(N = 165000: ~1.1M tets) whose free vertices are moved at random, with its peak RSS.

    python experiments/bench_point_data.py                  # the four reference meshes
    python experiments/bench_point_data.py --meshes demo --big 165000
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_improve import MESHES, load_mesh  # noqa: E402

import jtet  # noqa: E402
from jtet._point_data import _probed, carried_point_data, moved_vertices  # noqa: E402

A = np.array([1.3, -0.7, 2.1])


def _fields(mesh: jtet.TetMesh) -> dict:
    lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    unit = (mesh.points - lo) / (hi - lo)  # O(1) values: the error is absolute
    return (
        {
            "T": unit @ A,
            "u": unit.astype(np.float32),
            "marker": np.arange(mesh.n_points, dtype=np.int32) % 7,
            "S": np.sin(3 * unit[:, 0]) * np.exp(unit[:, 1]) + unit[:, 2] ** 2,  # curved
        },
        lo,
        hi,
    )


def run_mesh(name: str, seed: int, repeat: int) -> dict:
    mesh = load_mesh(name)
    fields, lo, hi = _fields(mesh)
    with_data = mesh.replace(point_data=fields)
    jtet.improve(mesh, seed=seed)  # compiles this mesh's batch shapes
    t_plain, t_data = [], []
    for _ in range(repeat):  # alternating, so a noisy stretch hits both
        t0 = time.perf_counter()
        plain = jtet.improve(mesh, seed=seed)
        t_plain.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        carried = jtet.improve(with_data, seed=seed)
        t_data.append(time.perf_counter() - t0)
    t_plain, t_data = float(np.median(t_plain)), float(np.median(t_data))
    t0 = time.perf_counter()
    carried_point_data(with_data, carried.mesh)  # the carrying alone, once more
    t_carry = time.perf_counter() - t0
    out = carried.mesh
    moved = moved_vertices(with_data, out)
    t0 = time.perf_counter()
    probed, found, _ = _probed(with_data, {"S": fields["S"]}, out.points[moved])
    t_probe = time.perf_counter() - t0
    differ = np.abs(probed["S"] - out.point_data["S"][moved]) > 1e-12
    unit = (out.points - lo) / (hi - lo)
    same = np.array_equal(out.points, plain.mesh.points) and np.array_equal(
        out.tets, plain.mesh.tets
    )
    return {
        "mesh": name,
        "tets": mesh.n_tets,
        "moved": int(moved_vertices(with_data, out).sum()),
        "new": out.n_points - mesh.n_points,
        "plain_s": t_plain,
        "data_s": t_data,
        "carry_s": t_carry,
        "probe_s": t_probe,
        "differ": int((differ & found).sum()),
        "differ_max": float(np.abs(probed["S"] - out.point_data["S"][moved])[found].max()),
        "error": float(np.abs(out.point_data["T"] - unit @ A).max()),
        "same": same,
    }


def run_big(n_points: int) -> dict:
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(0)
    p = rng.random((n_points, 3))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # qhull's vertex orders, fixed by from_arrays
        mesh = jtet.TetMesh.from_arrays(p, Delaunay(p).simplices)
    fields, lo, hi = _fields(mesh)
    mesh = mesh.replace(point_data=fields)
    moved = mesh.points.copy()
    free = mesh.topology.vertex_kind == 0
    # a move a tenth of the spacing: most stay in their stars, some leave the mesh
    moved[free] += rng.normal(scale=0.1 * n_points ** (-1 / 3), size=(int(free.sum()), 3))
    after = mesh.replace(points=moved, point_data=None)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    data, outside = carried_point_data(mesh, after)
    seconds = time.perf_counter() - t0
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    probed, found, _ = _probed(mesh, {"S": fields["S"]}, moved[free])
    probe_s = time.perf_counter() - t0
    differ = (np.abs(probed["S"] - data["S"][free]) > 1e-12) & found
    return {
        "tets": mesh.n_tets,
        "moved": int(free.sum()),
        "outside": outside,
        "seconds": seconds,
        "rss": (rss0, rss1),
        "probe_s": probe_s,
        "differ": int(differ.sum()),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", default=",".join(MESHES))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3, help="runs of each kind (medians)")
    ap.add_argument("--big", type=int, default=0, help="points of a Delaunay mesh (0: none)")
    args = ap.parse_args(argv)
    rows = [run_mesh(name, args.seed, args.repeat) for name in args.meshes.split(",") if name]
    if rows:
        print(
            f"{'mesh':16} {'tets':>7} {'moved':>6} {'new':>4} {'plain s':>8} {'data s':>7} "
            f"{'ratio':>6} {'carry s':>8} {'max error':>10}  same run  {'probe s':>8} "
            f"{'differ':>6} {'by up to':>8}"
        )
    for r in rows:
        print(
            f"{r['mesh']:16} {r['tets']:7d} {r['moved']:6d} {r['new']:4d} {r['plain_s']:8.2f} "
            f"{r['data_s']:7.2f} {r['data_s'] / r['plain_s']:6.2f} {r['carry_s']:8.3f} "
            f"{r['error']:10.1e}  {'yes' if r['same'] else 'NO ':8} {r['probe_s']:8.3f} "
            f"{r['differ']:6d} {r['differ_max']:8.1e}"
        )
    if args.big:
        b = run_big(args.big)
        print(
            f"\ncarrying alone, Delaunay mesh of {b['tets']} tets: {b['moved']} vertices moved "
            f"({b['outside']} out of the mesh) in {b['seconds']:.2f} s; peak RSS "
            f"{b['rss'][0]:.0f} -> {b['rss'][1]:.0f} MB; VTK's probe alone at the same "
            f"positions {b['probe_s']:.2f} s, differing at {b['differ']}"
        )
    return 0 if all(r["same"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
