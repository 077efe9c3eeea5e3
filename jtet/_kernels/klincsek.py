"""Klincsek's dynamic program for optimal edge removal: a JAX kernel for ONE ring.

Shewchuk, Section 2 (Figure 5, FILLTABLES). The ring (or open chain) ``v_0 .. v_{m-1}``
around an edge ``ab`` is triangulated as the polygon ``v_0 .. v_{m-1}`` (closed by the
edge ``v_{m-1} v_0``); each triangle ``(v_i, v_k, v_j)``, ``i < k < j``, induces the two
tets ``(v_i, v_k, v_j, a)`` and ``(v_i, v_j, v_k, b)`` (positive when the ring is ordered
counterclockwise about ``ab`` seen from ``a``, the convention of ``jtet._topology``). The
kernel returns ``q_new = Q[0, m-1]``, the max over all triangulations of the min quality of
the ``2(m-2)`` induced tets, and one optimal triangulation. Indices here are 0-based; the
paper's are 1-based. The same kernel serves closed rings (interior edges) and the open
chains of boundary edges (Figure 7): either way the polygon ``v_0 .. v_{m-1}`` is what
gets triangulated; the caller combines the chains (``min`` of their ``q_new``).

Layout and why (numbers from experiments/bench_edge_removal.py, 2-core CPU):

* Candidates: all ``T = C(m, 3)`` triangles ``(i, k, j)``, ordered by diagonal
  ``d = j - i``, then ``t = k - i``, then ``i``. Their ``2T`` tets are evaluated by the
  structure-of-arrays quality measure on corners gathered with static index arrays.
* Tables: ``Q`` and ``K`` are flat vectors of the intervals ``(i, i+d)``, ``d >= 2``,
  diagonal after diagonal. Diagonal ``d`` needs ``Q[i, i+t]``, ``Q[i+t, i+d]`` and the
  candidates ``(i, i+t, i+d)``, ``t = 1 .. d-1``: static row gathers into (d-1, m-d)
  grids, one max-min over ``t``, and a static ``dynamic_update_slice`` into each table
  (no scatter: DESIGN.md measured scatter-filled tables at 0.01-0.03M rings/s). Both
  choices matter on XLA:CPU, which fuses cheap producers into every consumer: with plain
  slices and concatenations of earlier diagonals it re-derives the whole DP tree per
  consumer (exponential in m; optimization barriers are stripped on CPU), and a chain of
  per-``t`` selects compiles 2x slower than the gathered grid. ``K`` stores
  ``t = k - i`` (int8); ties keep the smallest ``k`` as in Figure 5 (``q > Q[i, j]``).
  The ``lax.fori_loop`` form (``fill_tables_loop``, padded to (m-2)^2 per diagonal) is kept
  as the measured alternative; the unrolled diagonals are faster (see the benchmark).
* One kernel for small rings: rings of 3 .. ``PAD_M`` vertices are padded to ``PAD_M``
  and solved together (``padded_candidate_quality`` masks the padding exactly: same
  optimum, same triangulation). Each compiled shape costs ~0.7-2 s of CPU to build even
  at m = 3, and the kernels are a few percent of a run, so one padded shape beats one per
  size (cold compile of the 10k-tet cube 18.8 -> 13.5 s, experiments/results/compile.md).
* Readback: a fixed-size stack traversal (``m - 2`` steps of a ``fori_loop``) from
  ``(0, m-1)``, popping an interval, reading its ``K`` and pushing its two children. Every
  vertex ``0 < k < m-1`` is the middle vertex of exactly one triangle of any triangulation
  (induction on the split at ``K[i, j]``), so the output is canonical:
  ``tris[k-1] = (i_k, k, j_k)``.
* Batch layout: the kernels only broadcast over trailing axes, so the same code solves one
  ring ((m,) arrays; ``jax.vmap`` works as usual) or a chunk of C rings with the batch as
  the minor, contiguous axis ((m, C) arrays). The batch entries do the latter, in chunks of
  ``CHUNK`` rings under ``lax.map`` (tables stay in cache), with the quality evaluation and
  the DP in two separate maps (one map would fuse the quality into the DP's consumers and
  recompute it). ``jax.vmap`` puts the batch axis first, where XLA:CPU gathers and slices
  along a minor axis of length m or T: measured 10-20x slower.

Pruning (the paper's ``q_old`` short cut) cannot break out of a loop in a SIMD batch; here
it is a two-stage batch filter (``solve_rings(prune=...)``). Stage 1 (``screen_chunks``)
evaluates only the a-side tets ``(v_i, v_k, v_j, a)`` of every candidate and runs the DP
on them: since ``min(q_a, q_b) <= q_a`` for every triangulation, that is an upper bound
of ``q_new``, and a ring whose bound does not beat ``q_old`` cannot succeed. Survivors
(5-10 % of realistic rings at m >= 6) are compacted on the host into a smaller padded
batch and solved exactly by stage 2. (A cheaper signed-volume screen, dropping rings in
which some polygon edge has no candidate with two positive tets, is kept as
``prune="volume"``: realistic rings have no inverted candidates, so it rarely prunes.) A
successful ring always survives and gets bitwise the unpruned answer: batch capacities are
two chunks per kernel call, so every batch runs the same compiled kernel. Pruning applies
to rings above ``PAD_M`` only (``max_ring > 7``): the padded kernel solves every small ring
exactly, as one screen shape more would cost more compile time than it saves run time.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .. import _config
from .._aot import cached_call
from .._aot import prefetch as prefetch_kernels
from .._errors import JtetError
from .._quality import Vec, get_measure, signed_volume

__all__ = [
    "CHUNK",
    "prefetch",
    "kernel_specs",
    "candidate_triangles",
    "ring_kernel",
    "solve_ring",
    "solve_rings",
]

MIN_M = 3
MAX_M = 64  # K holds t = k - i in int8; compile time grows ~m^2 long before this bound
# Rings per chunk of the batch entries: the DP tables of one chunk stay in L1/L2.
CHUNK = 256
# Chunks per kernel call: every call has this many (two: with one, XLA drops the loop of
# ``lax.map`` and compiles a different body, which could round differently).
CALL_CHUNKS = 2
# Rings of MIN_M .. PAD_M vertices share ONE compiled kernel, each padded to PAD_M
# vertices (``solve_padded_chunks``). Every shape costs a compile (0.7-2 s of CPU even at
# m = 3) and a load: one padded kernel instead of five sizes and two screens cut the cold
# Klincsek build from ~11 to ~2.5 s of CPU, while the kernels' run time is a few percent of
# a run's (182k-tet cube: 0.23 s of 6.6 s for 103k rings; a padded ring costs what an m = 7
# ring costs, ~1.6 us). Larger rings get a kernel of their own size.
PAD_M = 7
# prune=True screens only rings of at least this size (and above PAD_M, whose rings are
# always solved exactly): below m = 6 the screen (half the quality work plus a DP, and a
# second host round trip) drops too few rings to pay (benchmark on realistic rings:
# m = 3, 4, 5 keep 100, 93, 29 % and run 1.3-3x slower pruned; m = 6 keeps 6 % and runs
# 1.4-2.5x faster).
PRUNE_MIN_M = PAD_M + 1


# ---------------------------------------------------------------------------------------
# Static index plans (NumPy, built once per m)


@dataclass(frozen=True, eq=False)
class _Plan:
    """Static index arrays of one ring size ``m``.

    ``ci, ck, cj``: (T,) candidate triangles ``(i, k, j)``, T = C(m, 3), ordered by
    ``(d = j - i, t = k - i, i)``; ``start[d][t]``: offset of the ``m - d`` triangles
    ``(i, i+t, i+d)``, ``i = 0 .. m-d-1``. ``off[d]``: offset of diagonal ``d`` in the flat
    tables (n = (m-1)(m-2)/2 intervals). ``edge_incidence``: (T, m), 1 where candidate ``c``
    has polygon edge ``e`` as a side (``(e, e+1)`` for ``e < m-1``; ``m-1`` is ``(0, m-1)``).
    """

    m: int
    ci: np.ndarray
    ck: np.ndarray
    cj: np.ndarray
    start: dict
    off: np.ndarray
    n: int
    edge_incidence: np.ndarray


@functools.cache
def _plan(m: int) -> _Plan:
    if not (isinstance(m, int) and MIN_M <= m <= MAX_M):
        raise JtetError(f"ring size m must be an int in [{MIN_M}, {MAX_M}], got {m!r}")
    ci, ck, cj, start = [], [], [], {}
    for d in range(2, m):
        start[d] = {}
        for t in range(1, d):
            start[d][t] = len(ci)
            for i in range(m - d):
                ci.append(i)
                ck.append(i + t)
                cj.append(i + d)
    ci, ck, cj = (np.asarray(v, np.int32) for v in (ci, ck, cj))
    assert len(ci) == math.comb(m, 3)
    inc = np.zeros((len(ci), m))
    for c, (i, k, j) in enumerate(zip(ci, ck, cj, strict=True)):
        for u, v in ((i, k), (k, j), (i, j)):
            if v == u + 1:
                inc[c, u] = 1.0
            elif (u, v) == (0, m - 1):
                inc[c, m - 1] = 1.0
    off = np.zeros(m, np.int32)
    o = 0
    for d in range(2, m):
        off[d] = o
        o += m - d
    return _Plan(m, ci, ck, cj, start, off, o, inc)


def candidate_triangles(m: int) -> Int[np.ndarray, "T 3"]:
    """The (C(m,3), 3) candidate triangles ``(i, k, j)`` in the kernel's order."""
    p = _plan(m)
    return np.stack([p.ci, p.ck, p.cj], axis=1)


