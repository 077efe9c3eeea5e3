"""Foundation benchmarks: throughput of jtet's per-tet kernels (one table per function).

    python experiments/bench_foundation.py [--tets 10000000] [--repeat 3] [--tables quality]

``quality`` table, one row per measure of ``jtet.MEASURES`` plus the dihedral-angle kernel,
rates in M tets/s, best of ``--repeat`` after a warm-up call (compilation excluded):

* ``jax 1 call``: the jitted ``jtet._quality`` function on device-resident SoA arrays
  (x, y, z of each corner as separate vectors) holding all ``--tets`` tets, one call;
* ``jax batches``: the same tets as pre-split batches of 2^20 (the optimizer's regime:
  many moderate calls, whose output buffers the allocator recycles; a single huge output
  pays first-touch page faults);
* ``numpy``: the straightforward NumPy formula on (m, 3) vectors (``np.cross``,
  ``np.linalg.norm``, ``np.cbrt``), measured in the same run on min(--tets, 1M) tets;
* ``speed-up``: best jax rate / numpy rate; ``max |diff|``: the two agree (generic tets).

Machines here are shared and noisy: compare columns of one run, not runs. The issue's
target for the quality kernels is >= 20M tets/s.

Add a table: write ``def <name>_table(args) -> None`` that prints it, register it in
``TABLES``; ``--tets`` is the problem size every table should honour.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import jax
import numpy as np

import jtet  # noqa: F401  (float64)
from jtet import _quality as Q

BATCH = 1 << 20
NUMPY_MAX = 1_000_000


def best_time(fn, repeat: int) -> float:
    """Smallest wall time of ``repeat`` calls of ``fn`` (which must block until done)."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def random_soa(n: int, seed: int = 0) -> list[list[np.ndarray]]:
    """Four corners x three coordinates of n independent uniform random tets: (n,) each."""
    rng = np.random.default_rng(seed)
    return [[rng.random(n) for _ in range(3)] for _ in range(4)]


# ---------------------------------------------------------------------------------------
# NumPy baselines: the textbook array-of-structures formulas.

_FACES = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))
_EDGE_FACES = ((2, 3), (1, 3), (1, 2), (0, 3), (0, 2), (0, 1))
_EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
_SIN_REGULAR = 2 * math.sqrt(2) / 3


def _np_parts(p):
    d = np.einsum("ij,ij->i", p[1] - p[0], np.cross(p[2] - p[0], p[3] - p[0]))
    n = [np.cross(p[b] - p[a], p[c] - p[a]) for a, b, c in _FACES]
    return d, n


def np_min_sine(p):
    d, n = _np_parts(p)
    nl = [np.linalg.norm(v, axis=1) for v in n]
    s = [np.linalg.norm(np.cross(n[f], n[g]), axis=1) / (nl[f] * nl[g]) for f, g in _EDGE_FACES]
    return np.sign(d) * np.min(s, axis=0) / _SIN_REGULAR


def np_radius_ratio(p):
    d, n = _np_parts(p)
    a, b, c = p[1] - p[0], p[2] - p[0], p[3] - p[0]
    w = (
        np.sum(a * a, 1)[:, None] * np.cross(b, c)
        + np.sum(b * b, 1)[:, None] * np.cross(c, a)
        + np.sum(c * c, 1)[:, None] * np.cross(a, b)
    )
    area = sum(np.linalg.norm(v, axis=1) for v in n)
    return 6 * d * np.abs(d) / (area * np.linalg.norm(w, axis=1))


def np_vol_length(p):
    d = _np_parts(p)[0]
    lsq = sum(np.sum((p[j] - p[i]) ** 2, axis=1) for i, j in _EDGES) / 6
    return math.sqrt(2) * d / lsq**1.5


def np_mean_ratio(p):
    d = _np_parts(p)[0]
    ssq = sum(np.sum((p[j] - p[i]) ** 2, axis=1) for i, j in _EDGES)
    return 12 * np.sign(d) * np.cbrt(0.25 * d * d) / ssq


def np_dihedral(p):
    d, n = _np_parts(p)
    return [
        np.degrees(
            np.arctan2(
                np.linalg.norm(np.cross(n[f], n[g]), axis=1), -np.einsum("ij,ij->i", n[f], n[g])
            )
        )
        for f, g in _EDGE_FACES
    ]


NUMPY = {
    "min_sine": np_min_sine,
    "radius_ratio": np_radius_ratio,
    "vol_length": np_vol_length,
    "mean_ratio": np_mean_ratio,
    "dihedral angles": np_dihedral,
}


# ---------------------------------------------------------------------------------------
# Tables


