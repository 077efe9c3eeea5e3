"""Vertex smoothing: move one vertex to raise the worst quality of the tets around it.

The kernel ``smooth_star`` is written for ONE vertex and its star (the tets containing it),
padded to a fixed capacity ``K``; ``smooth_pass`` gathers many stars into padded batches and
runs the kernel under ``jax.vmap``. Vertices solved in the same batch share no tet (they are
an independent set of the vertex-edge graph: maximal independent sets built by Luby-style
rounds with "worst star first" priorities), so their moves never interact; batches run one
after the other and each sees the positions the previous batches produced.

Objective. The true objective of a vertex is the smallest quality of its star, a nonsmooth
max-min. Solvers work on a smooth surrogate (``soft-min`` of log-quality, below) or directly
on the nonsmooth objective (``"active_set"``, after Freitag & Ollivier-Gooch), and every
result goes through the same safeguard: candidate points on the segment from the old to the
new position are scored with the TRUE minimum quality, and a move is accepted only if that
minimum rises by at least ``min_gain`` and no tet of positive quality becomes inverted or
degenerate (hill climbing). A rejected vertex stays exactly where it was.

Boundary. The kernel moves the vertex in ``v0 + h * basis @ t`` with ``t`` in R^3 and a
per-vertex (3, 3) ``basis`` whose unused columns are zero: identity for a free vertex, two
orthonormal in-plane vectors for a vertex sliding on a flat surface, one unit direction for a
vertex sliding along a straight subsegment line; one compiled kernel serves all three.

Coordinates inside the kernel are relative to ``v0`` (quality is translation invariant), and
``t`` is in units of the star's mean edge length ``h`` so that tolerances are scale free.
"""

from __future__ import annotations

import functools
import inspect
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._aot import cached_call, call_specs, prefetch_calls
from ._config import parallel_map
from ._errors import JtetError
from ._predicates import orient3d_tets
from ._quality import (
    _SIN_REGULAR,
    OBTUSE_BIAS,
    _cross,
    _dot,
    _safe_div,
    _TetGeometry,
    get_measure,
    tet_all_measures,
)
from ._topology import csr_rows

# For a tet whose local vertex i is the smoothed vertex v, the other three vertices in an
# order that makes (v, f0, f1, f2) an even permutation of the tet, hence positively oriented
# exactly when the tet is: (0,1,2,3), (1,0,3,2), (2,3,0,1), (3,2,1,0) without their head.
STAR_PERM = np.array([[1, 2, 3], [0, 3, 2], [3, 0, 1], [2, 1, 0]], dtype=np.int64)

SOLVERS = ("bfgs", "ncg", "bfgs_tr", "active_set", "hybrid")
# Stars up to 56 tets share one kernel shape (K = 56). A second, smaller shape (K = 32)
# for the same 32-star batches cost a second ~10 s CPU compile in a new process and a
# second executable to load, and its calls were no faster overall (fewer stars per
# batch); the 128-star batches of large colours do gain from it (``LARGE_CAPACITY``),
# and only large meshes build it. The kernel is bound by the
# work per padded slot (every slot's quality is evaluated ~45 times per star; measured
# when each evaluation was six dihedral pieces, now only the 5 worst tets' are), so the
# capacity is the smallest multiple of 8 above the stars of Gmsh and optimized fTetWild
# meshes (at most 50 tets measured; a mean of ~27): calls 12 % faster than at K = 64,
# the same output on the benchmark meshes (K = 40 rounds some reductions differently;
# 48 sends the rare 49-50-tet stars to the 128 shape, a second compile).
DEFAULT_CAPACITIES = (56, 128)
# A colour calls the large batch size (``smooth_pass``'s ``batch_sizes``) only when it
# fills at least this many large batches with stars of at most ``LARGE_CAPACITY`` tets:
# enough calls for both worker threads, and the reference meshes of 10k-33k tets (at
# most ~460 stars per colour) never need the large kernel's build. The first smoothing
# passes of meshes from ~50k tets do (``_driver.LARGE_SMOOTHING_TETS``).
LARGE_BATCHES_MIN = 4
# Star capacity of the large batches. A call's work per lane grows with K: 128 stars of at
# most 32 tets took 38 us per star at K = 32 and 53 at K = 56 (983k-tet cube, two
# threads, medians of 5), with the same new positions. 92-97 % of the stars of Gmsh
# meshes have at most 32 tets; the others go to small batches at K = 56.
LARGE_CAPACITY = 32

# ---------------------------------------------------------------------------------------
# Quality of a star as a function of the moving vertex.


def _corners(x: Float[Array, "3"], rel: Float[Array, "K 3 3"]):
    p0 = (x[0], x[1], x[2])
    p1, p2, p3 = ((rel[:, j, 0], rel[:, j, 1], rel[:, j, 2]) for j in range(3))
    return p0, p1, p2, p3


# Measures that are a minimum over the six dihedral angles' (biased) sines: the solvers see
# the six pieces, not their minimum (two near-minimal pieces of one tet otherwise look like
# one smooth function, and the ascent, blind to the second, stalls where they cross:
# measured on a 182k-tet cube, a pair of free vertices stuck at 25.2 degrees).
_PIECEWISE = {"min_sine": 1.0, "biased_min_sine": OBTUSE_BIAS}


def star_components(
    x: Float[Array, "3"], rel: Float[Array, "K 3 3"], measure: str
) -> Float[Array, "K C"]:
    """Smooth pieces of each star tet's quality, for the solvers' models (not for acceptance).

    ``x`` is the moving vertex and ``rel`` the star faces (K, vertex f0..f2, xyz), both in the
    same (relative) frame. For ``min_sine`` the six normalized dihedral sines
    |N_k x N_l| / (|N_k| |N_l|) / sin(regular) (C = 6) of a correct tet, the largest of the
    six -|sin| (six times) of an inverted one: the min-sine of a tet is itself nonsmooth,
    so the surrogate and the active-set step see every piece, and the minimum over pieces
    is exactly ``min_sine``; ``biased_min_sine`` likewise, with obtuse angles' sines times
    ``OBTUSE_BIAS``. For the other measures (smooth wherever the tet is not degenerate) the
    quality itself (C = 1).
    """
    p0, p1, p2, p3 = _corners(x, rel)
    if measure in _PIECEWISE:
        bias = _PIECEWISE[measure]
        g = _TetGeometry(p0, p1, p2, p3)
        n = g.normals
        nsq = [_dot(v, v) for v in n]
        sgn = jnp.sign(g.d)
        sines = []
        for f0, f1 in _TetGeometry.EDGE_FACES:
            c = _cross(n[f0], n[f1])
            s2 = _safe_div(_dot(c, c), nsq[f0] * nsq[f1])
            if bias != 1.0:  # as in _quality._signed_min_sine: obtuse angles count less
                s2 = jnp.where(_dot(n[f0], n[f1]) > 0, (bias * bias) * s2, s2)
            # sqrt'(0) is infinite: the floor keeps gradients finite at degenerate tets
            sines.append(sgn * jnp.sqrt(jnp.maximum(s2, 1e-300)) / _SIN_REGULAR)
        sines = jnp.stack(sines, axis=-1)
        # An inverted tet's min-sine is -min|sin| = the MAX of its (negative) pieces: all
        # six pieces take that value, so the min over pieces is min_sine for every tet and
        # the solvers climb the true objective (with -|sin| pieces they climbed -max|sin|
        # and the true-objective safeguard rejected their untangling moves).
        return jnp.where(g.d[:, None] < 0, jnp.max(sines, axis=-1, keepdims=True), sines)
    return get_measure(measure)(p0, p1, p2, p3)[:, None]