# ---------------------------------------------------------------------------------------
# Kernel pieces, each for ONE ring: ring-structured arrays have the ring structure on
# axis 0 and any trailing batch axes, which the code only broadcasts over: ring
# coordinates (m, ...), apex coordinates (...), candidate qualities (T, ...).


def _lift(x: np.ndarray, nb: int) -> np.ndarray:
    """A static array with ``nb`` trailing unit axes, to broadcast against batch axes."""
    return x.reshape(x.shape + (1,) * nb)


def _gather(ring: Vec, idx: np.ndarray) -> Vec:
    return (ring[0][idx], ring[1][idx], ring[2][idx])


def candidate_quality(
    a: Vec, b: Vec, ring: Vec, *, m: int, measure: str, side: str = "both"
) -> Float[Array, "T ..."]:
    """Quality of every candidate triangle of one ring: (T, ...), T = C(m, 3).

    ``side="both"``: min of the qualities of ``(v_i, v_k, v_j, a)`` and ``(v_i, v_j, v_k,
    b)``; ``"a"`` / ``"b"``: one side only. Each side is one elementwise SoA evaluation of
    the measure over all T candidates. ``a``, ``b``: SoA ``(x, y, z)`` of (...) arrays;
    ``ring``: SoA ``(x, y, z)`` of (m, ...) arrays.
    """
    p = _plan(m)
    q = get_measure(measure)
    vi, vk, vj = _gather(ring, p.ci), _gather(ring, p.ck), _gather(ring, p.cj)
    if side == "a":
        return q(vi, vk, vj, a)
    if side == "b":
        return q(vi, vj, vk, b)
    return jnp.minimum(q(vi, vk, vj, a), q(vi, vj, vk, b))


