"""Benchmark of optimal edge removal (Klincsek kernel); prints tables, asserts nothing.

Run: ``python experiments/bench_edge_removal.py [--quick] [--m 3 4 ...]``.

Tables (one function each, so that more can be added):

* ``table_raw_quality``: the raw SoA min-sine rate over N independent tets, the
  baseline every kernel number is compared against (measured in the same run: this
  machine is shared and noisy).
* ``table_kernel``: per ring size m, compile time and rings/s of the edge-removal kernel
  on realistic rings (jittered regular polygons around an edge): the diagonal DP (default)
  and the ``fori_loop`` DP, device-only; then the host entry ``solve_rings`` with and
  without pruning (screen survival and success fractions alongside); and the equivalent
  candidate-tet rate ``2 C(m,3) * rings/s`` as a fraction of the raw quality rate.
* ``table_ratio``: the same ratio at m = 6 (40 candidate tets per ring), raw and kernel
  timed interleaved so that load changes hit both alike; the target is >= 50 %.
* ``table_layout``: why the batch entries do not use ``jax.vmap``: the same kernel vmapped
  (batch axis first) against the chunked batch-minor layout, at one m.
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import jtet  # noqa: F401  (float64, compilation cache)
from jtet._kernels import klincsek as kl
from jtet._quality import MEASURES, min_sine


def best_time(fn, reps: int = 3) -> float:
    """Best wall time of ``reps`` calls of ``fn`` (already compiled)."""
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def realistic_rings(n: int, m: int, seed: int = 0, jitter: float = 0.15):
    """``n`` rings of size ``m`` around edges, as a mesh optimizer meets them.

    A regular m-gon of radius 1 in z = 0, counterclockwise seen from ``a`` above, with
    ``a``, ``b`` on the axis at heights ~ +-(ring edge length), every point jittered by
    ``jitter`` ring-edge lengths. Returns ``a (n,3), b (n,3), ring (n,m,3), q_old (n,)``
    with ``q_old`` the min-sine quality of the old tets ``(a, b, v_{i+1}, v_i)``.
    """
    rng = np.random.default_rng(seed)
    h = 2 * math.sin(math.pi / m)
    th = 2 * np.pi * (np.arange(m) + rng.uniform(-jitter, jitter, (n, m))) / m
    ring = np.stack([np.cos(th), np.sin(th), np.zeros((n, m))], -1)
    ring += jitter * h * rng.standard_normal((n, m, 3))
    a = np.array([0, 0, h]) * rng.uniform(0.6, 1.4, (n, 1)) + jitter * h * rng.standard_normal(
        (n, 3)
    )
    b = np.array([0, 0, -h]) * rng.uniform(0.6, 1.4, (n, 1)) + jitter * h * rng.standard_normal(
        (n, 3)
    )
    nxt = np.roll(ring, -1, axis=1)

    def soa(p):
        return tuple(jnp.asarray(p[..., c]) for c in range(3))

    ab = np.broadcast_to
    q = MEASURES["min_sine"](
        soa(ab(a[:, None], ring.shape)), soa(ab(b[:, None], ring.shape)), soa(nxt), soa(ring)
    )
    return a, b, ring, np.asarray(q).min(axis=1)


def table_raw_quality(n_tets: int = 4_000_000) -> float:
    """Raw SoA min-sine throughput (tets/s); prints one line and returns the rate."""
    rng = np.random.default_rng(1)
    pts = [tuple(jnp.asarray(rng.random(n_tets)) for _ in range(3)) for _ in range(4)]
    f = jax.jit(min_sine)
    jax.block_until_ready(f(*pts))
    dt = best_time(lambda: jax.block_until_ready(f(*pts)), reps=5)
    rate = n_tets / dt
    print(
        f"raw SoA min_sine: {n_tets / 1e6:.0f}M tets in {dt * 1e3:.1f} ms = {rate / 1e6:.1f}M tets/s"
    )
    return rate


def _timed_compile(fn) -> float:
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - t0


def _kernel_row(m: int, n: int, raw_rate: float, measure: str) -> dict:
    a, b, ring, q_old = realistic_rings(n, m, seed=m)
    cap = jtet._config.bucket_capacity(n, 2 * kl.CHUNK)
    soa = [jnp.asarray(x) for x in kl.to_chunks(a, b, ring, cap)]
    q_pad = jnp.asarray(np.pad(q_old, (0, cap - n), constant_values=np.inf).reshape(-1, kl.CHUNK))
    row = {"m": m, "rings": n}

    def device(form):
        return lambda: jax.block_until_ready(kl.solve_chunks(*soa, measure=measure, form=form))

    row["compile"] = _timed_compile(device("diagonal"))
    row["compile_loop"] = _timed_compile(device("loop"))
    row["diagonal"] = n / best_time(device("diagonal"))
    row["loop"] = n / best_time(device("loop"))

    def host(prune):
        return lambda: kl.solve_rings(a, b, ring, q_old, measure, prune=prune)

    for prune in (False, "quality", "volume"):
        host(prune)()  # compile (stage 2 capacity depends on the survivors)
        row[f"host_{prune}"] = n / best_time(host(prune))
    q_new, _ = kl.solve_rings(a, b, ring, q_old, measure, prune=False)
    row["succ"] = float(np.mean(q_new > q_old))
    for mode in ("quality", "volume"):
        alive = kl.screen_chunks(*soa, q_pad, measure=measure, mode=mode)
        row[f"surv_{mode}"] = float(np.asarray(alive).reshape(-1)[:n].mean())
    q_p, _ = kl.solve_rings(a, b, ring, q_old, measure, prune=True)
    win = q_new > q_old
    assert np.array_equal(q_p > q_old, win) and np.array_equal(q_p[win], q_new[win])
    row["tets_rate"] = row["diagonal"] * 2 * math.comb(m, 3)
    row["ratio"] = row["tets_rate"] / raw_rate
    return row


def table_kernel(ms, n_rings: dict, raw_rate: float, measure: str = "min_sine") -> dict:
    """Rings/s per m (see module docstring); returns {m: row dict}."""
    print(f"\nkernel ({measure}): rates in M rings/s, compile in s (cold, both maps)")
    print(
        f"{'m':>3} {'rings':>6} {'compile':>7} {'c.loop':>6} {'diag':>8} {'loop':>8} "
        f"{'host':>8} {'pruned':>8} {'p.vol':>8} {'surv':>5} {'s.vol':>5} {'succ':>6} "
        f"{'tets/s':>7} {'/raw':>5}"
    )
    rows = {}
    for m in ms:
        r = rows[m] = _kernel_row(m, n_rings.get(m, 1 << 15), raw_rate, measure)
        print(
            f"{m:>3} {r['rings']:>6} {r['compile']:>7.2f} {r['compile_loop']:>6.2f} "
            f"{r['diagonal'] / 1e6:>8.3f} {r['loop'] / 1e6:>8.3f} "
            f"{r['host_False'] / 1e6:>8.3f} {r['host_quality'] / 1e6:>8.3f} "
            f"{r['host_volume'] / 1e6:>8.3f} {r['surv_quality']:>5.2f} {r['surv_volume']:>5.2f} "
            f"{r['succ']:>6.3f} {r['tets_rate'] / 1e6:>6.1f}M {r['ratio']:>5.0%}",
            flush=True,
        )
    print(
        "diag / loop: device-only solve_chunks, unrolled-diagonal vs fori_loop DP (compile,"
        " c.loop: cold compile s); host: solve_rings(prune=False); pruned: prune='quality'"
        " (a-side quality + DP bound; what prune=True does for m >= PRUNE_MIN_M; below"
        " that host rows run the padded kernel of rings up to PAD_M, unpruned);"
        " p.vol: prune='volume'; surv / s.vol: fraction of"
        " rings passing each screen; succ: fraction with q_new > q_old; tets/s: 2 C(m,3)"
        " candidate tets per ring x diag rate; /raw: that over the raw quality rate."
    )
    return rows


def table_ratio(m: int = 6, n: int = 1 << 16, n_tets: int = 4_000_000, rounds: int = 7) -> float:
    """Kernel tets/s over raw quality tets/s at one m, timed interleaved (noisy machine).

    Alternates one raw min-sine call over ``n_tets`` independent tets and one device-only
    kernel call over ``n`` realistic rings, ``rounds`` times; best time of each.
    """
    rng = np.random.default_rng(1)
    pts = [tuple(jnp.asarray(rng.random(n_tets)) for _ in range(3)) for _ in range(4)]
    raw = jax.jit(min_sine)
    a, b, ring, _ = realistic_rings(n, m, seed=m)
    soa = [jnp.asarray(x) for x in kl.to_chunks(a, b, ring, n)]
    runs = {
        "raw": lambda: jax.block_until_ready(raw(*pts)),
        "kernel": lambda: jax.block_until_ready(kl.solve_chunks(*soa, measure="min_sine")),
    }
    for f in runs.values():
        f()
    best = {k: np.inf for k in runs}
    for _ in range(rounds):
        for k, f in runs.items():
            best[k] = min(best[k], best_time(f, reps=1))
    raw_rate = n_tets / best["raw"]
    tets = 2 * math.comb(m, 3)
    kern_rate = n * tets / best["kernel"]
    print(
        f"\nratio at m={m} (interleaved, best of {rounds}): raw {raw_rate / 1e6:.1f}M tets/s, "
        f"kernel {n / best['kernel'] / 1e6:.3f}M rings/s x {tets} tets = "
        f"{kern_rate / 1e6:.1f}M tets/s -> {kern_rate / raw_rate:.0%} of raw"
    )
    return kern_rate / raw_rate


def table_layout(m: int = 6, n: int = 1 << 14, measure: str = "min_sine") -> None:
    """jax.vmap of the one-ring kernel (batch axis first) vs the chunked batch-minor entry."""
    a, b, ring, _ = realistic_rings(n, m, seed=99)
    kern = jax.jit(
        jax.vmap(lambda *x: kl.ring_kernel(*x, m=m, measure=measure)),
    )
    args = [jnp.asarray(x) for x in (*a.T, *b.T)] + [jnp.asarray(ring[..., c]) for c in range(3)]
    c_vmap = _timed_compile(lambda: kern(*args))
    r_vmap = n / best_time(lambda: jax.block_until_ready(kern(*args)))
    soa = [jnp.asarray(x) for x in kl.to_chunks(a, b, ring, n)]
    c_chunk = _timed_compile(lambda: kl.solve_chunks(*soa, measure=measure))
    r_chunk = n / best_time(lambda: jax.block_until_ready(kl.solve_chunks(*soa, measure=measure)))
    print(f"\nlayout at m={m} ({n} rings): M rings/s (compile s)")
    print(f"  jax.vmap, batch axis first:      {r_vmap / 1e6:8.3f} ({c_vmap:.1f})")
    print(f"  chunked, batch axis minor:       {r_chunk / 1e6:8.3f} ({c_chunk:.1f})")


def table_full_pass(n_points: int) -> None:
    """One full edge-removal pass over a Delaunay mesh of ``n_points`` random points.

    ~165k points give ~1.1M tets (target: one pass <= 10 s on 2 cores, <= 4 GB). The
    first pass compiles the kernels for the capacities it meets, so it is run twice on
    the same mesh and both are reported; peak RSS is the process's high-water mark.
    """
    import resource
    import time

    from scipy.spatial import Delaunay

    import jtet
    from jtet._edge_removal import edge_removal_pass
    from jtet._topology import Topology

    rng = np.random.default_rng(0)
    pts = rng.random((n_points, 3))
    tets = Delaunay(pts).simplices.astype(np.int64)
    p = pts[tets]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets[vol < 0] = tets[vol < 0][:, [1, 0, 2, 3]]
    mesh = jtet.TetMesh(pts, tets[np.abs(vol) > 1e-15])
    print(f"\nfull pass: Delaunay mesh of {mesh.n_tets:,} tets ({n_points:,} points)")
    print(f"{'step':<36}{'seconds':>9}")
    print("-" * 45)
    t0 = time.perf_counter()
    Topology.build(mesh)
    print(f"{'topology (build)':<36}{time.perf_counter() - t0:>9.2f}")
    t0 = time.perf_counter()
    q = mesh.quality("min_sine")
    print(f"{'quality of every tet':<36}{time.perf_counter() - t0:>9.2f}")
    for label in ("edge pass, first (with compiles)", "edge pass, second (compiled)"):
        m2 = jtet.TetMesh(mesh.points, mesh.tets)  # fresh mesh: topology not cached
        t0 = time.perf_counter()
        out, stats, _ = edge_removal_pass(m2, quality=q)
        dt = time.perf_counter() - t0
        print(
            f"{label:<36}{dt:>9.2f}   {stats.attempts:,} edges tried, {stats.successes:,} removed"
        )
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    print(f"peak RSS of the process: {peak:.2f} GB (targets: pass <= 10 s, <= 4 GB)")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--m", type=int, nargs="*", default=list(range(3, 13)))
    ap.add_argument("--quick", action="store_true", help="small batches (smoke run)")
    ap.add_argument("--no-layout", action="store_true")
    ap.add_argument(
        "--full-pass",
        type=int,
        default=165_000,
        metavar="POINTS",
        help="points of the Delaunay mesh for the full-pass table (0: skip)",
    )
    args = ap.parse_args(argv)
    print(f"jax {jax.__version__}, devices {jax.devices()}")
    raw = table_raw_quality(1_000_000 if args.quick else 4_000_000)
    if args.quick:
        sizes = {m: 4096 for m in args.m}
    else:
        sizes = {m: (1 << 16 if m <= 8 else 1 << 15) for m in args.m}
    table_kernel(args.m, sizes, raw)
    table_ratio(n=4096 if args.quick else 1 << 16, n_tets=1_000_000 if args.quick else 4_000_000)
    if not args.no_layout:
        table_layout(n=4096 if args.quick else 1 << 14)
    if args.full_pass:
        table_full_pass(20_000 if args.quick else args.full_pass)


if __name__ == "__main__":
    main()