def star_qualities(
    x: Float[Array, "3"], rel: Float[Array, "K 3 3"], mask: Bool[Array, " K"], measure: str
) -> Float[Array, " K"]:
    """TRUE quality (``jtet.MEASURES[measure]``) of every star tet with the vertex at ``x``;
    +inf in padded slots. ``x`` and ``rel`` in the same frame."""
    return jnp.where(mask, get_measure(measure)(*_corners(x, rel)), jnp.inf)


def _subsets(a: int) -> tuple[np.ndarray, ...]:
    """All index subsets of size 1, 2, 3 of range(a), one (count, size) array per size."""
    import itertools

    return tuple(
        np.array(list(itertools.combinations(range(a), k)), dtype=np.int64) for k in (1, 2, 3)
    )


def _min_norm_in_hull(G: Float[Array, "A 3"], valid: Bool[Array, " A"]) -> Float[Array, "3"]:
    """Exact min-norm point of the convex hull of the valid rows of ``G`` (A small).

    The min-norm point d of the hull of the active gradients is the steepest ascent
    direction of their minimum (g . d >= |d|^2 for every active g). In R^3 it is the affine
    min-norm point of a face of at most 3 points (or 0 when 0 is in the hull), so every
    subset of size 1..3 is solved in closed form (equality-constrained least squares) and
    the one with non-negative weights that satisfies the optimality condition is kept. Returns 0 when none qualifies (stationary point).
    """
    a = G.shape[0]
    best_d = jnp.zeros(3)
    best_n = jnp.inf
    for idx in _subsets(a):
        S = G[idx]  # (n_sub, k, 3)
        k = idx.shape[1]
        # affine min-norm point g0 + sum_i w_i (g_i - g0) of each subset, closed form
        # (no LAPACK: batched tiny solves are custom calls, slow on CPU under vmap)
        g0 = S[:, 0]
        if k == 1:
            d = g0
            w_ok = jnp.ones(len(idx), bool)
        elif k == 2:
            e = S[:, 1] - g0
            ee = jnp.sum(e * e, -1)
            lam = -jnp.sum(g0 * e, -1) / ee  # inf/nan for coincident points: rejected
            d = g0 + lam[:, None] * e
            w_ok = (lam >= 0.0) & (lam <= 1.0)
        else:
            e1, e2 = S[:, 1] - g0, S[:, 2] - g0
            a11, a12, a22 = jnp.sum(e1 * e1, -1), jnp.sum(e1 * e2, -1), jnp.sum(e2 * e2, -1)
            b1, b2 = -jnp.sum(g0 * e1, -1), -jnp.sum(g0 * e2, -1)
            det = a11 * a22 - a12 * a12  # ~0 for collinear points: inf/nan, rejected
            w1 = (b1 * a22 - b2 * a12) / det
            w2 = (a11 * b2 - a12 * b1) / det
            d = g0 + w1[:, None] * e1 + w2[:, None] * e2
            w_ok = (w1 >= 0.0) & (w2 >= 0.0) & (w1 + w2 <= 1.0)
        dd = jnp.sum(d * d, axis=-1)
        rates = d @ G.T  # (n_sub, a)
        tol = 1e-9 * dd + 1e-14
        optimal = jnp.all(~valid[None, :] | (rates >= (dd - tol)[:, None]), axis=-1)
        ok = jnp.all(valid[idx], axis=-1) & w_ok & optimal & jnp.isfinite(dd)
        dd = jnp.where(ok, dd, jnp.inf)
        j = jnp.argmin(dd)
        better = dd[j] < best_n
        best_d = jnp.where(better, d[j], best_d)
        best_n = jnp.where(better, dd[j], best_n)
    return jnp.where(jnp.isfinite(best_n), best_d, 0.0)


def _smallest(c: Float[Array, " N"], k: int) -> Int[Array, " k"]:
    """Indices of the k smallest entries (k <= N, small), ties to the lowest index, each
    index once (also among +inf entries, e.g. padded slots): k passes of a min and a
    min-index over the entries not taken yet (two plain reductions vectorize on CPU;
    ``argmin``, a variadic reduction, measured 1.5x slower, ``lax.top_k`` and sorts ~10x
    slower under vmap)."""
    idx = jnp.arange(c.shape[0])

    def pick(r, state):
        out, free = state
        rest = jnp.where(free, c, jnp.inf)
        i = jnp.min(jnp.where(free & (rest == jnp.min(rest)), idx, c.shape[0]))
        return out.at[r].set(i), free & (idx != i)

    # a loop, not k unrolled copies: the same work, ~1.5 s less to compile (measured)
    start = (jnp.zeros(k, idx.dtype), jnp.ones(c.shape[0], bool))
    return jax.lax.fori_loop(0, k, pick, start)[0]


GRAD_STEP = 1e-6  # central-difference step of the active pieces' gradients, units of h