def padded_candidate_quality(
    a: Vec, b: Vec, ring: Vec, size: Int[Array, "..."], *, m: int, measure: str
) -> Float[Array, "T ..."]:
    """Candidate qualities of a ring of ``size <= m`` vertices padded to ``m``: (T, ...).

    The real ring is ``v_0 .. v_{s-1}`` (``s = size``); slots ``s .. m-1`` hold anything
    finite. The padded polygon is the real one plus the pad polygon ``P = v_0, v_{s-1},
    v_s, .., v_{m-1}`` across their shared edge ``v_0 v_{s-1}``. Candidates of real
    vertices keep their quality, those inside ``P`` get +inf and the mixed ones -inf. A
    triangulation of value > -inf has no mixed triangle, so it is a triangulation of the
    real polygon plus one of ``P`` (each lies in its own half of the shared edge), and
    its value is that of its real part: ``Q[0, m-1]`` is the real optimum, reached by the
    same sub-intervals and ties as the unpadded DP, and the readback's rows ``k - 1``,
    ``k = 1 .. s-2``, are the real triangles (``P``'s middle vertices are ``s-1 .. m-2``).
    """
    p = _plan(m)
    q = candidate_quality(a, b, ring, m=m, measure=measure)
    nb = size.ndim
    ci, ck, cj = (_lift(x, nb) for x in (p.ci, p.ck, p.cj))
    last = size[None] - 1  # index of v_{s-1}
    inside_pad = ((ci == 0) | (ci >= last)) & (ck >= last)  # i < k < j, all in P
    return jnp.where(cj <= last, q, jnp.where(inside_pad, jnp.inf, -jnp.inf))


@functools.cache
def _diagonal_tables(m: int) -> dict:
    """Static gather indices of ``fill_tables``: for every diagonal d, (d-1, m-d) arrays.

    ``iq[d][t-1, i]``: candidate ``(i, i+t, i+d)``; ``il[d]``, ``ir[d]``: rows of
    ``Q[i, i+t]`` and ``Q[i+t, i+d]`` in the flat table, row ``n`` (one past the last
    interval) holding +inf for ``Q[i, i+1]``.
    """
    p = _plan(m)
    iq, il, ir = {}, {}, {}
    for d in range(2, m):
        t = np.arange(1, d)[:, None]
        i = np.arange(m - d)[None, :]
        iq[d] = np.asarray([p.start[d][u] for u in range(1, d)], np.int32)[:, None] + i
        il[d] = np.where(t == 1, p.n, p.off[np.minimum(t, m - 1)] + i).astype(np.int32)
        ir[d] = np.where(d - t == 1, p.n, p.off[np.maximum(d - t, 0)] + i + t).astype(np.int32)
    ilr = {d: np.stack([il[d], ir[d]]) for d in il}  # one gather for both (compiles faster)
    return dict(iq=iq, il=il, ir=ir, ilr=ilr)


