"""Klincsek edge-removal kernel against brute-force enumeration of every triangulation.

Qualities are compared with ``atol = 1e-12``: the kernel and the reference evaluate the
same quality formula in different XLA executables, which may round the last bits
differently (fusion decides where a*b+c becomes an FMA); ~1e-16 is what we observe. The
DP itself only takes min and max, which are exact, so batch-size-independent paths
(pruned vs unpruned) are compared bitwise. The mean ratio is the exception: it grows like
|V|^(2/3), so on a flat tet a round-off volume of 1e-17 reads as a quality of ~1e-11 with
either sign; it gets ``atol = 1e-9``.
"""

from __future__ import annotations

import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtet
from jtet._errors import JtetError
from jtet._kernels import klincsek as kl
from jtet._quality import MEASURES, tet_quality

ATOL = 1e-12
ALL_MEASURES = sorted(MEASURES)


def atol(measure: str) -> float:
    return 1e-9 if measure == "mean_ratio" else ATOL


# ---------------------------------------------------------------------------------------
# Independent reference: every triangulation of the polygon 0..m-1


@functools.cache
def triangulations(i: int, j: int) -> tuple[tuple[tuple[int, int, int], ...], ...]:
    """All triangulations of the polygon i..j (closed by edge ij), as triangle tuples."""
    if j - i < 2:
        return ((),)
    out = []
    for k in range(i + 1, j):
        for left in triangulations(i, k):
            for right in triangulations(k, j):
                out.append(left + ((i, k, j),) + right)
    return tuple(out)


def candidate_qualities(a, b, ring, measure) -> dict:
    """{(i, k, j): min quality of (v_i, v_k, v_j, a), (v_i, v_j, v_k, b)} via _quality."""
    m = len(ring)
    pts = np.vstack([ring, a, b])
    tris = list(itertools.combinations(range(m), 3))
    tets = []
    for i, k, j in tris:
        tets.append([i, k, j, m])
        tets.append([i, j, k, m + 1])
    q = tet_quality(pts, np.asarray(tets), measure)
    return {t: min(q[2 * c], q[2 * c + 1]) for c, t in enumerate(tris)}


def brute_force(a, b, ring, measure) -> tuple[float, dict]:
    qt = candidate_qualities(a, b, ring, measure)
    best = max(min(qt[t] for t in T) for T in triangulations(0, len(ring) - 1))
    return best, qt


def check_triangulation(tris: np.ndarray, m: int) -> None:
    """m-2 triangles, each polygon edge used once, each diagonal twice, no crossings."""
    assert tris.shape == (m - 2, 3)
    assert np.array_equal(tris[:, 1], np.arange(1, m - 1)), "row k-1 has middle vertex k"
    assert np.all((tris[:, 0] < tris[:, 1]) & (tris[:, 1] < tris[:, 2]))
    assert tris.min() >= 0 and tris.max() <= m - 1
    count: dict = {}
    for i, k, j in tris.tolist():
        for e in ((i, k), (k, j), (i, j)):
            count[e] = count.get(e, 0) + 1
    boundary = {(i, i + 1) for i in range(m - 1)} | {(0, m - 1)}
    for e in boundary:
        assert count.get(e) == 1, f"polygon edge {e} used {count.get(e)} times"
    diagonals = [e for e in count if e not in boundary]
    assert all(count[e] == 2 for e in diagonals)
    assert len(diagonals) == m - 3
    for (p, q), (r, s) in itertools.combinations(diagonals, 2):
        assert not (p < r < q < s or r < p < s < q), f"diagonals {p, q} and {r, s} cross"


# ---------------------------------------------------------------------------------------
# Ring generators (seeded)