def _solve_active_set(t0, B, rel, mask, measure, max_iters, n_trials, active_rel, n_active=5):
    """Nonsmooth max-min ascent (after Freitag & Ollivier-Gooch) on the true components.

    Each step: the active set is the (at most ``n_active``) components within a relative
    width of the minimum; the direction is the min-norm point of the hull of their
    gradients; the step length is predicted where the linearized active minimum meets the
    first inactive component, and ``n_trials`` step lengths around it (x2, x1, /2, ...)
    are scored with the true minimum in one vectorized evaluation. When no trial improves,
    the step is retried with a narrower active set (``active_rel`` / 10, / 100, then the
    minimum alone): a too wide set can hold 0 in its hull although the true objective
    still rises (measured: stalls ~4e-3 below the optimum without the retries). Stops when
    the narrowest set fails too.

    Only the ``n_active`` worst tets are seen as their C pieces (``star_components``);
    every other tet, and every trial, is its true quality, one number per tet. The k
    smallest pieces lie in the k tets of smallest quality, so the active set is the same;
    a tet outside them enters the step length through its quality (the piece that is its
    minimum). Evaluating the true quality costs about half of the six pieces, and the
    rates and trials are most of the kernel's work.
    """
    C = star_components(jnp.zeros(3), rel[:1], measure).shape[-1]
    widths = jnp.array([active_rel, active_rel * 0.1, active_rel * 0.01, 0.0])
    scales = 2.0 ** (1.0 - jnp.arange(n_trials))
    slots = jnp.arange(rel.shape[0])

    def values(t):  # true quality of every star tet, +inf in padded slots
        return star_qualities(B @ t, rel, mask, measure)

    def body(state):
        i, t, q, level = state
        qmin = jnp.min(q)
        # the n_active worst tets as pieces, and the n_active smallest of their pieces
        tets = _smallest(q, n_active)
        rel_worst = rel[tets]
        real = mask[tets][:, None]

        def worst_pieces(t):
            return jnp.where(real, star_components(B @ t, rel_worst, measure), jnp.inf)

        pieces = worst_pieces(t)  # (n_active, C)
        top = _smallest(pieces.reshape(-1), n_active)
        top_tet, top_comp = top // C, top % C
        rel_top = rel_worst[top_tet]

        def top_comps(t):
            return star_components(B @ t, rel_top, measure)[jnp.arange(n_active), top_comp]

        # Gradients by central differences along the three coordinates (t is in units of
        # h: truncation ~1e-12, round-off ~1e-10 relative): six evaluations of n_active
        # tets. jacfwd's tangent code was ~40 % of the compiled kernel (compile 9.4 ->
        # 5.5 s CPU, experiments/results/compile.md).
        steps = GRAD_STEP * jnp.eye(3)
        G = ((jax.vmap(top_comps)(t + steps) - jax.vmap(top_comps)(t - steps)) / (2 * GRAD_STEP)).T
        active_top = pieces.reshape(-1)[top] <= qmin + widths[level] * jnp.abs(qmin) + 1e-14
        d = _min_norm_in_hull(G, active_top)
        dn = jnp.sqrt(d @ d)
        rate_a = jnp.min(jnp.where(active_top, G @ d, jnp.inf))
        # Rates along d only place the trial steps (the trials are scored exactly), so a
        # forward difference does: one evaluation instead of a JVP (2.7x an evaluation,
        # measured). A step of 1e-6 / |d| (units of h) keeps truncation ~1e-6 and
        # round-off ~1e-10 relative.
        fd = 1e-6 / jnp.maximum(dn, 1e-300)
        t_fd = t + fd * d
        # the worst tets' inactive pieces, then every other tet as its quality
        p_flat = pieces.reshape(-1)
        p_rate = (worst_pieces(t_fd).reshape(-1) - p_flat) / fd
        p_active = jnp.any((jnp.arange(p_flat.shape[0])[:, None] == top) & active_top, axis=1)
        p_closing = jnp.isfinite(p_flat) & ~p_active & (p_rate < rate_a)
        p_alpha = (p_flat - qmin) / jnp.where(p_closing, rate_a - p_rate, 1.0)
        others = mask & ~jnp.any(slots[:, None] == tets[None, :], axis=1)
        q_rate = jnp.where(others, (values(t_fd) - q) / fd, 0.0)
        q_closing = others & (q_rate < rate_a)
        q_alpha = (q - qmin) / jnp.where(q_closing, rate_a - q_rate, 1.0)
        alpha_max = 0.5 / jnp.maximum(dn, 1e-300)  # never more than h/2 per step
        closing_alpha = jnp.concatenate(
            [jnp.where(p_closing, p_alpha, jnp.inf), jnp.where(q_closing, q_alpha, jnp.inf)]
        )
        alpha = jnp.minimum(jnp.min(closing_alpha), alpha_max)
        T = t[None, :] + (alpha * scales)[:, None] * d[None, :]
        QT = jax.vmap(values)(T)  # (n_trials, K): kept, the next step needs no re-evaluation
        vals = jnp.min(QT, axis=-1)
        vals = jnp.where(jnp.isfinite(vals), vals, -jnp.inf)
        j = jnp.argmax(vals)
        improved = (vals[j] > qmin) & (dn > 1e-14) & (rate_a > 0)
        t_new = jnp.where(improved, T[j], t)
        q_new = jnp.where(improved, QT[j], q)
        return i + 1, t_new, q_new, jnp.where(improved, 0, level + 1)

    def cond(state):
        i, _, _, level = state
        return (i < max_iters) & (level < len(widths))

    # Carries that depend on the lane from the start: under vmap, JAX batches a while loop
    # whose carries start unbatched once more, to find which ones the body batches (the
    # kernel lowered in 0.95 -> 0.74 s, the same compiled program, outputs to the bit)
    lane = mask[0]
    zero = jnp.where(lane, 0, 0)
    t0 = jnp.where(lane, t0, t0)
    _, t, _, _ = jax.lax.while_loop(cond, body, (zero, t0, values(t0), zero))
    return t