def fill_tables(q_tri: Float[Array, "T ..."], *, m: int) -> tuple[Array, Array, Array]:
    """Klincsek's tables from the candidate qualities, diagonal by diagonal.

    Returns ``(q_new, Q, K)``: ``q_new = Q[0, m-1]`` (...); ``Q`` (n, ...) float and ``K``
    (n, ...) int8 flat tables, row ``off[d] + i`` for the interval ``(i, i+d)``, ``K``
    holding the optimal ``t = k - i``. Each diagonal is two static row gathers, a
    max-min over t and two update-slices into the tables.
    """
    p = _plan(m)
    tb = _diagonal_tables(m)
    batch = q_tri.shape[1:]
    nb = len(batch)
    # the flat Q table plus a +inf row standing for Q[i, i+1] (paper's convention)
    Q = jnp.concatenate(
        [jnp.zeros((p.n,) + batch, q_tri.dtype), jnp.full((1,) + batch, jnp.inf, q_tri.dtype)]
    )
    K = jnp.zeros((p.n,) + batch, jnp.int8)
    for d in range(2, m):
        sub = jnp.min(Q[tb["ilr"][d]], axis=0)  # min(Q[i, i+t], Q[i+t, i+d])
        c = jnp.minimum(q_tri[tb["iq"][d]], sub)  # (d-1, m-d, ...)
        best = jnp.max(c, axis=0)  # (m-d, ...)
        # the smallest maximizing t, as Figure 5's strict ">" (min() also guards NaN rows)
        t = _lift(np.arange(1, d, dtype=np.int8)[:, None], nb)
        arg = jnp.min(jnp.where(c == best[None], t, jnp.int8(d - 1)), axis=0)
        # update-slices, not concatenation of per-diagonal vectors: XLA:CPU would fuse
        # those into every later consumer and re-derive them (exponential in m)
        Q = jax.lax.dynamic_update_slice_in_dim(Q, best, int(p.off[d]), 0)
        K = jax.lax.dynamic_update_slice_in_dim(K, arg, int(p.off[d]), 0)
    return Q[p.n - 1], Q[: p.n], K


@functools.cache
def _loop_tables(m: int) -> dict:
    """Static gather tables of ``fill_tables_loop``: (m, m-2, m-2) per diagonal."""
    p = _plan(m)
    g = m - 2
    inf_row = p.n + g  # a +inf row standing for Q[i, i+1]
    iq = np.full((m, g, g), len(p.ci), np.int32)  # len(ci): a -inf row appended to q
    il = np.full((m, g, g), inf_row, np.int32)
    ir = np.full((m, g, g), inf_row, np.int32)
    for d in range(2, m):
        for t in range(1, d):
            i = np.arange(m - d)
            iq[d, t - 1, : m - d] = p.start[d][t] + i
            il[d, t - 1, : m - d] = inf_row if t == 1 else p.off[t] + i
            ir[d, t - 1, : m - d] = inf_row if d - t == 1 else p.off[d - t] + i + t
    return dict(g=g, inf_row=inf_row, size=inf_row + 1, iq=iq, il=il, ir=ir)


def fill_tables_loop(q_tri: Float[Array, "T ..."], *, m: int) -> tuple[Array, Array, Array]:
    """Same as ``fill_tables`` with a ``lax.fori_loop`` over the diagonals.

    Kept as the measured alternative (DESIGN.md asks for both): every diagonal is one
    masked max-min over a padded (m-2, m-2) grid of (t, i), gathered with dynamic rows of
    static tables; rows past the diagonal's end spill into the next diagonals' slots (or
    the padding), which later iterations overwrite.
    """
    p = _plan(m)
    tb = _loop_tables(m)
    g = tb["g"]
    batch = q_tri.shape[1:]
    nb = len(batch)
    q_ext = jnp.concatenate([q_tri, jnp.full((1,) + batch, -jnp.inf, q_tri.dtype)])
    Q0 = jnp.zeros((tb["size"],) + batch, q_tri.dtype).at[tb["inf_row"]].set(jnp.inf)
    K0 = jnp.zeros((tb["size"],) + batch, jnp.int8)
    iq, il, ir, off = (jnp.asarray(x) for x in (tb["iq"], tb["il"], tb["ir"], p.off))
    tcol = _lift(np.arange(1, g + 1, dtype=np.int8)[:, None], nb)

    def body(d, carry):
        Q, K = carry
        c = jnp.minimum(jnp.minimum(q_ext[iq[d]], Q[il[d]]), Q[ir[d]])  # (g, g, ...)
        row = jnp.max(c, axis=0)
        arg = jnp.min(jnp.where(c == row[None], tcol, jnp.int8(127)), axis=0)
        Q = jax.lax.dynamic_update_slice_in_dim(Q, row, off[d], 0)
        K = jax.lax.dynamic_update_slice_in_dim(K, arg, off[d], 0)
        return Q, K

    Q, K = jax.lax.fori_loop(2, m, body, (Q0, K0))
    return Q[p.n - 1], Q[: p.n], K[: p.n]


