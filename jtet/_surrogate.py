"""Smoothing on a smooth surrogate of a star's minimum quality, solved with optimistix.

The alternative solvers of ``jtet._smooth.smooth_star`` (``"bfgs"``, ``"ncg"``,
``"bfgs_tr"``, and the first stage of ``"hybrid"``). Kept apart so that the default
active-set path never imports optimistix (measured ~0.5 s in a new process).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import optimistix as optx

from ._errors import JtetError
from ._smooth import SOLVERS, star_components

# Below this quality the log in the surrogate is continued linearly (C1), so inverted and
# degenerate tets give a finite, steep penalty instead of log(<= 0).
_LOG_FLOOR = 1e-4


def _quiet(**kwargs) -> None:
    return None


class _BFGSTrustRegion(optx.AbstractBFGS):
    """BFGS Hessian approximation, dogleg steps, classical trust region (optimistix)."""

    rtol: float
    atol: float
    norm: object = optx.max_norm
    use_inverse: bool = False
    descent: optx.AbstractDescent = optx.DoglegDescent()
    search: optx.AbstractSearch = optx.ClassicalTrustRegion()
    verbose: Callable[..., None] = _quiet


def _soft_min_objective(t, args):
    """Surrogate to MINIMISE: (1/p) log sum exp(-p log c) = -log(soft-min of c).

    The log makes the temperature relative (a sliver at 0.01 and a good tet at 0.5 are
    weighted by their ratio, not their difference), so one sharpness ``p`` suits every star.
    """
    B, rel, mask, measure, p = args
    c = star_components(B @ t, rel, measure)
    phi = jnp.where(
        c >= _LOG_FLOOR,
        jnp.log(jnp.maximum(c, _LOG_FLOOR)),
        math.log(_LOG_FLOOR) + (c - _LOG_FLOOR) / _LOG_FLOOR,
    )
    z = jnp.where(mask[:, None], -p * phi, -jnp.inf)
    return jax.nn.logsumexp(z) / p


def _scaled_objective(t, args):
    scale, inner = args
    return scale * _soft_min_objective(t, inner)


def _make_solver(solver: str, rtol: float, atol: float):
    if solver == "bfgs":
        return optx.BFGS(rtol=rtol, atol=atol)
    if solver == "ncg":
        return optx.NonlinearCG(rtol=rtol, atol=atol)
    if solver == "bfgs_tr":
        return _BFGSTrustRegion(rtol=rtol, atol=atol)
    raise JtetError(f"unknown smoothing solver {solver!r}; choose one of {SOLVERS}")


def _solve_surrogate(t0, B, rel, mask, measure, solver, sharpness, max_iters, rtol, atol):
    """Minimise the soft-min surrogate with optimistix, one stage per sharpness value."""
    opt = _make_solver(solver, rtol, atol)
    t = t0
    for p in sharpness:  # continuation: a blunt stage finds the basin, a sharp one refines
        args = (B, rel, mask, measure, p)
        # Scale so the first (identity-Hessian) step is h/4 long: the raw gradient is
        # ~|grad q|/q, i.e. 100 for a sliver star and 1e4 in the linear continuation of an
        # inverted one, and Armijo backtracking from step 1 wasted the iteration budget.
        g0 = jax.grad(_soft_min_objective)(t, args)
        scale = 0.25 / jnp.maximum(jnp.sqrt(g0 @ g0), 1e-12)
        sol = optx.minimise(
            _scaled_objective,
            opt,
            t,
            args=(scale, args),
            max_steps=max_iters,
            throw=False,
        )
        t = jnp.where(jnp.all(jnp.isfinite(sol.value)), sol.value, t)
    return t