def _frame(a, b):
    u = (a - b) / np.linalg.norm(a - b)
    e1 = np.cross(u, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.1:
        e1 = np.cross(u, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1), u  # right-handed (e1, e2, u), u along b -> a


def ring_about(a, b, theta, radius, height, shift=(0.0, 0.0)):
    """Ring points at angles ``theta`` (increasing = counterclockwise seen from a)."""
    e1, e2, u = _frame(a, b)
    c = 0.5 * (a + b) + shift[0] * e1 + shift[1] * e2
    return (
        c
        + (radius * np.cos(theta))[:, None] * e1
        + (radius * np.sin(theta))[:, None] * e2
        + height[:, None] * u
    )


def random_edge(rng):
    a = rng.normal(size=3)
    d = rng.normal(size=3)
    return a, a - rng.uniform(0.5, 2.0) * d / np.linalg.norm(d)


def make_ring(kind: str, m: int, rng):
    """(a, b, ring) of one of several kinds, from valid to inverted and degenerate."""
    a, b = random_edge(rng)
    L = np.linalg.norm(a - b)
    theta = np.sort(rng.uniform(0, 2 * np.pi, m))
    radius = rng.uniform(0.3, 1.5, m) * L
    height = rng.uniform(-0.4, 0.4, m) * L
    if kind == "random":  # ordered ring around a random edge: mostly valid tets
        return a, b, ring_about(a, b, theta, radius, height)
    if kind == "regular":  # jittered regular polygon, the common case in a mesh
        th = 2 * np.pi * (np.arange(m) + rng.uniform(-0.2, 0.2, m)) / m
        return a, b, ring_about(a, b, th, np.full(m, L), 0.1 * L * rng.normal(size=m))
    if kind == "shuffled":  # vertex order scrambled: inverted and crossing tets
        return a, b, ring_about(a, b, rng.permutation(theta), radius, height)
    if kind == "off_axis":  # the edge ab does not pierce the ring
        return a, b, ring_about(a, b, theta, 0.3 * radius, height, shift=(2 * L, 0.0))
    if kind == "planar":  # ring points coplanar, ab across the plane; collinear triples
        pts = ring_about(a, b, theta, radius, np.zeros(m))
        if m >= 4:
            pts[2] = 0.5 * (pts[1] + pts[3])
        return a, b, pts
    if kind == "coplanar_all":  # a, b and the ring in one plane: every tet flat
        e1, e2, u = _frame(a, b)
        s = rng.uniform(-1, 1, (m, 2)) * L
        return a, b, 0.5 * (a + b) + s[:, :1] * e1 + s[:, 1:] * u
    raise ValueError(kind)


KINDS = ("random", "regular", "shuffled", "off_axis", "planar", "coplanar_all")
# kinds without exact ties between triangulations: different compiled paths may round the
# (all ~0) qualities of degenerate rings differently and so break ties differently, so
# comparisons of triangulations between paths use these
GENERIC = ("random", "regular", "shuffled", "off_axis")


def rings_batch(m: int, seed: int, per_kind: int = 2, kinds=KINDS):
    rng = np.random.default_rng(seed)
    items = [make_ring(k, m, rng) for k in kinds for _ in range(per_kind)]
    a, b, ring = (np.stack(x) for x in zip(*items, strict=True))
    return a, b, ring


def check_against_brute_force(m: int, measure: str, seed: int) -> None:
    a, b, ring = rings_batch(m, seed)
    q_new, tris = kl.solve_rings(a, b, ring, np.full(len(a), -np.inf), measure, prune=False)
    tol = atol(measure)
    for r in range(len(a)):
        best, qt = brute_force(a[r], b[r], ring[r], measure)
        assert abs(q_new[r] - best) <= tol, (r, q_new[r], best)
        check_triangulation(tris[r], m)
        achieved = min(qt[tuple(t)] for t in tris[r].tolist())
        assert abs(achieved - q_new[r]) <= tol


# ---------------------------------------------------------------------------------------
# Optimality


@pytest.mark.parametrize("measure", ALL_MEASURES)
@pytest.mark.parametrize("m", [4, 6])
def test_optimal_all_measures(m, measure):
    check_against_brute_force(m, measure, seed=100 + m)


@pytest.mark.parametrize("m", [3, 5, 7, 8, 9])
def test_optimal_min_sine(m):
    check_against_brute_force(m, "min_sine", seed=200 + m)


@pytest.mark.slow
@pytest.mark.parametrize("measure", ALL_MEASURES)
@pytest.mark.parametrize("m", range(3, 10))
def test_optimal_full_sweep(m, measure):
    check_against_brute_force(m, measure, seed=300 + m)


def test_triangulation_count_is_catalan():
    for m in range(3, 10):
        assert len(triangulations(0, m - 1)) == math.comb(2 * (m - 2), m - 2) // (m - 1)
        assert len(kl.candidate_triangles(m)) == math.comb(m, 3)


# ---------------------------------------------------------------------------------------
# Canonical flips


def octahedron(stretch: float):
    a = np.array([0.0, 0.0, stretch])
    b = np.array([0.0, 0.0, -stretch])
    ring = np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0]])
    return a, b, ring