def read_triangulation(K: Int[Array, "n ..."], *, m: int) -> Int[Array, "m-2 3 ..."]:
    """The optimal triangulation from the flat ``K`` table of ``fill_tables``.

    Returns (m-2, 3, ...) int32; row ``k-1`` is the triangle ``(i, k, j)`` whose middle
    vertex is ``k``. A fixed-size stack traversal: ``m - 2`` pops, each reading ``K`` of
    the popped interval and pushing its children (per-ring indices become one-hot
    selections, so the loop is the same for every ring of a batch).
    """
    p = _plan(m)
    batch = K.shape[1:]
    nb = len(batch)
    if m == 3:
        return jnp.broadcast_to(_lift(np.array([[0, 1, 2]], np.int32), nb), (1, 3) + batch)
    i32 = jnp.int32
    rows_f = _lift(np.arange(p.n, dtype=np.int32), nb)
    rows_s = _lift(np.arange(m, dtype=np.int32), nb)
    rows_t = _lift(np.arange(m - 2, dtype=np.int32), nb)
    Kint = K.astype(i32)
    off = jnp.asarray(p.off)

    def pick(rows, at, vals):
        return jnp.sum(jnp.where(rows == at[None], vals, 0), axis=0, dtype=i32)

    def push(st_i, st_j, sp, ok, u, v):
        at = (rows_s == sp[None]) & ok[None]
        return jnp.where(at, u[None], st_i), jnp.where(at, v[None], st_j), sp + ok.astype(i32)

    def body(_, carry):
        st_i, st_j, sp, ti, tj = carry
        i = pick(rows_s, sp - 1, st_i)
        j = pick(rows_s, sp - 1, st_j)
        k = i + pick(rows_f, off[j - i] + i, Kint)
        mid = rows_t == (k - 1)[None]
        ti = jnp.where(mid, i[None], ti)
        tj = jnp.where(mid, j[None], tj)
        sp = sp - 1
        st_i, st_j, sp = push(st_i, st_j, sp, (k - i) >= 2, i, k)
        st_i, st_j, sp = push(st_i, st_j, sp, (j - k) >= 2, k, j)
        return st_i, st_j, sp, ti, tj

    zeros_s = jnp.zeros((m,) + batch, i32)
    init = (
        zeros_s,
        zeros_s.at[0].set(m - 1),  # the stack starts with (0, m-1)
        jnp.ones(batch, i32),
        jnp.zeros((m - 2,) + batch, i32),
        jnp.zeros((m - 2,) + batch, i32),
    )
    _, _, _, ti, tj = jax.lax.fori_loop(0, m - 2, body, init)
    mids = jnp.broadcast_to(_lift(np.arange(1, m - 1, dtype=np.int32), nb), ti.shape)
    return jnp.stack([ti, mids, tj], axis=1)


def solve_from_quality(
    q_tri: Float[Array, "T ..."], *, m: int, form: str = "diagonal"
) -> tuple[Float[Array, "..."], Int[Array, "m-2 3 ..."]]:
    """DP and readback from the candidate qualities: ``(q_new, tris)``."""
    if form not in ("diagonal", "loop"):
        raise JtetError(f"unknown DP form {form!r}; use 'diagonal' or 'loop'")
    fill = fill_tables if form == "diagonal" else fill_tables_loop
    q_new, _, K = fill(q_tri, m=m)
    return q_new, read_triangulation(K, m=m)


def ring_kernel(
    ax, ay, az, bx, by, bz, rx, ry, rz, *, m: int, measure: str, form: str = "diagonal"
) -> tuple[Float[Array, "..."], Int[Array, "m-2 3 ..."]]:
    """Optimal edge removal of ONE ring (trailing batch axes allowed, see above).

    ``ax .. bz``: (...) apex coordinates; ``rx, ry, rz``: (m, ...) ring coordinates.
    Returns ``(q_new, tris)``: (...) and (m-2, 3, ...) int32 ring indices ``(i, k, j)``.
    ``form``: ``"diagonal"`` (unrolled diagonals, the default and faster) or ``"loop"``.
    """
    q_tri = candidate_quality((ax, ay, az), (bx, by, bz), (rx, ry, rz), m=m, measure=measure)
    return solve_from_quality(q_tri, m=m, form=form)


def screen_kernel(ax, ay, az, bx, by, bz, rx, ry, rz, q_old, *, m: int) -> Bool[Array, "..."]:
    """Volume screen for ONE ring: can some triangulation beat ``q_old >= 0`` at all?

    A candidate survives when both its tets have positive volume (every measure is <= 0 on
    a tet of volume <= 0); the ring survives iff every polygon edge is a side of a
    surviving candidate (each triangulation has exactly one triangle on each polygon edge).
    Never prunes where ``q_old < 0``. Cheap (no quality evaluation) but weak: realistic
    rings around an edge have no inverted candidates.
    """
    p = _plan(m)
    a, b, ring = (ax, ay, az), (bx, by, bz), (rx, ry, rz)
    vi, vk, vj = _gather(ring, p.ci), _gather(ring, p.ck), _gather(ring, p.cj)
    ok = (signed_volume(vi, vk, vj, a) > 0) & (signed_volume(vi, vj, vk, b) > 0)
    ok = ok | (q_old < 0)
    # number of surviving candidates on every polygon edge: (m, T) . (T, ...)
    per_edge = jnp.tensordot(jnp.asarray(p.edge_incidence.T), ok.astype(rx.dtype), axes=1)
    return jnp.all(per_edge > 0, axis=0)


# ---------------------------------------------------------------------------------------
# Jitted batch entries. Chunked SoA: apexes (nC, C), rings (nC, m, C), C = CHUNK; one
# lax.map over chunks for the qualities, another for the DP (see the module docstring).


@functools.partial(jax.jit, static_argnames=("measure", "form"))
def solve_chunks(ax, ay, az, bx, by, bz, rx, ry, rz, *, measure: str, form: str = "diagonal"):
    """Unpruned solve of a chunked batch -> q_new (nC, C), tris (nC, m-2, 3, C)."""
    m = rx.shape[1]
    q = jax.lax.map(
        lambda x: candidate_quality(x[0:3], x[3:6], x[6:9], m=m, measure=measure),
        (ax, ay, az, bx, by, bz, rx, ry, rz),
    )
    return jax.lax.map(lambda qc: solve_from_quality(qc, m=m, form=form), q)


