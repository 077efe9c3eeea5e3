"""Perturbation: leaving the local optimum the hill climb converged to.

Where the climb stops, the worst tets often have all four vertices pinned (boundary
fixed) and every flip that removes one creates a tet that is a little worse, so no
single operation raises the worst quality. A perturbation round (iterated local search)
applies such a flip on purpose, lets the climb run again from there, and keeps the
result only if the objective rose; otherwise the mesh goes back to where it was. The
mesh returned by a run is therefore never worse than the one the climb converged to.

Each attempt kicks the tets within ``window`` of the worst quality with edge removals
(or multi-face removals) allowed to lower their worst tet by up to ``slack``, gentlest
first (``kicks``). Measured on the Gmsh holeplate with the boundary fixed: the worst
dihedral angle went 29.10 -> 31.13 degrees in two kept rounds, where the climb alone had
converged (Stellar's flips + smoothing reach 31.4 there). Off by default
(``Options.perturb = 0``): the rounds that keep nothing cost the most, ~0.15 s per
attempt on 33k tets and ~2 s on 983k.
"""

from __future__ import annotations

import time

import numpy as np

# Slack and window in quality units (regular tet = 1), gentlest first. A narrow window
# kicks only the worst tet or two, a wide one its neighbours within 0.03 too. Measured on
# the four reference meshes: kept kicks had slacks of 0.05-0.2; 0.02 was never kept and
# 0.3 / 0.4 added nothing.
SLACKS = (0.05, 0.1, 0.2)
WINDOWS = (0.005, 0.03)
# The climb after a kick stops at its first pass without progress: the kick's repair is
# done in a pass or two, and an idle pass per attempt is ~0.05 s of fixed kernel costs.
# Measured on the holeplate: 31.13 degrees after 3.1 s of perturbation, against 30.79
# after 3.6 s with the run's patience of 2 (the shorter climbs end in other meshes,
# here better ones).
CLIMB_PATIENCE = 1


def kicks(ops: tuple[str, ...]) -> list[tuple[float | None, float, str]]:
    """(slack, window, kick) of every attempt of a round, in the order they are tried:
    the flips of ``ops`` at each slack, then vertex insertion ("insert", no slack)."""
    flips = [op for op in ("edge", "face") if op in ops]
    ladder = [(s, w, op) for s in SLACKS for w in WINDOWS for op in flips]
    if flips:  # a new vertex needs the flips (and smoothing) of the climb to pay off
        ladder += [(None, w, "insert") for w in WINDOWS]
    return ladder


def insert_step(mesh, opts, quality, workable):
    """A step function (``_driver.STEPS`` signature): a new vertex at the centroid of
    every ``workable`` tet (1-4 split), for the climb to move and connect."""
    from ._apply import split_tets
    from ._driver import _replaced
    from ._edge_removal import PassStats

    out, keep = split_tets(mesh, workable)
    n = int((~keep).sum())
    return _replaced(mesh, out, PassStats("insert", n, n), keep if n else None)


def kick_step(op: str, slack: float | None):
    """A step function (``_driver.STEPS`` signature) of edge or multi-face removal whose
    winners may lower the worst tet they touch by up to ``slack``, or ``insert_step``."""
    from ._driver import _replaced

    if op == "insert":
        return insert_step

    def run(mesh, opts, quality, workable):
        if op == "edge":
            from ._edge_removal import edge_removal_pass

            # unpruned: the pruning bound assumes a winner must beat the old worst tet
            out, stats, keep = edge_removal_pass(
                mesh,
                measure=opts.quality,
                max_ring=opts.max_ring,
                quality=quality,
                dirty=workable,
                min_improvement=-slack,
                prune=False,
            )
        else:
            from ._multiface import multiface_removal_pass

            out, stats, keep = multiface_removal_pass(
                mesh,
                measure=opts.quality,
                max_faces=opts.max_faces,
                quality=quality,
                dirty=workable,
                min_improvement=-slack,
            )
        return _replaced(mesh, out, stats, keep)

    return run


def better(new_q: np.ndarray, old_q: np.ndarray, near: float, tol: float) -> bool:
    """Whether qualities ``new_q`` beat ``old_q``: the worst rose by more than ``tol``, or
    it did not fall and fewer tets are within ``near`` of the old worst.

    The second clause counts fixing one of several equally bad tets (four pinned tets
    at 28.5 degrees on the 182k-tet cube) as progress. A full lexicographic order was
    measured too: it keeps rounds that only raise the 10th-worst tet, spends the
    ``perturb`` budget on them and ended the holeplate at 29.52 degrees, not 31.13.
    """
    old_worst, new_worst = float(old_q.min()), float(new_q.min())
    if new_worst > old_worst + tol:
        return True
    limit = old_worst + near
    return new_worst >= old_worst and int((new_q < limit).sum()) < int((old_q < limit).sum())


def perturb(run, t0: float) -> str:
    """Perturbation rounds on a converged ``run`` (a ``_driver._Run``), at most
    ``opts.perturb`` kept ones; returns the run's status, "converged". Each attempt is
    one history entry, op "perturb"; its climb may run up to ``max_passes`` passes of
    its own."""
    opts = run.opts
    attempts = kicks(opts.ops)
    good = np.inf if opts.good_quality is None else opts.good_quality
    kept_rounds = 0
    while kept_rounds < opts.perturb and attempts:
        for slack, window, op in attempts:
            run.check_stop(t0)
            ts = time.perf_counter()
            snap = run.snapshot()
            # the worst tets, and only those below the good-enough quality
            workable = run.q < min(float(run.q.min()) + window, good)
            if not workable.any():
                return "converged"
            try:
                # op "perturb": the kick leaves every operation's dirty tets to retry
                step = run.step("perturb", kick_step(op, slack), workable, record=False)
                if step.keep is None:  # no flip within the slack: nothing to undo
                    continue
                run.climb(t0, record=False, patience=CLIMB_PATIENCE)
                kept = better(run.q, snap[1], WINDOWS[0], opts.min_improvement)
            except BaseException:
                # stopped (Ctrl-C, time limit, a failed check) inside the round: the
                # kicked mesh may be worse than the converged one; return that one
                run.restore(snap)
                raise
            if not kept:
                run.restore(snap)
            entry = {
                "pass": run.passes - 1,
                "op": "perturb",
                "attempts": 1,
                "successes": int(kept),
                "kick": op,
                "slack": slack,
                "changes": int(step.stats.successes),
            }
            run.record(entry, time.perf_counter() - ts)
            if kept:
                kept_rounds += 1
                break
        else:
            return "converged"  # every attempt of the round failed
    return "converged"
