"""Benchmark of vertex smoothing (jtet._smooth): solvers, batch vs loop, passes on a sliver mesh.

Usage:  python experiments/bench_smooth.py [--mesh PATH.vtu] [--passes 5] [--solvers a,b]
        [--loop 64] [--quick]
        python experiments/bench_smooth.py --calls 40 [--mesh PATH.vtu]   # table 4 only

Tables (all timings in the same process, warm: each kernel is compiled before timing):

1. Kernel throughput per solver on every interior star of the mesh (stars taken as they
   are, not an independent set: this measures the kernel alone): vertices per second in
   padded vmapped batches of 64 vs a Python loop over single jitted solves (same kernel,
   ``--loop`` vertices), compile time, mean star-minimum gain and how often the solver's
   answer is within 1e-3 of the best of all solvers (per vertex).
2. Smoothing passes alone (no flips) with the fixed boundary: worst / max dihedral angle
   and worst min-sine after each pass, seconds per pass, and the best worst-quality
   reached per second of smoothing.
3. The default solver (``active_set``) with ``boundary="slide"``.
4. (``--calls N``) What one call of the optimizer's smoothing kernel costs, by the number
   of stars it holds: ``smooth_pass``'s own shapes (K = 56 in 32-lane calls run as lane
   groups of 8; 128 stars at K = 32), against one-lane calls (one per star, on the worker
   threads), medians over N calls of random interior stars, host work included; and how
   many new positions the one-lane calls reproduce to the bit. The late passes and the
   perturbation rounds' climbs make mostly calls of 1-3 stars.
"""

from __future__ import annotations

import argparse
import functools
import inspect
import os
import sys
import time

import jax
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import jtet  # noqa: E402
from jtet._quality import tet_dihedrals  # noqa: E402
from jtet._smooth import (  # noqa: E402
    SOLVERS,
    batched_smoother,
    gather_stars,
    motion_bases,
    smooth_pass,
    smooth_star,
    star_faces,
)

DEFAULT_MESH = "/work/shared/meshes/gmsh_cube.vtu"


def load_mesh(path: str | None) -> tuple[jtet.TetMesh, str]:
    if path and os.path.exists(path):
        import pyvista as pv

        return jtet.TetMesh.from_pyvista(pv.read(path)), os.path.basename(path)
    from jtet import _io

    if hasattr(_io, "demo_mesh"):
        return _io.demo_mesh(), "demo_mesh"
    raise SystemExit(f"no mesh: {path!r} does not exist and jtet._io has no demo_mesh")


def dihedral_summary(mesh: jtet.TetMesh) -> tuple[float, float, float]:
    _, lo, hi = tet_dihedrals(mesh.points, mesh.tets)
    return float(lo.min()), float(hi.max()), float(mesh.quality("min_sine").min())