@functools.partial(jax.jit, static_argnames=("measure",))
def solve_padded_chunks(ax, ay, az, bx, by, bz, rx, ry, rz, size, *, measure: str):
    """Unpruned solve of a chunked batch of rings padded to ``m = rx.shape[1]`` vertices,
    ``size`` (nC, C) int32 real vertices each (``padded_candidate_quality``) -> q_new
    (nC, C), tris (nC, m-2, 3, C) whose rows ``k-1 < size-2`` are the real triangles."""
    m = rx.shape[1]
    q = jax.lax.map(
        lambda x: padded_candidate_quality(x[0:3], x[3:6], x[6:9], x[9], m=m, measure=measure),
        (ax, ay, az, bx, by, bz, rx, ry, rz, size),
    )
    return jax.lax.map(lambda qc: solve_from_quality(qc, m=m), q)


@functools.partial(jax.jit, static_argnames=("measure", "mode"))
def screen_chunks(ax, ay, az, bx, by, bz, rx, ry, rz, q_old, *, measure: str, mode: str):
    """Stage 1 of the pruned solve over a chunked batch -> alive (nC, C) bool.

    ``mode="quality"``: the a-side tets ``(v_i, v_k, v_j, a)`` of all candidates with the
    full measure, then the DP on those qualities alone: an upper bound of ``q_new``
    (``min(q_a, q_b) <= q_a`` for every triangulation); alive iff the bound beats
    ``q_old``. Half the quality work plus one DP; on realistic rings it drops 90-95 % of
    the rings at m = 6..12 (experiments/bench_edge_removal.py).
    ``mode="volume"``: ``screen_kernel`` (cheap, rarely prunes realistic rings).
    """
    m = rx.shape[1]
    args = (ax, ay, az, bx, by, bz, rx, ry, rz)
    if mode == "volume":
        return jax.lax.map(lambda x: screen_kernel(*x, m=m), (*args, q_old))
    if mode != "quality":
        raise JtetError(f"unknown screen mode {mode!r}; use 'quality' or 'volume'")
    q_a = jax.lax.map(
        lambda x: candidate_quality(x[0:3], x[3:6], x[6:9], m=m, measure=measure, side="a"),
        args,
    )
    bound = jax.lax.map(lambda q: fill_tables(q, m=m)[0], q_a)
    return bound > q_old


def to_chunks(
    a: np.ndarray, b: np.ndarray, ring: np.ndarray, cap: int, chunk: int = CHUNK
) -> list[np.ndarray]:
    """(B, 3), (B, 3), (B, m, 3) -> apexes 6 x (cap/C, C) and ring 3 x (cap/C, m, C).

    ``cap`` is a multiple of ``chunk``; padding rings (``cap - B``) are all zero, so all
    their tets are degenerate (quality 0, no NaN).
    """
    n, m = ring.shape[:2]
    nc = cap // chunk
    out = []
    for p in (a, b):
        for c in range(3):
            x = np.zeros(cap)
            x[:n] = p[:, c]
            out.append(x.reshape(nc, chunk))
    for c in range(3):
        x = np.zeros((cap, m))
        x[:n] = ring[:, :, c]
        out.append(np.ascontiguousarray(x.reshape(nc, chunk, m).transpose(0, 2, 1)))
    return out


def _parallel_chunks(kernel, arrays: list[np.ndarray], **static):
    """``kernel(*arrays, **static)`` in calls of ``CALL_CHUNKS`` chunks each (the chunk axis
    0 holds a multiple of it), spread over the ``_config.WORKERS`` threads (XLA runs one
    call on one core).

    Every call has the same shape whatever the batch size and the number of workers: the
    kernel is compiled (or loaded from the cache) once per ring size and settings, not
    once per power-of-two batch size (cube, empty cache: 14 -> 7 Klincsek shapes).
    """
    nc = arrays[0].shape[0]
    assert nc % CALL_CHUNKS == 0, nc
    # traced once per shape and settings, then reloaded from disk by later processes
    name, settings = kernel.__name__, tuple(sorted(static.items()))
    fn = functools.partial(kernel, **static)
    parts = [[x[i : i + CALL_CHUNKS] for x in arrays] for i in range(0, nc, CALL_CHUNKS)]
    outs = _config.parallel_map(
        lambda part: jax.device_get(cached_call(name, settings, fn, *part)), parts
    )
    if len(outs) == 1:
        return outs[0]
    if isinstance(outs[0], tuple):
        return tuple(np.concatenate(o) for o in zip(*outs, strict=True))
    return np.concatenate(outs)


def prefetch(ms, measure: str = "min_sine", prune: bool | str = True) -> None:
    """Compile (or load) the kernels ``solve_rings`` needs for the ring sizes ``ms``, all
    at once on the worker threads, instead of one after the other as the sizes come."""
    prefetch_kernels(kernel_specs(ms, measure, prune))