def old_quality(a, b, ring, measure="min_sine"):
    m = len(ring)
    pts = np.vstack([ring, a, b])
    tets = [[m, m + 1, (i + 1) % m, i] for i in range(m)]
    return tet_quality(pts, np.asarray(tets), measure)


def test_regular_octahedron_4_4_flip_is_a_tie():
    a, b, ring = octahedron(1.0)
    q_old = old_quality(a, b, ring)
    assert np.all(q_old > 0)  # the convention: old tets (a, b, v_{i+1}, v_i) are positive
    q_new, tris, ok = kl.solve_ring(jnp.asarray(a), jnp.asarray(b), jnp.asarray(ring))
    # both triangulations of the square give four tets congruent to the old ones
    assert abs(float(q_new) - q_old.min()) <= ATOL
    check_triangulation(np.asarray(tris), 4)


def test_stretched_octahedron_4_4_flip_improves():
    a, b, ring = octahedron(2.5)  # long edge ab: removing it is a clear improvement
    q_old = old_quality(a, b, ring).min()
    q_new, tris = kl.solve_rings(a[None], b[None], ring[None], np.array([q_old]))
    assert q_new[0] > q_old + 0.1
    best, _ = brute_force(a, b, ring, "min_sine")
    assert abs(q_new[0] - best) <= ATOL
    check_triangulation(tris[0], 4)


def test_three_two_flip():
    # three tets around the long axis of a triangular bipyramid: the 3-2 flip wins
    # (min-sine 0.67 -> 0.95 at this height)
    a = np.array([0.0, 0.0, 1.0])
    b = np.array([0.0, 0.0, -1.0])
    th = 2 * np.pi * np.arange(3) / 3
    ring = np.stack([np.cos(th), np.sin(th), np.zeros(3)], axis=1)
    q_old = old_quality(a, b, ring).min()
    q_new, tris, ok = kl.solve_ring(jnp.asarray(a), jnp.asarray(b), jnp.asarray(ring), q_old)
    pts = np.vstack([ring, a, b])
    direct = tet_quality(pts, np.array([[0, 1, 2, 3], [0, 2, 1, 4]]), "min_sine").min()
    assert abs(float(q_new) - direct) <= ATOL
    assert np.array_equal(np.asarray(tris), [[0, 1, 2]])
    assert bool(ok) and float(q_new) > q_old


# ---------------------------------------------------------------------------------------
# Transformations agree: vmap, loops, layouts, jit, forms, pruning


def test_vmap_matches_loop_and_batch_layouts():
    m, measure = 6, "min_sine"
    a, b, ring = rings_batch(m, seed=7, kinds=GENERIC)
    kern = functools.partial(kl.ring_kernel, m=m, measure=measure)
    args = [jnp.asarray(x) for x in (*a.T, *b.T)] + [jnp.asarray(ring[..., c]) for c in range(3)]
    q_vmap, t_vmap = jax.jit(jax.vmap(kern))(*args)
    # one ring at a time
    for r in range(len(a)):
        q1, t1, _ = kl.solve_ring(
            jnp.asarray(a[r]), jnp.asarray(b[r]), jnp.asarray(ring[r]), measure=measure
        )
        assert abs(float(q1) - float(q_vmap[r])) <= ATOL
        assert np.array_equal(np.asarray(t1), np.asarray(t_vmap[r]))
    # the same kernel on trailing batch axes (batch-minor)
    args_t = args[:6] + [x.T for x in args[6:]]
    q_t, t_t = jax.jit(kern)(*args_t)
    np.testing.assert_allclose(np.asarray(q_t), np.asarray(q_vmap), rtol=0, atol=ATOL)
    assert np.array_equal(np.moveaxis(np.asarray(t_t), -1, 0), np.asarray(t_vmap))
    # the chunked host entry
    q_h, t_h = kl.solve_rings(a, b, ring, np.zeros(len(a)), measure, prune=False)
    np.testing.assert_allclose(q_h, np.asarray(q_vmap), rtol=0, atol=ATOL)
    assert np.array_equal(t_h, np.asarray(t_vmap))