def kernel_table(mesh, solvers, loop_n: int, batch: int = 64):
    ptr, opp_ids = star_faces(mesh)
    basis, movable, _ = motion_bases(mesh, "fixed")
    size = np.diff(ptr)
    rows = []
    results = {}
    for K in (32, 64):
        lo = 0 if K == 32 else 32
        verts = np.flatnonzero(movable & (size > lo) & (size <= K))
        if len(verts) == 0:
            continue
        nb = -(-len(verts) // batch) * batch
        padded = np.resize(verts, nb)
        opp, mask = gather_stars(padded, K, mesh.points, ptr, opp_ids)
        v0, bs = mesh.points[padded], basis[padded]
        for solver in solvers:
            kern = batched_smoother("min_sine", solver, 15)
            t = time.perf_counter()
            jax.block_until_ready(kern(v0[:batch], bs[:batch], opp[:batch], mask[:batch]))
            t_compile = time.perf_counter() - t
            t = time.perf_counter()
            outs = [
                kern(v0[s : s + batch], bs[s : s + batch], opp[s : s + batch], mask[s : s + batch])
                for s in range(0, nb, batch)
            ]
            jax.block_until_ready(outs)
            t_batch = time.perf_counter() - t
            q_old = np.concatenate([np.asarray(o[1]) for o in outs])[: len(verts)]
            q_new = np.concatenate([np.asarray(o[2]) for o in outs])[: len(verts)]
            single = jax.jit(functools.partial(smooth_star, measure="min_sine", solver=solver))
            jax.block_until_ready(single(v0[0], bs[0], opp[0], mask[0]))
            m = min(loop_n, len(verts))
            t = time.perf_counter()
            for i in range(m):
                jax.block_until_ready(single(v0[i], bs[i], opp[i], mask[i]))
            t_loop = (time.perf_counter() - t) / m
            results[(K, solver)] = q_new
            rows.append(
                dict(
                    K=K,
                    solver=solver,
                    n=len(verts),
                    compile_s=t_compile,
                    batch_vps=len(verts) / t_batch,
                    loop_vps=1.0 / t_loop,
                    gain=float(np.mean(q_new - q_old)),
                    q_new=float(np.mean(q_new)),
                )
            )
            print(f"  [kernel K={K} {solver}: {rows[-1]['batch_vps']:.0f} v/s]", flush=True)
    # agreement with the best solver per vertex
    for r in rows:
        best = np.max([results[(r["K"], s)] for s in solvers], axis=0)
        r["near_best"] = float(np.mean(results[(r["K"], r["solver"])] >= best - 1e-3))
    print()
    print("Table 1. Kernel throughput, one solve per interior star (warm, same process)")
    print(
        f"{'K':>3} {'solver':<11} {'stars':>6} {'compile s':>9} {'batch v/s':>10} "
        f"{'loop v/s':>9} {'ratio':>6} {'mean gain':>9} {'mean q':>7} {'near best':>9}"
    )
    for r in rows:
        print(
            f"{r['K']:>3} {r['solver']:<11} {r['n']:>6} {r['compile_s']:>9.1f} "
            f"{r['batch_vps']:>10.0f} {r['loop_vps']:>9.0f} {r['batch_vps'] / r['loop_vps']:>6.1f} "
            f"{r['gain']:>9.4f} {r['q_new']:>7.4f} {r['near_best']:>9.2f}"
        )
    return rows


def pass_table(mesh, solvers, passes: int, boundary: str = "fixed"):
    print()
    print(
        f"Table 2{'b' if boundary == 'slide' else ''}. Smoothing passes alone, boundary={boundary}"
    )
    lo, hi, q = dihedral_summary(mesh)
    print(f"  input: worst dihedral {lo:.2f}, max {hi:.2f}, worst min-sine {q:.4f}")
    print(
        f"{'solver':<11} {'pass':>4} {'seconds':>8} {'tried':>6} {'moved':>6} {'colours':>7} "
        f"{'worst dih':>9} {'max dih':>8} {'min-sine':>9} {'free worst dih':>14}"
    )
    summary = []
    kind = mesh.topology.vertex_kind
    # tets with a vertex the pass may move: the ones smoothing can improve at all
    movable_tet = (kind[mesh.tets] == 0).any(axis=1)
    for solver in solvers:
        # warm-up on a copy: compile every (K, batch) variant the passes will use
        smooth_pass(mesh, solver=solver, boundary=boundary)
        m = mesh
        total = 0.0
        for p in range(passes):
            m, st = smooth_pass(m, solver=solver, boundary=boundary)
            total += st.seconds
            lo, hi, q = dihedral_summary(m)
            _, lo_t, _ = tet_dihedrals(m.points, m.tets[movable_tet])
            print(
                f"{solver:<11} {p + 1:>4} {st.seconds:>8.2f} {st.attempts:>6} "
                f"{st.successes:>6} {st.n_colours:>7} {lo:>9.2f} {hi:>8.2f} {q:>9.4f} "
                f"{float(lo_t.min()):>14.2f}",
                flush=True,
            )
        summary.append((solver, total, lo, hi, q, float(lo_t.min())))
    print()
    print("  per solver after all passes: seconds, worst/max dihedral, min-sine, free-tet worst")
    for s, total, lo, hi, q, lf in summary:
        print(f"  {s:<11} {total:7.2f} s  {lo:6.2f} / {hi:6.2f}  {q:.4f}  {lf:6.2f}")
    return summary


def call_table(mesh, reps: int, measure: str = "biased_min_sine", seed: int = 0) -> list[dict]:
    """Table 4: median wall time of a smoothing kernel call by stars per call (see the
    module docstring). Returns one row per star count."""
    from jtet._config import parallel_map
    from jtet._smooth import _KERNEL_OPTIONS, LARGE_CAPACITY, _pass_kernel, _solve_batch

    params = inspect.signature(smooth_pass).parameters
    kernel = _pass_kernel(measure, *(params[k].default for k in _KERNEL_OPTIONS))
    small, large = params["batch_sizes"].default
    K = min(params["capacities"].default)
    ptr, opp_ids = star_faces(mesh)
    basis, movable, _ = motion_bases(mesh, "fixed")
    size = np.diff(ptr)
    pts = np.array(mesh.points)
    rng = np.random.default_rng(seed)
    stars = rng.permutation(np.flatnonzero(movable & (size > 0) & (size <= K)))
    fits = stars[size[stars] <= LARGE_CAPACITY]

    def batch_call(chunk, cap, lanes):
        return _solve_batch(kernel, cap, lanes, chunk, pts, basis, ptr, opp_ids)

    def one_lane_calls(chunk):
        outs = parallel_map(lambda v: batch_call(np.array([v]), K, 1), list(chunk))
        return np.concatenate([o[0] for o in outs]), np.concatenate([o[1] for o in outs])

    # build (or load) every shape before timing
    batch_call(stars[:1], K, small)
    if len(fits) >= large:
        batch_call(fits[:large], LARGE_CAPACITY, large)
    one_lane_calls(stars[:1])
    rows = []
    for b in (1, 2, 3, 8, 16, 32, large):
        pool = fits if b == large else stars
        if len(pool) < b:
            continue
        cap, lanes = (LARGE_CAPACITY, large) if b == large else (K, small)
        t_batch, t_one, same, moved = [], [], 0, 0
        for r in range(reps):
            start = (r * 37) % max(1, len(pool) - b + 1)
            chunk = pool[start : start + b]
            t = time.perf_counter()
            ids, pos = batch_call(chunk, cap, lanes)
            t_batch.append(time.perf_counter() - t)
            if b <= 8:
                t = time.perf_counter()
                ids1, pos1 = one_lane_calls(chunk)
                t_one.append(time.perf_counter() - t)
                mine = dict(zip(ids.tolist(), pos))
                theirs = dict(zip(ids1.tolist(), pos1))
                moved += len(set(mine) | set(theirs))
                same += sum(
                    1 for v in set(mine) & set(theirs) if np.array_equal(mine[v], theirs[v])
                )
        rows.append(
            dict(
                stars=b,
                shape=f"K={cap}, {lanes} lanes",
                batch_ms=1e3 * float(np.median(t_batch)),
                one_lane_ms=1e3 * float(np.median(t_one)) if t_one else None,
                same=same / moved if moved else None,
            )
        )
    print()
    print(f"Table 4. Smoothing kernel calls ({measure}), medians of {reps} calls, host included")
    print(
        f"{'stars':>5} {'shape':<18} {'ms/call':>8} {'us/star':>8} {'one-lane ms':>11} {'same':>5}"
    )
    for r in rows:
        one = "-" if r["one_lane_ms"] is None else f"{r['one_lane_ms']:.2f}"
        same = "-" if r["same"] is None else f"{r['same']:.2f}"
        print(
            f"{r['stars']:>5} {r['shape']:<18} {r['batch_ms']:>8.2f} "
            f"{1e3 * r['batch_ms'] / r['stars']:>8.0f} {one:>11} {same:>5}"
        )
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default=DEFAULT_MESH)
    ap.add_argument("--passes", type=int, default=5)
    ap.add_argument("--solvers", default=",".join(SOLVERS))
    ap.add_argument("--loop", type=int, default=64, help="vertices in the Python-loop baseline")
    ap.add_argument("--no-slide", action="store_true")
    ap.add_argument("--calls", type=int, default=0, help="table 4 only, with this many calls")
    args = ap.parse_args(argv)
    solvers = [s for s in args.solvers.split(",") if s]
    mesh, name = load_mesh(args.mesh)
    kinds = np.bincount(mesh.topology.vertex_kind, minlength=4)
    print(
        f"mesh {name}: {mesh.n_points} points, {mesh.n_tets} tets, vertex kinds "
        f"free/surface/segment/corner = {kinds.tolist()}; jax {jax.__version__}, "
        f"{os.cpu_count()} cpus, load {os.getloadavg()[0]:.1f}"
    )
    if args.calls:
        call_table(mesh, args.calls)
        return
    kernel_table(mesh, solvers, args.loop)
    pass_table(mesh, solvers, args.passes)
    if not args.no_slide:
        default = "active_set" if "active_set" in solvers else solvers[0]
        pass_table(mesh, [default], args.passes, boundary="slide")


if __name__ == "__main__":
    main()