def kernel_specs(ms, measure: str = "min_sine", prune: bool | str = True) -> list[tuple]:
    """``_aot.prefetch`` specs of the kernels ``solve_rings`` calls for ring sizes ``ms``."""
    f64 = np.dtype(np.float64)
    apex = [jax.ShapeDtypeStruct((CALL_CHUNKS, CHUNK), f64)] * 6

    def soa(m):
        return apex + [jax.ShapeDtypeStruct((CALL_CHUNKS, m, CHUNK), f64)] * 3

    specs = []
    if any(m <= PAD_M for m in ms):
        size = jax.ShapeDtypeStruct((CALL_CHUNKS, CHUNK), np.dtype(np.int32))
        static = {"measure": measure}
        specs.append(("solve_padded_chunks", (("measure", measure),), solve_padded_chunks,
                      [*soa(PAD_M), size], static))  # fmt: skip
    for m in sorted({m for m in ms if m > PAD_M}):
        static = {"measure": measure}
        specs.append(("solve_chunks", (("measure", measure),), solve_chunks, soa(m), static))
        if prune and not (prune is True and m < PRUNE_MIN_M):
            static = {"measure": measure, "mode": "quality" if prune is True else prune}
            specs.append(("screen_chunks", tuple(sorted(static.items())), screen_chunks,
                          [*soa(m), apex[0]], static))  # fmt: skip
    return [(name, settings, functools.partial(k, **st), a) for name, settings, k, a, st in specs]