def test_multi_chunk_batch_with_padding_matches_single_rings():
    m = 5
    rng = np.random.default_rng(11)
    n = 2 * kl.CHUNK + 37  # three chunks after padding, the last mostly padding
    items = [make_ring(GENERIC[r % len(GENERIC)], m, rng) for r in range(n)]
    a, b, ring = (np.stack(x) for x in zip(*items, strict=True))
    q, tris = kl.solve_rings(a, b, ring, np.zeros(n), prune=False)
    assert q.shape == (n,) and tris.shape == (n, m - 2, 3)
    for r in rng.choice(n, 12, replace=False).tolist() + [n - 1]:
        q1, t1, _ = kl.solve_ring(jnp.asarray(a[r]), jnp.asarray(b[r]), jnp.asarray(ring[r]))
        assert abs(float(q1) - q[r]) <= ATOL
        assert np.array_equal(np.asarray(t1), tris[r])


def test_jit_matches_no_jit():
    # Eager JAX compiles every primitive separately, so the eager side runs the DP and the
    # readback (the kernel's own logic) on jitted candidate qualities of a batch of rings
    # (trailing batch axis); the quality measures have their own tests.
    m = 4  # every distinct shape costs an eager compile: keep m small
    a, b, ring = rings_batch(m, seed=3, per_kind=2, kinds=GENERIC)
    q_tri = jax.jit(functools.partial(kl.candidate_quality, m=m, measure="min_sine"))(
        tuple(jnp.asarray(x) for x in a.T),
        tuple(jnp.asarray(x) for x in b.T),
        tuple(jnp.asarray(ring[..., c].T) for c in range(3)),
    )  # (T, B)
    solve = functools.partial(kl.solve_from_quality, m=m)
    q_j, t_j = jax.jit(solve)(q_tri)
    with jax.disable_jit():
        q_e, t_e = solve(q_tri)
    assert np.array_equal(np.asarray(q_j), np.asarray(q_e))  # min/max only: exact
    assert np.array_equal(np.asarray(t_j), np.asarray(t_e))
    for r in range(len(a)):
        best, _ = brute_force(a[r], b[r], ring[r], "min_sine")
        assert abs(float(q_e[r]) - best) <= ATOL


def test_loop_form_matches_diagonal_form():
    m = 5
    a, b, ring = rings_batch(m, seed=5, kinds=GENERIC)
    soa = kl.to_chunks(a, b, ring, 2 * kl.CHUNK)
    qd, td = kl.solve_chunks(*soa, measure="min_sine", form="diagonal")
    ql, tl = kl.solve_chunks(*soa, measure="min_sine", form="loop")
    np.testing.assert_allclose(np.asarray(ql), np.asarray(qd), rtol=0, atol=ATOL)
    assert np.array_equal(np.asarray(tl), np.asarray(td))


def mixed_sizes_batch(width: int, n: int, seed: int):
    """``n`` generic rings of random sizes 3..width, zero-padded to ``width`` vertices."""
    rng = np.random.default_rng(seed)
    sizes = rng.integers(3, width + 1, n)
    a, b, ring = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, width, 3))
    for r, k in enumerate(sizes.tolist()):
        a[r], b[r], ring[r, :k] = make_ring(GENERIC[r % len(GENERIC)], k, rng)
    return a, b, ring, sizes