def smooth_star(
    v0: Float[Array, "3"],
    basis: Float[Array, "3 3"],
    opp: Float[Array, "K 3 3"],
    mask: Bool[Array, " K"],
    measure: str = "min_sine",
    *,
    solver: str = "active_set",
    max_iters: int = 15,
    sharpness: tuple[float, ...] = (20.0, 80.0),
    min_gain: float = 1e-9,
    n_backtrack: int = 12,
    n_trials: int = 6,
    active_rel: float = 1e-2,
    rtol: float = 1e-7,
    atol: float = 1e-9,
) -> tuple[Float[Array, "3"], Float[Array, ""], Float[Array, ""]]:
    """Move one vertex to raise the minimum quality of its star (hill climbing).

    Args:
        v0: (3,) current position of the vertex.
        basis: (3, 3) columns span the allowed motion (unused columns zero): identity for
            a free vertex, two orthonormal in-plane vectors for sliding on a plane, one unit
            direction for sliding on a line, all zero for a fixed vertex.
        opp: (K, 3, 3) star faces: for each tet containing the vertex, the coordinates of
            its three other vertices, ordered so that (v, f0, f1, f2) has the orientation of
            the tet (see ``STAR_PERM``). Padded slots may hold anything finite.
        mask: (K,) True for real star tets.
        measure: quality measure name (``jtet.MEASURES``), static.
        solver: ``"bfgs"``, ``"ncg"``, ``"bfgs_tr"`` (optimistix on the soft-min surrogate),
            ``"active_set"`` (nonsmooth ascent on the true objective) or ``"hybrid"`` (one
            BFGS stage at ``sharpness[0]``, then the active-set ascent), static.
        max_iters: iteration cap of each solver stage, static.
        sharpness: soft-min sharpness p of each surrogate stage (continuation), static.
        min_gain: the true star minimum must rise by more than this to accept a move.
        n_backtrack: number of points v0 + 2^-j (x* - v0), j < n_backtrack, scored by the
            true objective in the final safeguard.
        n_trials: step lengths scored per active-set iteration, static.
        active_rel: active-set width, relative to the current minimum.

    Returns:
        (new_pos (3,), q_old, q_new): the accepted position (``v0`` itself when no move
        raises the minimum), and the star's minimum quality before and after. ``q_new >
        q_old + min_gain`` iff the vertex moved; every star tet with positive quality keeps
        a quality >= min(its old quality, min_gain) > 0.
    """
    any_real = jnp.any(mask)
    # Padded slots get a copy of a real face: garbage there could make NaN gradients that
    # leak through jnp.where into the real lanes.
    first = jnp.argmax(mask)
    opp = jnp.where(mask[:, None, None], opp, opp[first][None])
    rel = opp - v0
    dist = jnp.sqrt(jnp.sum(rel * rel, axis=-1))  # (K, 3)
    n_real = jnp.maximum(jnp.sum(mask), 1)
    h = jnp.sum(jnp.where(mask[:, None], dist, 0.0)) / (3.0 * n_real)
    h = jnp.where(h > 0, h, 1.0)
    B = basis * h

    # Acceptance is decided in GLOBAL coordinates on the rounded candidate points, i.e. on
    # exactly the numbers the mesh will store (the solvers use the relative frame).
    t0 = jnp.zeros(3)
    if solver != "active_set":
        # optimistix (and equinox, lineax) only for the surrogate solvers: ~0.5 s of
        # imports the default active-set path does not pay
        from ._surrogate import _solve_surrogate
    if solver == "active_set":
        t_star = _solve_active_set(t0, B, rel, mask, measure, max_iters, n_trials, active_rel)
    elif solver == "hybrid":  # a blunt BFGS stage finds the basin, the active set polishes
        t_star = _solve_surrogate(
            t0, B, rel, mask, measure, "bfgs", tuple(sharpness[:1]), max_iters, rtol, atol
        )
        t_star = jnp.where(jnp.all(jnp.isfinite(t_star)), t_star, t0)
        t_star = _solve_active_set(t_star, B, rel, mask, measure, max_iters, n_trials, active_rel)
    else:
        t_star = _solve_surrogate(
            t0, B, rel, mask, measure, solver, tuple(sharpness), max_iters, rtol, atol
        )
    t_star = jnp.where(jnp.all(jnp.isfinite(t_star)), t_star, t0)

    # Safeguard on the TRUE objective: the best of x0 + 2^-j (x* - x0).
    s = 0.5 ** jnp.arange(n_backtrack, dtype=jnp.float64)
    T = s[:, None] * t_star[None, :]
    P = v0[None, :] + T @ B.T  # (J, 3) candidate positions, rounded as they will be stored
    # v0 itself is the last row: one copy of the measure's code for both
    Q = jax.vmap(lambda x: star_qualities(x, opp, mask, measure))(jnp.vstack([P, v0[None]]))
    Q, q0 = Q[:-1], Q[-1]  # (J, K), (K,)
    q_old = jnp.min(q0)
    qmin = jnp.min(Q, axis=-1)
    # a correct tet stays clearly correct: above min_gain, or at least as good as before
    # (a float-positive quality at round-off level is no proof of orientation)
    keeps_positive = jnp.all((q0 <= 0.0) | (Q >= jnp.minimum(q0, min_gain)), axis=-1)
    ok = keeps_positive & jnp.isfinite(qmin) & (qmin > q_old + min_gain) & any_real
    j = jnp.argmax(jnp.where(ok, qmin, -jnp.inf))
    accept = ok[j]
    new_pos = jnp.where(accept, P[j], v0)
    q_new = jnp.where(accept, qmin[j], q_old)
    return new_pos, q_old, q_new


@functools.cache
def batched_smoother(measure: str, solver: str, max_iters: int, **options):
    """Jitted ``vmap`` of ``smooth_star`` over (v0 (B,3), basis (B,3,3), opp (B,K,3,3),
    mask (B,K)) for fixed static settings; cached so a pass never re-traces it, and
    exported to disk (``_aot``) so a new process does not trace it either."""
    fn = functools.partial(
        smooth_star, measure=measure, solver=solver, max_iters=max_iters, **options
    )
    settings = (measure, solver, max_iters, tuple(sorted(options.items())))
    # siblings: the first call also starts loading the other star capacities an earlier
    # process exported, so the capacities load side by side, not one after the other
    return functools.partial(cached_call, "smooth_star", settings, _lane_groups(fn), siblings=True)


# A small batch (at most GROUPED_LANES stars) runs its lanes in groups of LANE_GROUP, one
# group after the other, and skips the groups that hold no star (padding). Under one
# vmap every lane pays for the slowest lane's iterations and padded lanes cost as much
# as real ones, so a call holding 1-8 stars cost as much as a full one: the climbs after
# perturbation kicks make mostly such calls (holeplate: 540 of 724 calls held 1-8
# stars). Measured at K = 56 (holeplate stars, one thread): 1-8 stars of 32 lanes 1.4 ms
# a call instead of 2.9-3.0; full calls 114 us a star instead of 94. One executable per
# shape as before (a separate 8-lane shape cost a second ~10 s CPU compile). Large
# batches (``LARGE_CAPACITY``) are always full: they keep the plain vmap.
LANE_GROUP = 8
GROUPED_LANES = 32


def _grouped(batch: int) -> bool:
    """Whether a call of ``batch`` lanes runs them in groups (``_lane_groups``)."""
    return batch <= GROUPED_LANES and batch % LANE_GROUP == 0 and batch > LANE_GROUP


