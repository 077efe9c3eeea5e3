"""Throughput of jtet's robust orient3d against naive float64 determinants, and how often each
stage of the predicate is reached.

    python experiments/bench_predicates.py [--n 1000000] [--repeat 3]

Prints one table. Rates are M queries/s (best of ``--repeat``); the ratio column is against
``np.linalg.det`` measured in the same run (machines here are noisy and shared).
"""

import argparse
import time

import numpy as np

from jtet import _predicates as P


def best_time(fn, repeat):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def filter_only(a, b, c, d):
    """Stage 1 alone, chunked like orient3d."""
    n, k = len(a), P._CHUNK
    return [
        P._orient3d_filter(a[s : s + k], b[s : s + k], c[s : s + k], d[s : s + k])
        for s in range(0, n, k)
    ]


def naive_linalg(a, b, c, d):
    return np.sign(np.linalg.det(np.stack([b - a, c - a, d - a], axis=1)))


def naive_einsum(a, b, c, d):
    return np.sign(np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)))


def inputs(kind, n, rng):
    if kind == "random":
        return tuple(rng.random((n, 3)) for _ in range(4))
    a, b, c = (rng.uniform(-1, 1, (n, 3)) for _ in range(3))
    if kind == "grid coplanar":  # exactly coplanar, tilted plane, integer coordinates
        a, b, c = (np.round(8 * x) for x in (a, b, c))
        s, t = rng.integers(-2, 3, (2, n, 1))
        return a, b, c, a + s * (b - a) + t * (c - a)
    s, t = rng.uniform(-2, 2, (2, n, 1))
    d = a + s * (b - a) + t * (c - a)  # on the plane up to rounding
    if kind == "near coplanar + 1ulp":
        d = np.nextafter(d, np.where(rng.random((n, 3)) < 0.5, -np.inf, np.inf))
    return a, b, c, d


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)

    print(f"extended-precision middle stage enabled: {P._LD_ENABLED}")
    header = (
        f"{'input':<24}{'n':>9}{'method':>22}{'Mq/s':>8}{'vs det':>8}"
        f"{'to stage 2':>12}{'to exact':>11}"
    )
    print(header)
    print("-" * len(header))
    for kind, n in [
        ("random", args.n),
        ("grid coplanar", args.n // 5),
        ("near coplanar", args.n // 5),
        ("near coplanar + 1ulp", args.n // 5),
    ]:
        a, b, c, d = inputs(kind, n, rng)
        q = (a, b, c, d)
        t_det = best_time(lambda q=q: naive_linalg(*q), args.repeat)
        _, (n_ld, n_exact) = P._orient3d_staged(a, b, c, d)
        rows = [
            ("np.linalg.det", t_det, "", ""),
            ("einsum+cross", best_time(lambda q=q: naive_einsum(*q), args.repeat), "", ""),
            (
                "float64 filter only",
                best_time(lambda q=q: filter_only(*q), args.repeat),
                "",
                "",
            ),  # fmt: skip
            (
                "orient3d (robust)",
                best_time(lambda q=q: P.orient3d(*q), args.repeat),
                f"{n_ld / n:.4%}",
                f"{n_exact / n:.4%}",
            ),  # fmt: skip
        ]
        for name, t, s2, s3 in rows:
            print(f"{kind:<24}{n:>9}{name:>22}{n / t / 1e6:>8.2f}{t_det / t:>8.2f}{s2:>12}{s3:>11}")
        naive = naive_einsum(a, b, c, d).astype(np.int8)
        robust = P.orient3d(a, b, c, d)
        print(f"{'':<24}{'':>9}{'einsum sign != robust':>22}{(naive != robust).mean():>8.2%}")

    # the exact stage alone, and the classifier
    a, b, c, d = inputs("near coplanar", 20_000, rng)
    t_exact = best_time(lambda: P._orient3d_exact(a, b, c, d), 1)
    print(f"\nexact integer stage alone: {len(a) / t_exact / 1e3:.1f} k queries/s")
    if P._LD_ENABLED:
        t_ld = best_time(lambda: P._orient3d_filter_ld(a, b, c, d), args.repeat)
        print(f"extended-precision filter alone: {len(a) / t_ld / 1e6:.2f} M queries/s")
    n = args.n // 5
    p, q, a, b, c = (rng.uniform(-1, 1, (n, 3)) for _ in range(5))
    t_seg = best_time(lambda: P.segment_crosses_triangle(p, q, a, b, c), args.repeat)
    print(f"segment_crosses_triangle, random: {n / t_seg / 1e6:.2f} M queries/s")
    p, q, a, b, c = (rng.integers(-2, 3, (20_000, 3)).astype(float) for _ in range(5))
    t_seg = best_time(lambda: P.segment_crosses_triangle(p, q, a, b, c), args.repeat)
    print(f"segment_crosses_triangle, integer grid {{-2..2}}^3: {20_000 / t_seg / 1e6:.3f} M q/s")


if __name__ == "__main__":
    main()