def test_padded_kernel_matches_one_kernel_per_size():
    # rings of 3..PAD_M vertices share the padded kernel; each size alone through its own
    # kernel (solve_chunks) must give the same optimum (ATOL: another executable) and the
    # same triangulation (generic rings have no ties), and the pad rows are -1
    width = kl.PAD_M + 2  # the two largest sizes take the per-size path
    a, b, ring, sizes = mixed_sizes_batch(width, 600, seed=13)
    q_mix, t_mix = kl.solve_rings(a, b, ring, np.zeros(len(a)), prune=False, sizes=sizes)
    assert t_mix.shape == (len(a), width - 2, 3)
    for k in np.unique(sizes).tolist():
        idx = np.flatnonzero(sizes == k)
        soa = kl.to_chunks(a[idx], b[idx], ring[idx, :k], kl._capacity(len(idx)))
        q_k, t_k = kl.solve_chunks(*soa, measure="min_sine")
        q_k, t_k = kl._unchunk_q(q_k, len(idx)), kl._unchunk_tris(t_k, len(idx))
        np.testing.assert_allclose(q_mix[idx], q_k, rtol=0, atol=ATOL)
        assert np.array_equal(t_mix[idx, : k - 2], t_k)
        assert np.all(t_mix[idx, k - 2 :] == -1)
    for r in np.flatnonzero(sizes <= kl.PAD_M)[:8]:
        k = sizes[r]
        best, _ = brute_force(a[r], b[r], ring[r, :k], "min_sine")
        assert abs(q_mix[r] - best) <= ATOL
        check_triangulation(t_mix[r, : k - 2], k)


def test_small_rings_in_a_wide_batch_keep_the_batch_width():
    # every ring small enough for the padded kernel, but the batch is wider than PAD_M:
    # tris still has m - 2 rows per ring (the docstring's shape), the extra ones -1
    m = kl.PAD_M + 2
    a, b, ring, sizes = mixed_sizes_batch(kl.PAD_M, 40, seed=3)
    wide = np.concatenate([ring, np.zeros((len(a), 2, 3))], axis=1)
    q_w, t_w = kl.solve_rings(a, b, wide, np.zeros(len(a)), sizes=sizes)
    q_n, t_n = kl.solve_rings(a, b, ring, np.zeros(len(a)), sizes=sizes)
    assert t_w.shape == (len(a), m - 2, 3)
    assert np.array_equal(q_w, q_n) and np.array_equal(t_w[:, : kl.PAD_M - 2], t_n)
    assert np.all(t_w[:, kl.PAD_M - 2 :] == -1)


def test_padding_slots_do_not_matter():
    # whatever the kernel finds in the slots past a ring's size (zeros, huge values,
    # NaN), its result is the same bit for bit
    a, b, ring, sizes = mixed_sizes_batch(kl.PAD_M, 2 * kl.CHUNK, seed=17)
    past = np.arange(kl.PAD_M) >= sizes[:, None]
    size_chunks = sizes.astype(np.int32).reshape(-1, kl.CHUNK)
    outs = []
    for fill in (0.0, 1e3, np.nan):
        padded = ring.copy()
        padded[past] = fill
        soa = kl.to_chunks(a, b, padded, 2 * kl.CHUNK)
        outs.append(
            [np.asarray(x) for x in kl.solve_padded_chunks(*soa, size_chunks, measure="min_sine")]
        )
    for q, t in outs[1:]:
        assert np.array_equal(q, outs[0][0]) and np.array_equal(t, outs[0][1])


def test_bad_sizes_raise():
    a = np.zeros((2, 3))
    for sizes in ([3], [2, 4], [3, 6]):
        with pytest.raises(JtetError, match="sizes"):
            kl.solve_rings(a, a, np.zeros((2, 5, 3)), np.zeros(2), sizes=np.array(sizes))


def realistic(m: int, n: int, seed: int):
    """Jittered regular rings with q_old = the worst old tet (a mix of wins and losses)."""
    rng = np.random.default_rng(seed)
    items = [make_ring("regular", m, rng) for _ in range(n)]
    a, b, ring = (np.stack(x) for x in zip(*items, strict=True))
    q_old = np.array([old_quality(a[r], b[r], ring[r]).min() for r in range(n)])
    return a, b, ring, q_old


@pytest.mark.parametrize("prune", [False, True])
def test_threads_split_chunks_without_changing_results(monkeypatch, prune):
    # the chunk axis is split over worker threads; 1, 2 and 3 workers (3 does not divide
    # the 4 chunks: falls back to 2) must give bit-identical results
    from jtet import _config

    m = kl.PRUNE_MIN_M
    a, b, ring, q_old = realistic(m, 3 * kl.CHUNK, seed=5)
    results = []
    for workers in (1, 2, 3):
        monkeypatch.setattr(_config, "WORKERS", workers)
        results.append(kl.solve_rings(a, b, ring, q_old, prune=prune))
    for q, t in results[1:]:
        assert np.array_equal(q, results[0][0]) and np.array_equal(t, results[0][1])