def _lane_groups(fn):
    """``jax.vmap(fn)`` over (v0 (B, 3), basis (B, 3, 3), opp (B, K, 3, 3), mask (B, K)),
    in groups of ``LANE_GROUP`` lanes for B <= ``GROUPED_LANES``; lanes whose mask is all
    False are padding, and a group of padding only returns (v0, 0, 0) unsolved."""
    lanes = jax.vmap(fn)

    def run(v0, basis, opp, mask):
        B = v0.shape[0]
        if not _grouped(B):
            return lanes(v0, basis, opp, mask)
        zeros = jnp.zeros(LANE_GROUP, v0.dtype)

        def group(args):
            v0, basis, opp, mask = args
            return jax.lax.cond(
                jnp.any(mask), lambda: lanes(v0, basis, opp, mask), lambda: (v0, zeros, zeros)
            )

        def split(x):
            return x.reshape((B // LANE_GROUP, LANE_GROUP) + x.shape[1:])

        out = jax.lax.map(group, tuple(split(x) for x in (v0, basis, opp, mask)))
        return tuple(x.reshape((B,) + x.shape[2:]) for x in out)

    return run


# ---------------------------------------------------------------------------------------
# Host side: candidates, motion bases, independent sets, padded batches.


@dataclass(frozen=True)
class SmoothStats:
    """What one ``smooth_pass`` did.

    Attributes:
        attempts: vertices handed to the kernel.
        successes: vertices that moved (their star minimum rose by more than ``min_gain``).
        skipped: candidates not attempted because their star exceeds the largest capacity.
        pinned: boundary vertices that ``boundary="slide"`` would move but whose incident
            subfacets / subsegments are not flat / straight to ``slide_tol``, or that end
            a curved edge (kept fixed).
        moved: (successes,) int64 ids of the vertices that moved.
        moved_tets: (m,) bool, the tets with a moved vertex (the only ones whose quality
            changed).
        moved_measures: (quality ``measure``, min dihedral, max dihedral), each (k,), of
            the tets ``np.flatnonzero(moved_tets)`` at their new positions (degrees).
        worst_before, worst_after: smallest tet quality of the whole mesh before / after.
        n_colours: number of independent sets (sequential batches) the candidates needed.
        seconds: wall time of the pass.
    """

    attempts: int
    successes: int
    skipped: int
    pinned: int
    moved: np.ndarray = field(repr=False)
    moved_tets: np.ndarray = field(repr=False)
    worst_before: float
    worst_after: float
    n_colours: int
    seconds: float
    moved_measures: tuple = field(default=(), repr=False)


def _unit_rows(v: np.ndarray) -> np.ndarray:
    nrm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, nrm, out=np.zeros_like(v), where=nrm > 0)


def _snap(v: np.ndarray) -> np.ndarray:
    """Unit rows with round-off components zeroed: an axis-aligned plane or line then gets
    an exactly axis-aligned basis, and a slide leaves that coordinate bit-identical."""
    v = np.where(np.abs(v) < 1e-14, 0.0, v)
    return _unit_rows(v)


def plane_basis(normals: Float[np.ndarray, "k 3"]) -> Float[np.ndarray, "k 3 3"]:
    """(k, 3, 3) bases whose columns 0, 1 are orthonormal and orthogonal to each unit
    normal, column 2 zero. Built from the coordinate axis least aligned with the normal."""
    n = _snap(normals)
    k = len(n)
    axis = np.zeros((k, 3))
    axis[np.arange(k), np.argmin(np.abs(n), axis=1)] = 1.0
    u1 = _unit_rows(np.cross(n, axis))
    u2 = np.cross(n, u1)
    out = np.zeros((k, 3, 3))
    out[:, :, 0] = u1
    out[:, :, 1] = u2
    return out


def motion_bases(
    mesh, boundary: str = "fixed", slide_tol: float = 1e-10
) -> tuple[np.ndarray, np.ndarray, int]:
    """Per-vertex motion basis (n, 3, 3), movable mask (n,), and the number of pinned
    vertices (slide requested but the incident surface is not flat/straight to
    ``slide_tol``).

    ``boundary="fixed"``: interior vertices (``vertex_kind == 0``) get the identity, every
    other vertex is fixed. ``"slide"``: kind 1 vertices move in the plane of their surface,
    kind 2 along their straight subsegment line, kind 3 never. A sliding vertex is kept
    only if every subfacet containing it has a unit normal n_f with |n_f . u| <= slide_tol
    for each basis column u, and every subsegment containing it is parallel to its line
    to ``slide_tol``: then each incident subfacet moves within its own plane and the
    surface stays geometrically identical (provided no tet inverts, which the kernel
    guarantees). Vertices of subfacets next to an inverted or flat tet are pinned too:
    such a subfacet may be folded, and sliding would change the surface the folds cover;
    and the ends of curved edges (``TetMesh.curved_edges``), whose nodes stay only while
    the ends do.
    """
    if boundary not in ("fixed", "slide"):
        raise JtetError(f"boundary must be 'fixed' or 'slide', got {boundary!r}")
    from ._topology import FREE, SEGMENT, SURFACE

    topo = mesh.topology
    n = mesh.n_points
    kind = np.asarray(topo.vertex_kind)
    basis = np.zeros((n, 3, 3))
    free = kind == FREE
    basis[free] = np.eye(3)
    pinned = 0
    if boundary == "slide":
        surf = np.flatnonzero(kind == SURFACE)
        seg = np.flatnonzero(kind == SEGMENT)
        basis[surf] = plane_basis(np.asarray(topo.surface_normal)[surf])
        basis[seg, :, 0] = _snap(np.asarray(topo.segment_direction)[seg])
        sliding = np.zeros(n, bool)
        sliding[surf] = True
        sliding[seg] = True
        sliding &= np.abs(basis).sum(axis=(1, 2)) > 0  # a zero normal/direction: fixed
        bad = np.zeros(n, bool)
        pts = mesh.points
        sf = topo.faces[topo.subfacet]
        if len(sf):
            p = pts[sf]
            fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            degenerate = np.linalg.norm(fn, axis=1) == 0
            fn = _unit_rows(fn)
            verts = sf.reshape(-1)
            dots = np.einsum("ij,ijk->ik", np.repeat(fn, 3, axis=0), basis[verts])
            viol = (np.abs(dots).max(axis=1) > slide_tol) | np.repeat(degenerate, 3)
            bad[verts[viol]] = True
            # a subfacet next to an inverted or flat tet may be folded over its neighbours;
            # sliding a vertex of it changes the area the folds cover, i.e. the surface.
            # Next to positive tets it cannot fold (the kernel keeps them positive).
            ft = topo.face_tets[topo.subfacet]
            has = ft >= 0
            positive = np.ones(ft.shape, bool)
            positive[has] = orient3d_tets(pts, mesh.tets[ft[has]]) > 0
            bad[sf[~positive.all(axis=1)].reshape(-1)] = True
        se = topo.edges[topo.subsegment]
        if len(se):
            e = _unit_rows(pts[se[:, 1]] - pts[se[:, 0]])
            verts = se.reshape(-1)
            # a SURFACE vertex has no subsegment; for SEGMENT vertices column 0 is the line
            cr = np.linalg.norm(np.cross(np.repeat(e, 2, axis=0), basis[verts, :, 0]), axis=1)
            viol = sliding[verts] & (kind[verts] == SEGMENT) & (cr > slide_tol)
            bad[verts[viol]] = True
        if mesh.has_curved_edges:
            # a curved edge keeps its node only while both its ends stay where they are
            # (``_quadratic.curved_edges_kept``): a vertex sliding off one would write the
            # curved boundary back straight there
            bad[np.asarray(mesh.curved_edges.edges).reshape(-1)] = True
        bad &= sliding
        pinned = int(bad.sum())
        sliding &= ~bad
        basis[~(free | sliding)] = 0.0
    else:
        basis[~free] = 0.0
    movable = np.abs(basis).sum(axis=(1, 2)) > 0
    return basis, movable, pinned


def star_faces(mesh, verts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(ptr (n+1,), opp (S, 3)): for every vertex v, rows ptr[v]:ptr[v+1] of ``opp`` list
    the star faces of v (the other three vertices of each tet containing v, in the order
    of ``STAR_PERM``, so that (v, f0, f1, f2) is positively oriented like the tet).

    ``verts`` (optional (n,) bool mask): only these vertices get their star; the others
    get an empty one. A late pass smooths a few hundred vertices of a large mesh, and
    the whole-mesh gather cost more than their kernel calls (0.09 s at 182k tets).
    """
    topo = mesh.topology
    vptr = np.asarray(topo.vert_tets_ptr)
    sizes = np.diff(vptr)
    if verts is not None:
        sizes = np.where(np.asarray(verts, bool), sizes, 0)
    ptr = np.zeros(mesh.n_points + 1, np.int64)
    np.cumsum(sizes, out=ptr[1:])
    owner = np.repeat(np.arange(mesh.n_points), sizes)
    # rows of vert_tets for the selected vertices: each vertex's run, concatenated
    rows = vptr[owner] + (np.arange(len(owner)) - ptr[owner])
    tv = mesh.tets[np.asarray(topo.vert_tets)[rows]]
    local = np.argmax(tv == owner[:, None], axis=1)
    opp = np.take_along_axis(tv, STAR_PERM[local], axis=1)
    return ptr, opp


def star_tets(topo, verts: np.ndarray, m: int) -> Bool[np.ndarray, " m"]:
    """(m,) bool: the tets that have one of the vertices ``verts`` (k,) (from their stars,
    not a scan of every tet)."""
    out = np.zeros(m, bool)
    out[topo.vert_tets[csr_rows(topo.vert_tets_ptr, np.asarray(verts, np.int64))[0]]] = True
    return out


def independent_sets(
    candidates: Bool[np.ndarray, " n"], edges: np.ndarray, priority: np.ndarray
) -> list[np.ndarray]:
    """Split the candidate vertices into independent sets of the graph ``edges`` (E, 2).

    Each set is a MAXIMAL independent set of the candidates not yet assigned, built by
    Luby-style rounds: every undecided vertex whose ``priority`` (lower = earlier) beats
    all its undecided neighbours joins the set, and its neighbours are excluded from this
    set; rounds repeat until nothing is undecided. Two vertices of one set are never
    joined by an edge, hence share no tet. Vectorized over edges (no loop over vertices).
    Maximal sets need fewer colours than one Jones-Plassmann round per colour (measured on
    the Gmsh cube: 24 -> 11 sets), so the kernel runs fewer, fuller batches.
    """
    remaining = np.asarray(candidates, bool).copy()
    a, b = edges[:, 0], edges[:, 1]
    live = remaining[a] & remaining[b]
    a, b = a[live], b[live]
    a_first = priority[a] < priority[b]
    sets = []
    while remaining.any():
        chosen = np.zeros_like(remaining)
        undecided = remaining.copy()
        while undecided.any():
            both = undecided[a] & undecided[b]
            beaten = np.zeros_like(remaining)
            beaten[b[both & a_first]] = True
            beaten[a[both & ~a_first]] = True
            new = undecided & ~beaten
            chosen |= new
            undecided &= ~new
            # neighbours of the new members cannot join this set
            blocked = np.zeros_like(remaining)
            blocked[b[new[a]]] = True
            blocked[a[new[b]]] = True
            undecided &= ~blocked
        sets.append(np.flatnonzero(chosen))
        remaining &= ~chosen
        keep = remaining[a] & remaining[b]
        a, b, a_first = a[keep], b[keep], a_first[keep]
    return sets


def smooth_pass(
    mesh,
    *,
    measure: str = "min_sine",
    boundary: str = "fixed",
    threshold: float | None = None,
    candidates: np.ndarray | None = None,
    quality: np.ndarray | None = None,
    solver: str = "active_set",
    max_iters: int = 8,
    n_trials: int = 3,
    capacities: tuple[int, ...] = DEFAULT_CAPACITIES,
    min_gain: float = 1e-9,
    sharpness: tuple[float, ...] = (20.0, 80.0),
    slide_tol: float = 1e-10,
    batch_sizes: tuple[int, int] = (32, 128),
    levels: int = 4,
    seed: int = 0,
    min_scaled_jacobian: float | None = None,
):
    """One smoothing pass over the mesh: every candidate vertex is tried once.

    Args:
        mesh: the ``TetMesh``.
        measure: quality measure to raise (``jtet.MEASURES``).
        boundary: ``"fixed"`` (only interior vertices move) or ``"slide"`` (flat-surface
            vertices move in their plane, straight-subsegment vertices along their line).
        threshold: only vertices of tets with quality below this are tried (None: all).
        candidates: optional (n,) bool mask of vertices to try (e.g. those whose
            neighbourhood changed); combined with ``threshold``.
        quality: optional (m,) ``measure`` of every tet of ``mesh``, if already known.
        solver, max_iters, n_trials, min_gain, sharpness: see ``smooth_star``. A pass
            needs no converged stars (the optimizer smooths again where it helps): 8
            iterations of 3 trial steps measured 1.5-2.5x faster than 15 x 6 over whole
            ``improve`` runs at equal worst quality (``bench_improve.py --smooth-effort``).
        capacities: star capacities K (padded tets per star); a star larger than the
            largest is skipped and counted.
        slide_tol: flatness / straightness tolerance for sliding (see ``motion_bases``).
        batch_sizes: (small, large) vertices per kernel call. A colour with at least
            ``LARGE_BATCHES_MIN`` large batches of stars of at most ``LARGE_CAPACITY`` tets
            runs full large batches of them at that capacity; every other star goes to a
            small batch at the smallest of ``capacities`` holding it. Fixed sizes, so the
            kernel compiles once per (capacity, batch) pair, and small meshes never call
            (nor compile) the large one. A call costs ~2.5 ms of fixed work plus its lanes:
            32 lanes per call spend ~84 us of two cores per star, 128 lanes ~59 (K = 56;
            983k-tet cube, 8192 stars, medians of 5, before the lane groups below made
            full 32-lane calls ~20 % slower; batch 256 rounds differently). A
            separate batch size of 8 for the perturbation rounds' climbs (holeplate: 540
            of 724 calls hold 1-8 vertices) raised the cold compile overhead on the cube
            from 6.1 to 10.5-11.0 s; the small batch runs its lanes in groups of 8
            instead, skipping the groups of padding (``_lane_groups``), in the same
            executable.
        levels: the worst-star quality is cut into this many quantile levels; worse levels
            are smoothed first, random order within a level (see ``independent_sets``).
        seed: seed of the random tie-breaking.
        min_scaled_jacobian: floor of the guard on curved tets (``_curved_guard``): a
            move that bends a tet with a curved edge below it and below the star's worst
            is undone (None: no guard).

    Returns:
        (new TetMesh, SmoothStats). The new mesh has the same tets, regions and protected
        entities; only the points of moved vertices differ. Every moved vertex raised the
        minimum quality of its star, and no tet of positive quality became inverted or
        degenerate, so the mesh's worst quality never decreases. The topology of the input
        is reused by the new mesh (smoothing changes no connectivity and keeps every
        subfacet in its plane).
    """
    t_start = time.perf_counter()
    get_measure(measure)
    if solver not in SOLVERS:
        raise JtetError(f"unknown smoothing solver {solver!r}; choose one of {SOLVERS}")
    capacities = tuple(sorted(int(k) for k in capacities))
    topo = mesh.topology
    n = mesh.n_points
    tets = mesh.tets
    q = mesh.quality(measure) if quality is None else np.asarray(quality)
    worst_before = float(q.min())

    basis, cand, pinned = motion_bases(mesh, boundary, slide_tol)
    if candidates is not None:
        c = np.asarray(candidates, bool)
        if c.shape != (n,):
            raise JtetError(f"candidates must be a bool mask of shape ({n},), got {c.shape}")
        cand &= c
    # worst quality of each candidate's star (+inf elsewhere): only the candidates' tets
    # are read (late passes: a few hundred stars of a large mesh)
    vq = np.full(n, np.inf)
    stars = np.flatnonzero(cand & (np.diff(topo.vert_tets_ptr) > 0))
    if len(stars):
        pos, starts = csr_rows(topo.vert_tets_ptr, stars)
        vq[stars] = np.minimum.reduceat(q[topo.vert_tets[pos]], starts)
    if threshold is not None:
        cand &= vq < threshold
    ptr, opp_ids = star_faces(mesh, cand)
    size = np.diff(ptr)
    cand &= size > 0
    too_big = cand & (size > capacities[-1])
    cand &= ~too_big

    # priority: quantile level of the star's worst quality (worst first), random within.
    # The random draws go to the vertices of tets, in id order: points no tet uses (kept
    # as they are) take none, so appending such points changes nothing of the run.
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero(cand)
    level = np.zeros(n)
    if len(idx) and levels > 1:
        cuts = np.quantile(vq[idx], np.linspace(0, 1, levels + 1)[1:-1])
        level[idx] = np.searchsorted(cuts, vq[idx], side="right")
    used = np.flatnonzero(np.diff(topo.vert_tets_ptr) > 0)
    priority = level
    priority[used] += rng.random(len(used))
    sets = independent_sets(cand, topo.edges, priority)

    pts = np.array(mesh.points, dtype=np.float64)
    # one partial serves every capacity (the shapes of its arguments pick the executable)
    kernel = _pass_kernel(measure, solver, max_iters, min_gain, sharpness, n_trials)
    plan = [_colour_tasks(verts, size, capacities, batch_sizes) for verts in sets]
    attempts = sum(len(task[2]) for tasks in plan for task in tasks)
    # every (capacity, batch) shape the pass will call, built at once on the worker
    # threads: a new process compiles them side by side instead of one per first call
    # (cold: ~10 s each for the smoothing kernel)
    # (one prefetch for all capacities: one per capacity built K = 32 and K = 64 one
    # after the other, as each prefetch of a single shape runs on the calling thread)
    shapes = sorted({(K, batch) for tasks in plan for K, batch, _ in tasks})
    prefetch_calls(kernel, [_kernel_structs(K, b) for K, b in shapes])
    moved_all = []
    guard = min_scaled_jacobian is not None and mesh.has_curved_edges
    if guard:
        from ._curved_guard import curved_corners

        near_curved = curved_corners(mesh)  # only their moves can bend a curved tet
    for tasks in plan:
        # one colour's vertices share no tet: its batches are independent, solved in
        # parallel, and every batch reads only points no other batch of it writes
        results = parallel_map(
            lambda task: _solve_batch(kernel, *task, pts, basis, ptr, opp_ids), tasks
        )
        for ids, positions in results:
            if guard:
                check = np.flatnonzero(near_curved[ids])
                bends = _bends_curved_tets(
                    mesh, topo, pts, ids[check], positions[check], min_scaled_jacobian
                )
                keep = np.ones(len(ids), bool)
                keep[check[bends]] = False
                ids, positions = ids[keep], positions[keep]
            pts[ids] = positions
            moved_all.append(ids)
    moved = np.concatenate(moved_all) if moved_all else np.zeros(0, np.int64)
    new = mesh.replace(points=pts)
    # connectivity and subfacet planes are unchanged: the topology stays valid
    new.__dict__["topology"] = topo
    # only tets with a moved vertex changed quality
    redo = star_tets(topo, moved, len(tets))
    # one evaluation of the moved tets serves worst_after and the caller's per-tet
    # measures (``improve`` evaluated them a second time: one kernel call per pass)
    _, lo_moved, hi_moved, q_moved = tet_all_measures(pts, tets[redo])
    q_moved = q_moved[measure]
    worst_after = min(float(q[~redo].min(initial=np.inf)), float(q_moved.min(initial=np.inf)))
    stats = SmoothStats(
        attempts=attempts,
        successes=len(moved),
        skipped=int(too_big.sum()),
        pinned=pinned,
        moved=np.sort(moved),
        moved_tets=redo,
        worst_before=worst_before,
        worst_after=worst_after,
        n_colours=len(sets),
        seconds=time.perf_counter() - t_start,
        moved_measures=(q_moved, lo_moved, hi_moved),
    )
    return new, stats


def _bends_curved_tets(mesh, topo, pts, ids, positions, floor: float) -> np.ndarray:
    """(v,) bool: the moves of vertices ``ids`` (v,) (no two in one tet) to
    ``positions`` (v, 3) that the guard on curved tets rejects (``_curved_guard``):
    their star's worst scaled Jacobian falls below both ``floor`` and its worst before
    (vertices at ``pts``; curved edges as ``mesh`` has them)."""
    from ._curved_guard import below, scaled_jacobians

    pos, _ = csr_rows(topo.vert_tets_ptr, ids)
    owner = np.repeat(np.arange(len(ids)), np.diff(topo.vert_tets_ptr)[ids])
    star = mesh.tets[topo.vert_tets[pos]]
    # the old stars at ``pts``, not ``mesh.points``: earlier colours of the pass moved
    # some of their vertices (their curved edges are straight from then on). The moves
    # are tried in ``pts`` itself and taken back (not in a copy of ``pts`` per batch,
    # which costs O(n) each)
    before = scaled_jacobians(mesh, pts, star)
    saved = pts[ids].copy()
    pts[ids] = positions
    after = scaled_jacobians(mesh, pts, star)
    pts[ids] = saved
    return below(floor, before, owner, after, owner, len(ids))


def _pass_kernel(measure, solver, max_iters, min_gain, sharpness, n_trials):
    """The ``batched_smoother`` of ``smooth_pass``'s settings."""
    return batched_smoother(
        measure,
        solver,
        int(max_iters),
        min_gain=float(min_gain),
        sharpness=tuple(sharpness),
        n_trials=int(n_trials),
    )


_KERNEL_OPTIONS = ("solver", "max_iters", "min_gain", "sharpness", "n_trials")


def pass_kernel_specs(
    measure: str = "min_sine", large_batches: bool = False, **options
) -> list[tuple]:
    """``_aot.prefetch`` specs of the kernel that ``smooth_pass(mesh, measure=measure,
    **options)`` calls for most stars (smallest capacity, small batch; with
    ``large_batches`` the large batch too, which the first passes of large meshes call).
    ``options``: any of ``smooth_pass``'s solver, max_iters, min_gain, sharpness,
    n_trials, capacities, batch_sizes (its defaults otherwise).

    The smoothing kernel is the largest build of a new process (cold: ~9 s, one core);
    ``improve`` builds it in the background from its start, so it compiles while the
    statistics and the flip passes run instead of alone at the first smoothing pass.
    """
    known = {*_KERNEL_OPTIONS, "capacities", "batch_sizes"}
    if not set(options) <= known:
        raise JtetError(f"unknown smoothing options {sorted(set(options) - known)}")
    params = inspect.signature(smooth_pass).parameters
    o = {k: options.get(k, params[k].default) for k in known}
    kernel = _pass_kernel(measure, *(o[k] for k in _KERNEL_OPTIONS))
    small, large = o["batch_sizes"]
    shapes = [(min(o["capacities"]), small)] + ([(LARGE_CAPACITY, large)] if large_batches else [])
    return call_specs(kernel, [_kernel_structs(K, batch) for K, batch in shapes])


def _colour_tasks(verts, size, capacities, batch_sizes) -> list[tuple]:
    """Kernel calls (capacity K, padded batch size, vertex ids) of one colour: full large
    batches of stars of at most ``LARGE_CAPACITY`` tets when there are at least
    ``LARGE_BATCHES_MIN`` of them, then every other vertex in small batches at the
    smallest capacity holding its star."""
    small, large = batch_sizes
    tasks = []
    fits = np.flatnonzero(size[verts] <= LARGE_CAPACITY)
    if len(fits) >= LARGE_BATCHES_MIN * large:
        full = len(fits) // large * large
        tasks += [
            (LARGE_CAPACITY, large, verts[fits[i : i + large]]) for i in range(0, full, large)
        ]
        rest = np.ones(len(verts), bool)
        rest[fits[:full]] = False
        verts = verts[rest]
    bucket = np.searchsorted(np.asarray(capacities), size[verts], side="left")
    for bi, K in enumerate(capacities):
        vb = verts[bucket == bi]
        tasks += [(K, small, vb[i : i + small]) for i in range(0, len(vb), small)]
    return tasks


def _kernel_structs(K: int, batch: int) -> list:
    """Argument shapes of a ``batched_smoother`` call: v0, basis, opp, mask."""
    f64 = np.float64
    return [
        jax.ShapeDtypeStruct((batch, 3), f64),
        jax.ShapeDtypeStruct((batch, 3, 3), f64),
        jax.ShapeDtypeStruct((batch, K, 3, 3), f64),
        jax.ShapeDtypeStruct((batch, K), np.bool_),
    ]


def gather_stars(
    verts: np.ndarray, K: int, pts: np.ndarray, ptr: np.ndarray, opp_ids: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Padded star faces (len(verts), K, 3, 3) and mask (len(verts), K) of ``verts``.
    Padded slots repeat the vertex's last star face (finite, masked out)."""
    lo = ptr[verts]
    cnt = ptr[verts + 1] - lo
    slot = np.arange(K)
    mask = slot[None, :] < cnt[:, None]
    rows = lo[:, None] + np.minimum(slot[None, :], cnt[:, None] - 1)
    # np.take gathers rows 3-4x faster than indexing (a 128 x 56 star batch: ~0.8 ->
    # ~0.25 ms per kernel call)
    return np.take(pts, np.take(opp_ids, rows, axis=0), axis=0), mask


def _solve_batch(
    kernel, K, batch, chunk, pts, basis, ptr, opp_ids
) -> tuple[np.ndarray, np.ndarray]:
    """Smooth the vertices ``chunk`` (an independent set, star sizes <= K) in one kernel
    call padded to ``batch``; returns (moved ids (j,), their new positions (j, 3))."""
    b = len(chunk)
    padded = np.concatenate([chunk, np.full(batch - b, chunk[0])]) if b < batch else chunk
    opp, mask = gather_stars(padded, K, pts, ptr, opp_ids)
    if _grouped(batch):
        # groups of padding only are skipped (an all-False mask); padding in the last
        # group with stars stays a copy of the first star, which converges with it (an
        # empty star's lane would iterate to max_iters and hold its group that long)
        mask[-(-b // LANE_GROUP) * LANE_GROUP :] = False
    v0, vbasis = np.take(pts, padded, axis=0), np.take(basis, padded, axis=0)
    new_pos, q_old, q_new = kernel(v0, vbasis, opp, mask)
    new_pos, q_old, q_new = (np.asarray(a)[:b] for a in (new_pos, q_old, q_new))
    ok = q_new > q_old
    return chunk[ok], new_pos[ok]