def quality_table(args) -> None:
    n = args.tets
    host = random_soa(n)
    dev = [tuple(jax.device_put(c) for c in corner) for corner in host]
    batches = [
        [tuple(jax.device_put(c[s : s + BATCH]) for c in corner) for corner in host]
        for s in range(0, n, BATCH)
    ]
    n_np = min(n, NUMPY_MAX)
    aos = [np.stack([c[:n_np] for c in corner], axis=1) for corner in host]
    kernels = dict(Q.MEASURES)
    kernels["dihedral angles"] = Q.dihedral_angles

    print(f"quality kernels: {n:,} random tets, SoA float64, best of {args.repeat}")
    head = (
        f"{'measure':<17}{'jax 1 call':>12}{'jax batches':>13}{'numpy':>9}"
        f"{'speed-up':>10}{'max |diff|':>12}"
    )
    print(head)
    print("-" * len(head))
    for name, fn in kernels.items():
        g = jax.jit(fn)
        jax.block_until_ready(g(*dev))  # compile + warm-up, both shapes
        jax.block_until_ready(g(*batches[0]))
        t_one = best_time(lambda g=g: jax.block_until_ready(g(*dev)), args.repeat)

        def run_batches(g=g):
            jax.block_until_ready([g(*b) for b in batches])

        t_bat = best_time(run_batches, args.repeat)
        ref = NUMPY[name]
        t_np = best_time(lambda ref=ref: ref(aos), args.repeat)
        # agreement on generic tets (the first n_np of the jax output)
        ours = np.asarray(jax.block_until_ready(g(*batches[0]))).reshape(-1, min(BATCH, n))
        theirs = np.asarray(ref([a[: min(BATCH, n_np)] for a in aos]))
        k = theirs.shape[-1]
        diff = float(np.max(np.abs(ours[..., :k] - theirs)))
        r_one, r_bat, r_np = n / t_one / 1e6, n / t_bat / 1e6, n_np / t_np / 1e6
        print(
            f"{name:<17}{r_one:>12.1f}{r_bat:>13.1f}{r_np:>9.2f}"
            f"{max(r_one, r_bat) / r_np:>9.0f}x{diff:>12.1e}"
        )
    print("rates in M tets/s; numpy on", f"{n_np:,} tets")


def delaunay_cube(n_tets: int, seed: int = 0) -> "jtet.TetMesh":
    """A Delaunay mesh of random points in the unit cube with about ``n_tets`` tets."""
    from scipy.spatial import Delaunay

    import jtet

    rng = np.random.default_rng(seed)
    pts = rng.random((max(n_tets // 6, 8), 3))  # Delaunay of random points: ~6.7 tets/point
    tets = Delaunay(pts).simplices.astype(np.int64)
    p = pts[tets]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets[vol < 0] = tets[vol < 0][:, [1, 0, 2, 3]]
    return jtet.TetMesh(pts, tets[np.abs(vol) > 1e-15])


def topology_table(args) -> None:
    """Topology of a Delaunay mesh of ~``--topology-tets`` tets vs a NumPy baseline.

    The baseline (same process) is the irreducible core of the job: np.unique of the
    sorted face and edge keys with their inverse, which any face/edge table needs.
    """
    from jtet._topology import Topology, row_keys

    n = args.topology_tets
    t0 = time.perf_counter()
    mesh = delaunay_cube(n)
    t_mesh = time.perf_counter() - t0
    m, npts = mesh.n_tets, mesh.n_points

    def baseline():
        tf = np.sort(mesh.tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]], axis=2).reshape(
            -1, 3
        )
        np.unique(row_keys(tf, npts), return_inverse=True)
        te = np.sort(mesh.tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]], axis=2)
        te = te.reshape(-1, 2)
        np.unique(te[:, 0] * npts + te[:, 1], return_inverse=True)

    t_base = best_time(baseline, args.repeat)
    t_topo = best_time(lambda: Topology.build(mesh), args.repeat)
    T = Topology.build(mesh)
    print(f"topology: Delaunay mesh of {m:,} tets, {npts:,} points (made in {t_mesh:.1f} s)")
    print(f"{'step':<44}{'seconds':>9}{'ratio':>8}")
    print("-" * 61)
    print(f"{'baseline: np.unique faces + edges (inverse)':<44}{t_base:>9.2f}{1.0:>8.2f}")
    print(f"{'Topology.build (faces, rings, protection)':<44}{t_topo:>9.2f}{t_topo / t_base:>8.2f}")
    print(
        f"{len(T.faces):,} faces, {len(T.edges):,} edges, "
        f"{int(T.edge_boundary.sum()):,} boundary edges; target <= 5 s for ~1M tets"
    )


TABLES = {"quality": quality_table, "topology": topology_table}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tets", type=int, default=10_000_000, help="problem size (tets)")
    ap.add_argument("--repeat", type=int, default=3, help="best of this many runs")
    ap.add_argument("--topology-tets", type=int, default=1_000_000, help="topology mesh size")
    ap.add_argument("--tables", nargs="+", default=list(TABLES), choices=list(TABLES))
    args = ap.parse_args()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} cpu(s), "
        f"load average {load:.1f}"
    )
    for name in args.tables:
        print()
        TABLES[name](args)


if __name__ == "__main__":
    main()