def _capacity(n: int) -> int:
    """Rings of a padded batch: ``n`` rounded up to whole calls of ``CALL_CHUNKS``."""
    call = CALL_CHUNKS * CHUNK
    return max(1, -(-n // call)) * call


def _unchunk_q(q, n: int) -> np.ndarray:
    return np.asarray(q).reshape(-1)[:n]


def _unchunk_tris(t, n: int) -> np.ndarray:
    t = np.asarray(t)  # (nC, m-2, 3, C)
    return t.transpose(0, 3, 1, 2).reshape((-1,) + t.shape[1:3])[:n]


# ---------------------------------------------------------------------------------------
# Public entries


@functools.partial(jax.jit, static_argnames=("measure",))
def solve_ring(
    a: Float[Array, "3"],
    b: Float[Array, "3"],
    ring: Float[Array, "m 3"],
    q_old: Float[Array, ""] = -jnp.inf,
    *,
    measure: str = "min_sine",
) -> tuple[Float[Array, ""], Int[Array, "m-2 3"], Bool[Array, ""]]:
    """Optimal edge removal of one ring (jitted; ``m = ring.shape[0]`` is static).

    ``a``, ``b``: (3,) the edge's endpoints; ``ring``: (m, 3) the ring (or open chain)
    ordered counterclockwise about ``ab`` seen from ``a``. Returns ``(q_new, tris,
    success)``: the exact optimum (never pruned), the (m-2, 3) int32 triangulation in ring
    indices (row ``k-1`` has middle vertex ``k``) and ``q_new > q_old``. Plain
    ``(..., 3)`` arrays here for convenience: this entry is for one ring, not for speed.
    """
    m = ring.shape[0]
    q_new, tris = ring_kernel(
        a[0], a[1], a[2], b[0], b[1], b[2], ring[:, 0], ring[:, 1], ring[:, 2],
        m=m, measure=measure,
    )  # fmt: skip
    return q_new, tris, q_new > q_old


def _fan(m: int) -> np.ndarray:
    k = np.arange(1, m - 1, dtype=np.int32)
    return np.stack([np.zeros_like(k), k, k + 1], axis=1)


def solve_rings(
    a: Float[np.ndarray, "B 3"],
    b: Float[np.ndarray, "B 3"],
    ring: Float[np.ndarray, "B m 3"],
    q_old: Float[np.ndarray, " B"],
    measure: str = "min_sine",
    prune: bool | str = True,
    sizes: Int[np.ndarray, " B"] | None = None,
) -> tuple[Float[np.ndarray, " B"], Int[np.ndarray, "B m-2 3"]]:
    """Optimal edge removal of a batch of rings (host entry).

    ``a``, ``b``: (B, 3) edge endpoints; ``ring``: (B, m, 3) rings ordered as in
    ``solve_ring``; ``q_old``: (B,) the worst quality of the tets each removal would
    replace; ``sizes``: (B,) vertices of each ring, in [3, m] (None: all m), ring ``r``
    being ``ring[r, :sizes[r]]``. Returns NumPy ``(q_new (B,), tris (B, m-2, 3) int32)``,
    ``tris[r, k-1] = (i, k, j)`` in ring indices for ``k = 1 .. sizes[r]-2``; later rows
    are -1.

    Rings of up to ``PAD_M`` vertices are solved exactly by one kernel, padded to
    ``PAD_M`` (``prune`` does not apply to them). Larger rings are solved per size, in
    batches padded to whole kernel calls of ``CALL_CHUNKS * CHUNK`` rings, so every call
    of one size has the same shape. ``prune=False``: every ring solved exactly.
    ``prune=True``: ``"quality"`` for ``m >= PRUNE_MIN_M``. ``prune="quality"``: stage 1
    evaluates the a-side tets and bounds ``q_new`` by the DP on them alone, stage 2
    solves only the rings whose bound beats ``q_old``; ``prune="volume"``: stage 1 is the
    signed-volume screen of ``screen_kernel`` instead. With pruning every ring with
    ``q_new > q_old`` gets the unpruned result; a dropped ring reports ``q_new = -inf``
    and a placeholder fan triangulation, so ``q_new > q_old`` is the success test either
    way.
    """
    get_measure(measure)
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    ring = np.asarray(ring, np.float64)
    q_old = np.asarray(q_old, np.float64)
    if ring.ndim != 3 or ring.shape[2] != 3 or a.shape != (ring.shape[0], 3):
        raise JtetError(
            f"expected a, b (B, 3) and ring (B, m, 3); got {a.shape}, {b.shape}, {ring.shape}"
        )
    if b.shape != a.shape or q_old.shape != (ring.shape[0],):
        raise JtetError(f"b must be (B, 3) and q_old (B,); got {b.shape}, {q_old.shape}")
    if prune not in (False, True, "volume", "quality"):
        raise JtetError(f"prune must be a bool, 'quality' or 'volume'; got {prune!r}")
    n, m = ring.shape[:2]
    _plan(m)
    sizes = np.full(n, m) if sizes is None else np.asarray(sizes)
    if sizes.shape != (n,) or (n and not (MIN_M <= sizes.min() and sizes.max() <= m)):
        raise JtetError(f"sizes must be (B,) = ({n},) ints in [{MIN_M}, {m}]")
    small = np.flatnonzero(sizes <= PAD_M)
    if m <= PAD_M:  # the usual case (max_ring <= PAD_M): every ring small, no copies
        return _solve_padded(a, b, ring, sizes, measure, m)
    q_new = np.full(n, -np.inf)
    tris = np.full((n, m - 2, 3), -1, np.int32)
    if small.size:
        q_new[small], t = _solve_padded(a[small], b[small], ring[small], sizes[small], measure, m)
        tris[small, : t.shape[1]] = t
    for k in np.unique(sizes[sizes > PAD_M]).tolist():
        idx = np.flatnonzero(sizes == k)
        q_new[idx], tris[idx, : k - 2] = _solve_size(
            a[idx], b[idx], ring[idx, :k], q_old[idx], measure, prune
        )
    return q_new, tris


def _solve_padded(a, b, ring, sizes, measure: str, m: int):
    """``solve_rings`` of rings of at most ``PAD_M`` vertices by the padded kernel:
    ``(q_new (n,), tris (n, min(m, PAD_M) - 2, 3))``, rows past a ring's size -1."""
    n = len(a)
    # what the slots past a ring's size hold never matters (masked in the kernel, tested
    # with zeros, huge values and NaN): zero-pad or cut the vertex axis to PAD_M
    ring = ring[:, :PAD_M] if m >= PAD_M else np.pad(ring, ((0, 0), (0, PAD_M - m), (0, 0)))
    cap = _capacity(n)
    size_pad = np.full(cap, MIN_M, np.int32)  # padding rings: all-zero triangles
    size_pad[:n] = sizes
    soa = [*to_chunks(a, b, ring, cap), size_pad.reshape(-1, CHUNK)]
    q_new, tris = _parallel_chunks(solve_padded_chunks, soa, measure=measure)
    tris = _unchunk_tris(tris, n)[:, : min(m, PAD_M) - 2]
    tris[np.arange(tris.shape[1]) >= sizes[:, None] - 2] = -1  # rows of the pad polygon
    return _unchunk_q(q_new, n), tris


def _solve_size(a, b, ring, q_old, measure: str, prune: bool | str):
    """``solve_rings`` of rings of one size ``m > PAD_M`` (pruned as ``prune`` says)."""
    n, m = ring.shape[:2]
    cap = _capacity(n)
    soa = to_chunks(a, b, ring, cap)
    if not prune or (prune is True and m < PRUNE_MIN_M):
        q_new, tris = _parallel_chunks(solve_chunks, soa, measure=measure)
        return _unchunk_q(q_new, n), _unchunk_tris(tris, n)

    mode = "quality" if prune is True else prune
    q_pad = np.full(cap, np.inf)  # padding rings never survive the screen
    q_pad[:n] = q_old
    alive = _parallel_chunks(
        screen_chunks, [*soa, q_pad.reshape(-1, CHUNK)], measure=measure, mode=mode
    )
    idx = np.flatnonzero(_unchunk_q(alive, n))
    q_new = np.full(n, -np.inf)
    tris = np.broadcast_to(_fan(m), (n, m - 2, 3)).copy()
    if idx.size:
        sub = to_chunks(a[idx], b[idx], ring[idx], _capacity(idx.size))
        q2, t2 = _parallel_chunks(solve_chunks, sub, measure=measure)
        q_new[idx] = _unchunk_q(q2, idx.size)
        tris[idx] = _unchunk_tris(t2, idx.size)
    return q_new, tris