@pytest.mark.parametrize("prune", [True, "quality", "volume"])
def test_pruned_matches_unpruned_on_successes(prune):
    m = kl.PRUNE_MIN_M
    a, b, ring, q_old = realistic(m, 300, seed=21)
    # a few rings whose old tets are inverted (q_old < 0), and some hopeless ones
    q_old[:10] = -0.5
    q_old[10:20] = 2.0
    q_u, t_u = kl.solve_rings(a, b, ring, q_old, prune=False)
    q_p, t_p = kl.solve_rings(a, b, ring, q_old, prune=prune)
    win = q_u > q_old
    assert 0 < win.sum() < len(win)  # the case mixes successes and failures
    assert np.array_equal(q_p > q_old, win)
    assert np.array_equal(q_p[win], q_u[win])  # bitwise: same compiled loop body
    assert np.array_equal(t_p[win], t_u[win])
    assert np.all(q_p[~win] <= q_old[~win])
    for r in np.flatnonzero(~win)[:5]:
        check_triangulation(t_p[r], m)  # placeholder for dropped rings, still valid


def test_small_rings_are_not_pruned_by_default():
    m = kl.PRUNE_MIN_M - 1
    a, b, ring, q_old = realistic(m, 50, seed=4)
    q_u, t_u = kl.solve_rings(a, b, ring, q_old, prune=False)
    q_p, t_p = kl.solve_rings(a, b, ring, q_old, prune=True)
    assert np.array_equal(q_p, q_u) and np.array_equal(t_p, t_u)


def test_quality_screen_prunes_realistic_rings():
    m = 6
    a, b, ring, q_old = realistic(m, 256, seed=8)
    soa = kl.to_chunks(a, b, ring, 2 * kl.CHUNK)
    q_pad = np.pad(q_old, (0, 2 * kl.CHUNK - 256), constant_values=np.inf)
    alive = np.asarray(
        kl.screen_chunks(*soa, q_pad.reshape(-1, kl.CHUNK), measure="min_sine", mode="quality")
    ).reshape(-1)[:256]
    q_u, _ = kl.solve_rings(a, b, ring, q_old, prune=False)
    assert np.all(alive[q_u > q_old])  # never drops a success
    assert alive.mean() < 0.5  # and drops most of the rest


def test_volume_screen_drops_inverted_rings_only_when_allowed():
    a, b, ring = make_ring("off_axis", 6, np.random.default_rng(2))
    alive_pos = kl.screen_kernel(*a, *b, *ring.T, 0.1, m=6)
    alive_neg = kl.screen_kernel(*a, *b, *ring.T, -0.1, m=6)
    assert not bool(alive_pos) and bool(alive_neg)


# ---------------------------------------------------------------------------------------
# Inputs


def test_empty_batch():
    q, t = kl.solve_rings(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 5, 3)), np.zeros(0))
    assert q.shape == (0,) and t.shape == (0, 3, 3)


def test_bad_inputs_raise():
    a = np.zeros((2, 3))
    with pytest.raises(JtetError):
        kl.solve_rings(a, a, np.zeros((2, 2, 3)), np.zeros(2))  # m < 3
    with pytest.raises(JtetError):
        kl.solve_rings(a, a, np.zeros((3, 5, 3)), np.zeros(2))  # B mismatch
    with pytest.raises(JtetError):
        kl.solve_rings(a, a, np.zeros((2, 5, 3)), np.zeros(3))  # q_old mismatch
    with pytest.raises(JtetError):
        kl.solve_rings(a, a, np.zeros((2, 5, 3)), np.zeros(2), measure="nope")
    with pytest.raises(JtetError):
        kl.solve_rings(a, a, np.zeros((2, 5, 3)), np.zeros(2), prune="maybe")
    assert issubclass(JtetError, Exception) and jtet.JtetError is JtetError
