"""improve(): the hill-climbing host loop around the batched operations.

Each pass runs the enabled operations in turn (edge removal, multi-face removal,
smoothing). Every operation only applies changes that raise the worst quality of the
tets it touches, so the mesh's worst quality never decreases. An operation re-attempts
only sites whose neighbourhood changed since it last tried them ("dirty" tets), which is
where most of the speed is won: most attempts fail, and failing again is pure waste.
On a large mesh, the passes after the first choose their edge and face steps on the
same mesh and apply them together (``_flip_steps``): one topology update for both.
"""

from __future__ import annotations

import functools
import sys
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ._errors import InvariantError, MeshInputError
from ._mesh import TetMesh
from ._options import Options


@dataclass
class StepResult:
    """What one operation did to the mesh."""

    mesh: TetMesh
    stats: object  # has .as_dict(), .attempts, .successes
    keep: np.ndarray | None  # (m_old,) tets kept in order (None: tets unchanged)
    changed: np.ndarray  # (m_new,) tets whose neighbourhood changed
    # (quality, min dihedral, max dihedral) of the tets np.flatnonzero(changed), when the
    # operation evaluated them already (smoothing); () otherwise
    measures: tuple = ()


def _flip_options(op: str, opts: Options, quality, dirty, **extra) -> dict:
    """The options of an edge-removal (``op`` "edge") or multi-face removal ("face") step
    of a run with ``opts``."""
    size = {"max_ring": opts.max_ring} if op == "edge" else {"max_faces": opts.max_faces}
    return dict(
        measure=opts.quality,
        quality=quality,
        dirty=dirty,
        min_improvement=opts.min_improvement,
        min_scaled_jacobian=opts.min_scaled_jacobian,
        **size,
        **extra,
    )


def _edge_step(
    mesh: TetMesh, opts: Options, quality, dirty, prune: bool = True, sites=None, forbidden=None
) -> StepResult:
    from ._edge_removal import edge_removal_pass

    out, stats, keep = edge_removal_pass(
        mesh,
        **_flip_options(
            "edge", opts, quality, dirty, prune=prune, sites=sites, forbidden=forbidden
        ),
    )
    return _replaced(mesh, out, stats, keep)


def _face_step(
    mesh: TetMesh, opts: Options, quality, dirty, sites=None, forbidden=None
) -> StepResult:
    from ._multiface import multiface_removal_pass

    out, stats, keep = multiface_removal_pass(
        mesh, **_flip_options("face", opts, quality, dirty, sites=sites, forbidden=forbidden)
    )
    return _replaced(mesh, out, stats, keep)


def _flip_steps(mesh: TetMesh, opts: Options, quality, edge_dirty, face_dirty, forbidden=None):
    """An edge-removal step and a multi-face removal step chosen on the same mesh and
    applied together: one topology update instead of two (on a large mesh, each costs
    in proportion to the whole mesh). The face step takes no tet of the edge step's
    winners; the faces around the edge step's new tets wait for the next pass.

    Returns (StepResult with the face step's stats, the edge step's stats, the edge
    step's seconds)."""
    from ._apply import apply_plans
    from ._edge_removal import plan_edge_removal
    from ._multiface import plan_multiface_removal

    ts = time.perf_counter()
    edge_plan, edge_stats = plan_edge_removal(
        mesh, **_flip_options("edge", opts, quality, edge_dirty, forbidden=forbidden)
    )
    edge_seconds = time.perf_counter() - ts
    face_plan, face_stats = plan_multiface_removal(
        mesh,
        **_flip_options("face", opts, quality, face_dirty, forbidden=forbidden),
        prior=edge_plan,
    )
    out, keep = apply_plans(mesh, [edge_plan, face_plan])
    return _replaced(mesh, out, face_stats, keep), edge_stats, edge_seconds


def _replaced(mesh: TetMesh, out: TetMesh, stats, keep: np.ndarray | None) -> StepResult:
    if keep is None:
        return StepResult(mesh, stats, None, np.zeros(mesh.n_tets, bool))
    changed = np.arange(out.n_tets) >= int(keep.sum())
    # tets next to a new tet have a new neighbourhood too (their faces' far side changed)
    nb = out.topology.tet_neighbors[changed]
    changed[nb[nb >= 0]] = True
    return StepResult(out, stats, keep, changed)


def _smooth_step(mesh: TetMesh, opts: Options, quality, dirty) -> StepResult:
    from ._smooth import smooth_pass

    candidates = None
    if dirty is not None:
        candidates = np.zeros(mesh.n_points, bool)
        candidates[mesh.tets[dirty].reshape(-1)] = True
    out, stats = smooth_pass(
        mesh,
        quality=quality,
        measure=opts.quality,
        boundary=opts.boundary,
        threshold=opts.smooth_threshold,
        candidates=candidates,
        seed=opts.seed,
        min_scaled_jacobian=opts.min_scaled_jacobian,
    )
    return StepResult(out, stats, None, stats.moved_tets, stats.moved_measures)


STEPS = {"edge": _edge_step, "face": _face_step, "smooth": _smooth_step}

# From this many tets, the edge step and the face step of a pass after the first are
# applied together (``_flip_steps``): one topology update for both. Late steps change a
# few hundred tets, but an update renumbers the whole mesh: ~0.15 s per step at 983k
# tets (~20 ms at 100k). 983k-tet Gmsh cube, perturb 0: passes 1-4's flip steps 1.60 ->
# 0.86 s, min dihedral 28.11 either way; with the rounds, seeds 0 / 1: 33.02 / 33.03 ->
# 33.25 / 33.26 degrees (rounds vary with their luck); 182k cube seeds 0-2 32.98 /
# 33.56 / 32.57 -> 32.98 / 33.80 / 32.60. Not in the first pass: there the edge step
# changes ~half of the tets, and the face step chosen before it ends the 983k cube at
# 32.05 degrees instead of 33.02 (and slower); merged in every pass of every climb, the
# holeplate's seeds 0-2 ended at 31.60 / 33.00 / 31.13 instead of 33.14 / 33.67 / 33.90.
# Not on small meshes (and so never in the rounds' climbs): their updates cost a few
# ms, and merged from the second pass the reference meshes and the demo (seeds 0-2) gain
# no time within the noise (24.1 -> 23.2 s in all) for as many ups as downs (mean min
# dihedral 34.05 -> 34.01).
MERGE_FLIP_STEPS = 100_000


def _step_groups(ops: tuple[str, ...], merge: bool) -> list[tuple[str, ...]]:
    """The steps of a pass over ``ops``, in order: with ``merge``, ("edge", "face") where
    a face step follows an edge step directly; one op each otherwise."""
    groups, i = [], 0
    while i < len(ops):
        if merge and tuple(ops[i : i + 2]) == ("edge", "face"):
            groups.append(("edge", "face"))
            i += 2
        else:
            groups.append((ops[i],))
            i += 1
    return groups


def _objective(q: np.ndarray, good: float | None) -> np.ndarray:
    """Worst quality, then thresholded means mean(min(q, t)) for t = 0.1, 0.2, ... up to
    ``good`` (the good-enough quality; None: up to 1, the regular tet).

    A pass makes progress when any entry rises: the worst tet improved, or the
    second-worst ones did (the spirit of the paper's lexicographic objective).
    """
    top = 1.0 if good is None else good
    thresholds = [t for t in np.arange(1, 10) / 10 if t < top - 1e-9] + [top]
    return np.array([q.min()] + [np.minimum(q, t).mean() for t in thresholds])


def _workable(dirty: np.ndarray | None, q: np.ndarray, good: float | None) -> np.ndarray | None:
    """(m,) tets an operation may work around: dirty ones below the good-enough quality."""
    if good is None:
        return dirty
    bad = q < good
    return bad if dirty is None else dirty & bad


class _Run:
    """The state of one ``improve`` run: the current mesh, its per-tet measures, what
    each operation has still to look at, the history; ``step`` and ``climb`` advance it.
    """

    def __init__(self, opts: Options, mesh: TetMesh, q, lo_t, hi_t, callback):
        self.opts, self.current, self.callback = opts, mesh, callback
        self.q, self.lo_t, self.hi_t = q, lo_t, hi_t
        self.dirty = {op: None for op in opts.ops}  # None: everything is new to the operation
        self.history: list[dict] = []
        self.checker = None
        self.passes = 0  # passes started so far (the ``pass`` of history entries)
        # (f, 4) tets the flips of ``climb`` must not create again (None: any): those a
        # perturbation kick removed, for the climb after it
        self.forbidden = None

    def snapshot(self) -> tuple:
        """What ``restore`` needs to undo later steps (arrays are replaced, never edited)."""
        return self.current, self.q, self.lo_t, self.hi_t, dict(self.dirty)

    def restore(self, snap: tuple) -> None:
        self.current, self.q, self.lo_t, self.hi_t, dirty = snap
        self.dirty = dict(dirty)

    def check_stop(self, t0: float) -> None:
        """Raise ``_Stop`` on Ctrl-C, when the time limit is up or when the goals are met
        (between operations)."""
        from ._interrupt import pressed

        if pressed():  # its KeyboardInterrupt was swallowed (see _interrupt)
            raise _Stop("interrupted")
        limit = self.opts.time_limit
        if limit is not None and time.perf_counter() - t0 > limit:
            raise _Stop("time limit")
        self.check_goal()

    def goal_reached(self) -> bool:
        """Whether the current mesh meets the options' dihedral-angle goals (False
        when neither is set)."""
        opts = self.opts
        if opts.goal_min_dihedral is None and opts.goal_max_dihedral is None:
            return False
        return not opts.missed_goals(float(self.lo_t.min()), float(self.hi_t.max()))

    def check_goal(self) -> None:
        """Raise ``_Stop("goal reached")`` when the current mesh meets the goals."""
        if self.goal_reached():
            raise _Stop("goal reached")

    def step(self, op: str, run_op, workable, record: bool = True) -> StepResult:
        """Run ``run_op(mesh, opts, quality, workable)`` and make its mesh current."""
        ts = time.perf_counter()
        try:
            step = run_op(self.current, self.opts, self.q, workable)
        except MeshInputError as e:
            # the input passed the same checks: the operation broke the mesh
            raise InvariantError(
                f"pass {self.passes - 1}, operation {op!r}: the mesh is no longer valid: {e}"
            ) from e
        if step.mesh is not self.current:
            if self.checker is not None:
                self.checker.check(step.mesh, self.passes - 1, op)
            for other, d in self.dirty.items():
                if d is not None and step.keep is not None:
                    new = np.zeros(step.mesh.n_tets - int(step.keep.sum()), bool)
                    d = np.concatenate([d[step.keep], new])
                self.dirty[other] = None if d is None else d | step.changed
            self.q, self.lo_t, self.hi_t = _updated_tet_measures(
                step, self.opts.quality, self.q, self.lo_t, self.hi_t
            )
            self.current = step.mesh
        if op in self.dirty:
            self.dirty[op] = step.changed.copy()
        if record:
            self.record(
                {"pass": self.passes - 1, **_stats_dict(op, step.stats)}, time.perf_counter() - ts
            )
        return step

    def flip_steps(self, record: bool = True) -> StepResult:
        """An edge step and a face step of this pass, applied together (``_flip_steps``);
        recorded as two history entries, both with the mesh after both."""
        good = self.opts.good_quality
        edge_dirty = _workable(self.dirty["edge"], self.q, good)
        face_dirty = _workable(self.dirty["face"], self.q, good)
        ts = time.perf_counter()
        edge = {}

        def run_op(mesh, opts, quality, _):
            step, edge["stats"], edge["seconds"] = _flip_steps(
                mesh, opts, quality, edge_dirty, face_dirty, self.forbidden
            )
            return step

        step = self.step("edge+face", run_op, None, record=False)
        # both steps tried their sites on the same mesh: neither retries them until
        # their neighbourhood changes
        self.dirty["edge"], self.dirty["face"] = step.changed.copy(), step.changed.copy()
        if record:
            pass_ = self.passes - 1
            self.record({"pass": pass_, **_stats_dict("edge", edge["stats"])}, edge["seconds"])
            self.record(
                {"pass": pass_, **_stats_dict("face", step.stats)},
                time.perf_counter() - ts - edge["seconds"],
            )
        return step

    def record(self, entry: dict, seconds: float) -> dict:
        """Complete ``entry`` with the current mesh's measures, log it and keep it."""
        entry.update(
            worst_quality=float(self.q.min()),
            min_dihedral=float(self.lo_t.min()),
            max_dihedral=float(self.hi_t.max()),
            n_tets=self.current.n_tets,
            seconds=seconds,
        )
        self.history.append(entry)
        if self.opts.progress:
            _log(entry)
        if self.callback is not None:
            self.callback(entry)
        return entry

    def objective(self) -> np.ndarray:
        return _objective(self.q, self.opts.good_quality)

    def progressed(self, before: np.ndarray) -> bool:
        """Whether the objective rose from ``before`` enough to count as progress."""
        # relative rises; the worst quality may be <= 0 (inverted input), hence abs
        need = np.maximum(self.opts.min_progress * np.abs(before), self.opts.min_improvement)
        return bool((self.objective() > before + need).any())

    def climb(
        self, t0: float, record: bool = True, patience: int | None = None, give_up=None
    ) -> str:
        """Passes of every operation until ``patience`` (default: the option's) passes in a
        row make no progress ("converged"), ``max_passes`` ("max passes") or ``give_up``
        (a test of the (m,) qualities after each pass) returns True ("gave up"); raises
        ``_Stop`` (Ctrl-C, time limit, or the goals met before an operation or at the
        end)."""
        opts = self.opts
        stall = 0
        patience = opts.patience if patience is None else patience
        for _ in range(opts.max_passes):
            before = self.objective()
            self.passes += 1
            # from the second pass on, a large mesh's edge and face steps share one
            # topology update (``_flip_steps``)
            merge = self.passes > 1 and self.current.n_tets >= MERGE_FLIP_STEPS
            for group in _step_groups(opts.ops, merge):
                self.check_stop(t0)
                if group == ("edge", "face"):
                    self.flip_steps(record)
                    continue
                (op,) = group
                workable = _workable(self.dirty[op], self.q, opts.good_quality)
                run_op = STEPS[op]
                if self.forbidden is not None and op in ("edge", "face"):
                    run_op = functools.partial(run_op, forbidden=self.forbidden)
                self.step(op, run_op, workable, record)
            stall = 0 if self.progressed(before) else stall + 1
            if stall >= patience:
                self.check_goal()  # its last operation may have reached it
                return "converged"
            # tested after convergence: a climb that stopped anyway was not cut short
            if give_up is not None and give_up(self.q):
                self.check_goal()
                return "gave up"
        self.check_goal()
        return "max passes"


@dataclass
class ImproveResult:
    """Outcome of ``jtet.improve``.

    ``status`` is "converged" (no progress for ``patience`` passes), "max passes",
    "goal reached" (``goal_min_dihedral`` / ``goal_max_dihedral``), "time limit",
    "interrupted" or "invariant violation: <message>" (``check=True`` only;
    ``mesh`` is then the last mesh that passed the checks). ``notes`` are sentences for
    the user that ``summary()`` prints after the table, e.g. that the worst tet has all
    its vertices on the fixed boundary and ``boundary="slide"`` may free it.
    ``selected_stats`` (with ``Options.regions`` or ``TetMesh.protected_tets``): the
    statistics of the tets the run could change (those of the regions, minus the
    protected ones) before and after (``stats_before`` / ``stats_after`` are the whole
    mesh's), None otherwise.
    """

    mesh: TetMesh
    stats_before: object
    stats_after: object
    history: list = field(default_factory=list)
    status: str = "converged"
    seconds: float = 0.0
    options: Options | None = None
    # sentences for the user: why the worst tet stayed, which option may free it
    notes: list = field(default_factory=list)
    selected_stats: tuple | None = None
    # the limit of kept perturbation rounds of the run: ``options.perturb``, or the
    # automatic count for the mesh's size (``Options.perturb_rounds``)
    perturb_rounds: int = 0

    def summary(self) -> str:
        from ._stats import format_table

        stats, labels = (self.stats_before, self.stats_after), ("before", "after")
        if self.selected_stats is not None:  # the whole mesh, then the regions improved
            names, regions = self.mesh.label_names, self.options.regions
            parts = []
            if regions:
                parts.append("regions " + ",".join(names.get((3, r), str(r)) for r in regions))
            if len(self.mesh.protected_tets):
                parts.append("unprotected")
            which = ", ".join(parts)
            stats += tuple(self.selected_stats)
            labels += (f"before ({which})", f"after ({which})")
        table = format_table(*stats, time_s=self.seconds, labels=labels)
        phases = _phases(self.history, self.perturb_rounds)
        return "\n".join([table, *phases, *(f"note: {n}" for n in self.notes)])

    def plot(self, path, measure: str | None = None) -> None:
        """Write the run's figure to ``path`` (PNG / PDF / SVG by its suffix; what
        ``jtet improve --plot`` draws): before / after histograms of dihedral angles and
        of ``measure`` (default: the optimized quality), and the smallest and largest
        dihedral angle after each operation against the seconds spent."""
        from ._report import plot_run

        plot_run(self, path, measure)

    def as_dict(self) -> dict:
        return {
            "status": self.status,
            "seconds": self.seconds,
            "options": self.options.as_dict() if self.options else None,
            "stats_before": self.stats_before.as_dict(),
            "stats_after": self.stats_after.as_dict(),
            "history": self.history,
            "notes": self.notes,
            "perturb_rounds": self.perturb_rounds,
            **(
                {
                    "selected_stats_before": self.selected_stats[0].as_dict(),
                    "selected_stats_after": self.selected_stats[1].as_dict(),
                }
                if self.selected_stats is not None
                else {}
            ),
        }


def _kicks(history: list[dict]) -> list[dict]:
    """The perturbation attempts of a run's history (each kick is one entry)."""
    return [e for e in history if e["op"] == "perturb"]


def _kept(kicks: list[dict]) -> int:
    """How many of ``kicks`` were kept (one per place of a kept round)."""
    return sum(e["successes"] > 0 for e in kicks)


def _kept_rounds(kicks: list[dict]) -> int:
    """How many rounds of ``kicks`` kept one (``Options.perturb`` counts these)."""
    return len({e["round"] for e in kicks if e["successes"] > 0})


def _gave_up(kicks: list[dict]) -> int:
    """How many of ``kicks`` had their climb given up (``_perturb.attempt_give_up``)."""
    return sum(e["gave_up"] for e in kicks)


def _phases(history: list[dict], rounds: int) -> list[str]:
    """Lines for ``summary()``: what the climb and the perturbation rounds (at most
    ``rounds`` kept) each took and gave (seconds of their operations; the smallest
    dihedral angle after them), so that a user sees whether the rounds (``--perturb``)
    are worth their time on a mesh."""
    if not history:
        return []
    kicks = _kicks(history)
    climb = history[: history.index(kicks[0])] if kicks else history
    lines = []
    if climb:
        passes = len({e["pass"] for e in climb})
        lines.append(
            f"climb: {passes} pass{'es' if passes != 1 else ''} in "
            f"{sum(e['seconds'] for e in climb):.2f} s, min dihedral -> "
            f"{climb[-1]['min_dihedral']:.2f} deg"
        )
    if kicks:
        gave_up = _gave_up(kicks)
        lines.append(
            f"perturbation rounds: {_kept(kicks)} of {len(kicks)} kicks kept (at most "
            f"{rounds} round{'s' if rounds != 1 else ''}"
            + (f"; {gave_up} climb{'s' if gave_up != 1 else ''} given up" if gave_up else "")
            + ") in "
            f"{sum(e['seconds'] for e in kicks):.2f} s, min dihedral -> "
            f"{kicks[-1]['min_dihedral']:.2f} deg"
        )
    return lines


def improve(
    mesh: TetMesh, options: Options | None = None, *, callback=None, **overrides
) -> ImproveResult:
    """Improve the quality of ``mesh`` by hill climbing; see ``jtet.Options``.

    ``improve(mesh, ops=("edge",), quality="min_sine", max_ring=7)`` and
    ``improve(mesh, Options(...))`` are equivalent. Returns an ``ImproveResult`` whose
    ``.mesh`` is the improved mesh (the input is never modified). Ctrl-C (or a
    ``KeyboardInterrupt`` raised by ``callback``) and ``time_limit`` stop the run and
    return the best mesh so far, with ``status`` "interrupted" / "time limit" (the time
    limit is checked between operations). With ``check=True`` an operation that breaks an
    invariant is discarded and the run stops: ``.mesh`` is the last good mesh and
    ``status`` is "invariant violation: <what, where>" (one line). Without checks, an
    operation whose output is not even a conforming mesh raises ``InvariantError``.
    ``callback(entry)``, if given, is called with each history entry as it is made.

    Raises:
        MeshInputError: the input is not a conforming mesh (a face in more than two tets,
            duplicate tets, inconsistent vertex orders), its protected entities are not in
            it, or its extent is outside [1e-30, 1e30] (float64 quality would overflow).
            Inverted and degenerate tets and a non-manifold boundary are fine.
    """
    opts = (options or Options()).replace(**overrides) if overrides else (options or Options())
    if mesh.has_curved_edges:
        return _improve_keeping_curved_edges(mesh, opts, callback)
    return _improve(mesh, opts, callback)


def _improve(mesh: TetMesh, opts: Options, callback) -> ImproveResult:
    """``improve`` once its options are resolved (a mesh with curved edges keeps them:
    the run's operations read them, ``_curved_guard``)."""
    from ._aot import prefetch_in_background
    from ._quality import prefetch_kernels, tet_all_measures, warm_start_kernels
    from ._stats import mesh_stats

    if mesh.point_data:
        return _improve_carrying_point_data(mesh, opts, callback)
    if mesh.cell_data:
        return _improve_carrying_cell_data(mesh, opts, callback)
    t0 = time.perf_counter()
    # the run's topologies (the checks', every step's) treat subfacets bent by less than
    # the feature angle as one surface; the caller's mesh object is left as it was
    mesh = mesh._with_feature_angle(opts.feature_angle)
    seam = _seam_to_pin(mesh)
    if mesh.periodic or mesh.node_sets or seam is not None:
        return _improve_pinned(mesh, opts, callback, seam)
    if opts.regions is not None or len(mesh.protected_tets):
        # the run changes only these tets: those of the regions, minus the protected ones
        sel = np.ones(mesh.n_tets, bool)
        if opts.regions is not None:
            sel = np.isin(mesh.region, _resolved_regions(mesh, opts.regions))
        sel &= ~mesh.protected_tet_mask()
        if not sel.any():
            raise MeshInputError(
                "nothing to improve: every tet "
                + ("of the regions option's regions " if opts.regions is not None else "")
                + "is a protected tet"
            )
        if not sel.all():
            return _improve_part(mesh, sel, opts, callback, t0)
    specs = _pass_kernel_specs(opts, mesh.n_tets)
    # the run's kernels that earlier processes left on disk load on background threads
    # while the checks build the mesh's topology (NumPy sorts that release the GIL)
    warm_start_kernels({spec[:2] for spec in specs})
    _require_conforming(mesh)
    _require_scale(mesh)
    # builds only after the checks: a refused mesh must not leave compilations that its
    # process's exit then waits for (background threads are joined at exit). The pass
    # kernels compile side by side in the background while the run computes its
    # statistics and first passes (the smoothing kernel, ~9 s cold, used to compile
    # alone after the flip passes); the per-tet kernel is needed at once.
    prefetch_in_background(specs)
    prefetch_kernels()
    from ._advice import boundary_only_share, notes

    # only a fixed boundary's run notes it (its topology is built: ~30 ms at 983k tets)
    fixed = opts.boundary == "fixed"
    input_boundary_only = boundary_only_share(mesh) if fixed else (0.0, False)
    # one evaluation of every tet serves the statistics and the optimizer's measures
    per_tet = tet_all_measures(mesh.points, mesh.tets)
    stats_before = mesh_stats(mesh, per_tet=per_tet)
    _, lo_t, hi_t, qualities = per_tet
    q = qualities[opts.quality]
    run = _Run(opts, mesh, q, lo_t, hi_t, callback)
    # counted on the input's tets (the rounds' 1-4 splits add some)
    rounds = opts.perturb_rounds(mesh.n_tets)
    if opts.check:
        from ._invariants import InvariantChecker

        run.checker = InvariantChecker(mesh)
    from ._interrupt import catch_ctrl_c

    ctrl_c = catch_ctrl_c()
    status = "converged"
    try:
        ctrl_c.__enter__()
        status = run.climb(t0)
        if status == "converged" and rounds > 0:
            from ._perturb import perturb

            status = perturb(run, t0, rounds)
    except _Stop as stop:
        status = stop.status
    except KeyboardInterrupt:
        status = "interrupted"
    except InvariantError as e:
        if run.checker is None:  # nothing vouches for ``current``: do not return it
            raise
        # the checker runs before ``current`` is replaced: it is the last good mesh
        status = "invariant violation: " + " ".join(str(e).split())
    finally:
        ctrl_c.__exit__(None, None, None)

    current, history = run.current, run.history
    # rounds cut short by a goal or the time limit did not stop at their own limit
    kept = _kept_rounds(_kicks(history))
    return ImproveResult(
        mesh=current,
        stats_before=stats_before,
        stats_after=mesh_stats(current),
        history=history,
        status=status,
        seconds=time.perf_counter() - t0,
        options=opts,
        notes=notes(
            current,
            opts,
            run.q,
            run.lo_t,
            run.hi_t,
            kept if status == "converged" else -1,
            rounds,
            input_boundary_only,
        ),
        perturb_rounds=rounds,
    )


def _improve_keeping_curved_edges(mesh: TetMesh, opts: Options, callback) -> ImproveResult:
    """``improve`` of a mesh with curved edges (``TetMesh.curved_edges``): the run's
    operations keep its curved tets from folding (``_curved_guard``), the curved edges
    that bend a bounding surface are protected for the run (a flip would cut straight
    across the curved surface: ``surface_curved_edges``), and the result keeps the
    curved edges whose edge it still has, with both ends in place
    (``_quadratic.curved_edges_kept``), and the input's own protected edges."""
    import dataclasses

    from ._curved_guard import scaled_jacobians, surface_curved_edges
    from ._quadratic import curved_edges_kept

    surface = surface_curved_edges(mesh)
    pinned = mesh._with_pinned(surface, np.zeros(0, np.int64))
    result = _improve(pinned, opts, callback)
    keep = curved_edges_kept(mesh, result.mesh)
    curved = mesh.curved_edges
    out = result.mesh.replace(
        curved_edges=(curved.edges[keep], curved.points[keep]),
        protected_edges=mesh.protected_edges,
        protected_edge_labels=mesh.protected_edge_labels,
    )
    n_kept, n_lost = int(keep.sum()), int((~keep).sum())
    before = scaled_jacobians(mesh, mesh.points, mesh.tets).min()
    after = scaled_jacobians(out, out.points, out.tets).min()
    floor = opts.min_scaled_jacobian
    notes = [
        *result.notes,
        f"curved edges: {n_kept} of the input's {len(keep)} mid-edge nodes off their edge's "
        "midpoint (a curved boundary) kept for a quadratic output (--quadratic); "
        f"{len(surface)} bend a bounding surface and were never flipped"
        + (
            f"; {n_lost} dropped (not an edge of the output with both ends in place: "
            "flipped inside the volume or within a flat face, or an end moved inside the "
            "volume; a quadratic output puts the midpoint there)"
            if n_lost
            else ""
        ),
        f"smallest scaled Jacobian of the curved tets: {before:.3f} -> {after:.3f} "
        + (
            "(no guard: min_scaled_jacobian is None)"
            if floor is None
            else f"(no change could take a tet below min({floor:g}, the tets it replaced))"
        ),
    ]
    return dataclasses.replace(result, mesh=out, notes=notes)


def _improve_carrying_point_data(mesh: TetMesh, opts: Options, callback) -> ImproveResult:
    """``improve`` of a mesh with point data (``TetMesh.point_data``): the run works on
    the mesh without it, and the result's vertices that the run moved or inserted get
    values read off the input mesh at their positions (``carried_point_data``)."""
    import dataclasses

    from ._point_data import carried_point_data, moved_vertices

    result = _improve(mesh.replace(point_data=None), opts, callback)
    t0 = time.perf_counter()
    data, n_outside = carried_point_data(mesh, result.mesh)
    n_moved = int(moved_vertices(mesh, result.mesh).sum())
    names = ", ".join(mesh.point_data)
    notes = [
        *result.notes,
        f"point data ({names}): read off the input mesh at the {n_moved} vertices the run "
        "moved or inserted (linear in the input tet; integer arrays: the nearest input "
        "vertex's value)",
    ]
    if n_outside:
        notes.append(
            f"{n_outside} of those vertices lie in no tet of the input mesh; their point "
            "data are those of the nearest input vertex"
        )
    return dataclasses.replace(
        result,
        mesh=result.mesh.replace(point_data=data),
        notes=notes,
        seconds=result.seconds + time.perf_counter() - t0,
    )


def _improve_carrying_cell_data(mesh: TetMesh, opts: Options, callback) -> ImproveResult:
    """``improve`` of a mesh with cell data (``TetMesh.cell_data``): the run works on
    the mesh without it, with the faces where an integer array changes value inside a
    region protected (a label of their own, removed from the result), so no tet of the
    result straddles two values; the result's tets then take the values of the input
    tets they overlap (``carried_cell_data``)."""
    import dataclasses

    from ._cell_data import carried_cell_data, id_arrays, interface_faces

    ids = id_arrays(mesh)
    faces = interface_faces(mesh, ids)
    run_mesh = mesh.replace(cell_data=None)
    label = min(0, int(mesh.protected_face_labels.min(initial=0))) - 2
    if len(faces):
        # listed after the mesh's own: a face protected already keeps its own label
        run_mesh = run_mesh.replace(
            protected_faces=np.concatenate([mesh.protected_faces, faces]),
            protected_face_labels=np.concatenate(
                [mesh.protected_face_labels, np.full(len(faces), label)]
            ),
        )
    result = _improve(run_mesh, opts, callback)
    t0 = time.perf_counter()
    out = result.mesh
    if len(faces):
        own = out.protected_face_labels != label
        out = out.replace(
            protected_faces=out.protected_faces[own],
            protected_face_labels=out.protected_face_labels[own],
        )
    data, n_new, n_unconfirmed = carried_cell_data(mesh, out)
    names = ", ".join(mesh.cell_data)
    notes = [
        *result.notes,
        f"cell data ({names}): the {n_new} new or changed tets take the values of the "
        "input tet they overlap",
    ]
    if ids:
        notes.append(
            f"{', '.join(ids)}: a distinct integer in every input tet, taken for element "
            "ids: a new tet has the id of an input tet it overlaps"
        )
    if len(faces):
        worst = result.mesh.tets[int(np.argmin(result.mesh.quality(opts.quality)))]
        kept_faces = result.mesh.protected_faces[result.mesh.protected_face_labels == label]
        at_interface = np.isin(worst, kept_faces).any()
        notes.append(
            f"the faces where an integer cell array changes value inside a region "
            f"({len(faces)} in the input) were kept in place, as region interfaces are"
            + (
                "; the worst tet touches them: if an array is no label of pieces "
                "(materials, parts), leave it out of the input (jtet improve --drop NAME, "
                "TetMesh.replace(cell_data=...)) for a freer run"
                if at_interface
                else ""
            )
        )
    if n_unconfirmed:
        notes.append(
            f"{n_unconfirmed} of those tets overlap no input tet found at their centroid "
            "(a tet slid off a curved boundary); they take the values of the input tet "
            "with the nearest centroid"
        )
    return dataclasses.replace(
        result,
        mesh=out.replace(cell_data=data),
        notes=notes,
        seconds=result.seconds + time.perf_counter() - t0,
    )


class _Seam(NamedTuple):
    """What a run pins of a seam (coincident surfaces whose sides share no vertex)."""

    n_coincident: int  # vertices at the same coordinates as another vertex of the tets
    verts: np.ndarray  # (j,) those and the other vertices of the seam's triangles
    edges: np.ndarray  # (k, 2) sorted: the seam triangles' edges, and the boundary edges
    # between two coincident vertices


def _seam_to_pin(mesh: TetMesh) -> _Seam | None:
    """The seam of ``mesh``: its vertices at the same coordinates as another vertex, the
    seam's triangles (boundary faces whose twin, the face of the coincident vertices on
    the other side, is a boundary face too), their vertices (a crack's front, which both
    sides share, among them) and edges. None without a seam, or when the mesh protects
    all of those already (the run on the mesh the pins make, among others)."""
    from ._topology import match_rows
    from ._validity import coincident_points, seam_triangles

    pairs = coincident_points(mesh.points, mesh.tets)
    if len(pairs) == 0:
        return None
    n = mesh.n_points
    coincident = np.unique(pairs)
    on = np.zeros(n, bool)
    on[coincident] = True
    seam_faces = seam_triangles(_boundary_faces_at(mesh.tets, on, 1), pairs, n)
    seam = _Seam(
        len(coincident),
        np.unique(np.concatenate([coincident, seam_faces.reshape(-1)])),
        np.unique(
            np.concatenate(
                [
                    seam_faces[:, [[0, 1], [0, 2], [1, 2]]].reshape(-1, 2),
                    _boundary_edges_between(mesh.tets, coincident, n),
                ]
            ),
            axis=0,
        ),
    )
    held = (
        np.isin(seam.verts, mesh.protected_vertices).all()
        and (match_rows(mesh.protected_edges, seam.edges, n) >= 0).all()
    )
    return None if held else seam


def _improve_pinned(mesh: TetMesh, opts: Options, callback, seam: _Seam | None = None):
    """``improve`` of a mesh with periodic links (``TetMesh.periodic``), node sets
    (``TetMesh.node_sets``) or a ``seam`` (``_seam_to_pin``). The periodic vertices and
    the boundary edges between two of them, and the seam's vertices and edges, are
    protected for the run (no move, no 2-2 flip on a periodic surface or either side of
    a seam), so every periodic surface keeps its triangulation, its partner's image, and
    the two sides of a seam still match vertex for vertex, triangle for triangle; the
    vertices of each node set are protected (but those of a set of every vertex, which
    constrains nothing). Vertex ids never change, so the pairs and the sets stay valid.
    The result (an ``ImproveResult``) has the input's own protected edges and vertices
    (those of the run were never removed nor moved), its periodic links and node sets."""
    import dataclasses

    links = [link.pairs.reshape(-1) for link in mesh.periodic]
    verts = np.unique(np.concatenate([np.zeros(0, np.int64), *links]))
    edges = _boundary_edges_between(mesh.tets, verts, mesh.n_points)
    if seam is not None:
        verts = np.union1d(verts, seam.verts)
        edges = np.concatenate([edges, seam.edges])
    sets = [s.ids for s in mesh.node_sets if len(s.ids) < mesh.n_points]
    verts = np.unique(np.concatenate([verts, *sets]))
    pinned = mesh._with_pinned(edges, verts, periodic=(), node_sets=())
    result = _improve(pinned, opts, callback)
    out = result.mesh.replace(
        protected_edges=mesh.protected_edges,
        protected_edge_labels=mesh.protected_edge_labels,
        protected_vertices=mesh.protected_vertices,
        protected_vertex_labels=mesh.protected_vertex_labels,
        periodic=mesh.periodic,
        node_sets=mesh.node_sets,
    )
    notes = list(result.notes)
    if seam is not None:
        notes.insert(
            0,
            f"{seam.n_coincident} vertices lie at the same coordinates as others: "
            "surfaces inside the mesh whose two sides share no vertex (a crack, a cohesive "
            "interface, parts that were not merged). They and the other vertices of the "
            "triangles there (a crack's front) stayed in place and those triangles' edges "
            "were not flipped, so the two sides still match vertex for vertex. If the "
            "sides belong together, merge the points before improving (Gmsh: "
            "mesh.removeDuplicateNodes, or volumes fragmented before meshing): the tets "
            "there can then be improved further",
        )
    return dataclasses.replace(result, mesh=out, notes=notes)


def _boundary_faces_at(tets: np.ndarray, on: np.ndarray, k: int) -> np.ndarray:
    """(f, 3) sorted rows: the boundary faces of ``tets`` (m, 4) with at least ``k``
    vertices where ``on`` (n,) bool. Only the tets with ``k`` or more corners there hold
    such a face, and every tet holding one is among them: the faces are counted there,
    not through a whole-mesh topology, which the run on the pinned mesh builds again
    anyway (its subsegments change)."""
    from ._topology import faces_at, row_keys

    faces, _ = faces_at(tets, on, k)
    # one int64 key per face, in the rows' lexicographic order (np.unique over rows
    # sorts them as structured records: ~5x slower)
    _, first, count = np.unique(row_keys(faces, len(on)), return_index=True, return_counts=True)
    return faces[first[count == 1]]


def _boundary_edges_between(tets, verts, n: int) -> np.ndarray:
    """(k, 2) sorted rows: the edges of boundary faces of ``tets`` (m, 4) whose two
    vertices are both in ``verts`` (j,) of ``n``."""
    from ._topology import row_keys

    on = np.zeros(n, bool)
    on[verts] = True
    edges = _boundary_faces_at(tets, on, 2)[:, [[0, 1], [0, 2], [1, 2]]].reshape(-1, 2)
    edges = edges[on[edges].all(axis=1)]
    _, first = np.unique(row_keys(edges, n), return_index=True)
    return edges[first]


def _resolved_regions(mesh: TetMesh, regions: tuple[int | str, ...]) -> list[int]:
    """The labels of ``Options.regions`` in ``mesh``, names resolved through
    ``mesh.label_names``; ``MeshInputError`` names the labels and names it lacks."""
    named = {name: label for (dim, label), name in mesh.label_names.items() if dim == 3}
    unknown = [r for r in regions if isinstance(r, str) and r not in named]
    if unknown:
        have = ", ".join(f"{n} ({lb})" for n, lb in named.items()) or "none"
        raise MeshInputError(
            f"the mesh has no region named {', '.join(map(repr, unknown))} (regions "
            f"option); its named regions: {have}"
        )
    labels = [named[r] if isinstance(r, str) else r for r in regions]
    present = np.unique(mesh.region)
    missing = sorted(set(labels) - set(present.tolist()))
    if missing:
        have = ", ".join(str(r) for r in present[:20]) + (", ..." if len(present) > 20 else "")
        raise MeshInputError(
            f"the mesh has no region {', '.join(map(str, missing))} (regions option); "
            f"its regions are {have}"
        )
    return labels


def _improve_part(mesh: TetMesh, sel, opts: Options, callback, t0: float) -> ImproveResult:
    """``improve`` of the tets ``sel`` (m,) as a mesh of their own, spliced back into
    ``mesh`` (``Options.regions``, ``TetMesh.protected_tets``): the other tets, their
    vertices and the faces they share with ``sel``'s stay exactly as they are."""
    from ._stats import mesh_stats
    from ._submesh import Submesh

    _require_conforming(mesh)  # the whole input, as a run on all of it would
    stats_before = mesh_stats(mesh)  # its counts come from the robust orient3d
    bad = stats_before.n_inverted + stats_before.n_degenerate
    if bad:
        # the part's run sees nothing of the tets around it, and where tets overlap
        # (inverted) or are flat, a flip there can make a face that one of those has
        raise MeshInputError(
            f"the mesh has {bad} inverted or degenerate tet(s); improving only some of its "
            "tets (regions, protected tets) needs a mesh without: improve it whole first"
        )
    part = Submesh(mesh, sel)
    # the cut faces' edges and vertices protected: no flip or move can change them
    result = _improve(part.pinned_cut(), opts.replace(regions=None), callback)
    spliced = part.splice(mesh, result.mesh)
    if spliced is None:  # the pinned cut and valid tets make this impossible
        raise InvariantError(
            "the run on the selected tets changed a face they share with the others, or made "
            "a face of another tet"
        )
    new, status = spliced[0], result.status
    if opts.check:
        from ._invariants import InvariantChecker

        try:
            InvariantChecker(mesh).check(new, len(result.history), "splice")
        except InvariantError as e:
            new, status = mesh, "invariant violation: " + " ".join(str(e).split())
    stats_after = mesh_stats(new)
    notes = list(result.notes)
    measure = opts.quality
    outside = stats_after.quality_min[measure] < result.stats_after.quality_min[measure]
    if outside:
        why = []
        if len(mesh.protected_tets):
            why.append("a protected tet")
        labels = _resolved_regions(mesh, opts.regions) if opts.regions is not None else []
        if opts.regions is not None and not np.isin(mesh.region, labels).all():
            others = ", ".join(map(str, np.setdiff1d(mesh.region, labels)))
            why.append(f"in region(s) {others}, not in the regions option")
        notes.append(
            f"the worst tet by {measure} ({stats_after.quality_min[measure]:.4f}) is one "
            f"the run left alone ({' or '.join(why)})"
        )
    return ImproveResult(
        mesh=new,
        stats_before=stats_before,
        stats_after=stats_after,
        history=result.history,
        status=status,
        seconds=time.perf_counter() - t0,
        options=opts,
        notes=notes,
        selected_stats=(result.stats_before, result.stats_after),
        perturb_rounds=result.perturb_rounds,
    )


def _stats_dict(op: str, stats) -> dict:
    """JSON-friendly counts of an operation's stats object (arrays left out)."""
    import dataclasses

    if hasattr(stats, "as_dict"):
        d = stats.as_dict()
    else:
        # the fields themselves, not dataclasses.asdict: that deep-copies the arrays it
        # is about to drop (a mesh-sized mask per smoothing pass)
        d = {
            f.name: getattr(stats, f.name)
            for f in dataclasses.fields(stats)
            if not isinstance(getattr(stats, f.name), np.ndarray | tuple)
        }
    return {"op": op, **{k: v for k, v in d.items() if k != "op"}}


class _Stop(Exception):
    """Ends a run between operations with ``status`` ("interrupted", "time limit",
    "goal reached")."""

    def __init__(self, status: str):
        super().__init__(status)
        self.status = status


# Quality measures multiply up to six lengths: beyond these extents they overflow to
# inf / NaN or underflow to 0 in float64 (measured: fine at 1e+-35, broken at 1e+-40).
MIN_EXTENT, MAX_EXTENT = 1e-30, 1e30


def _require_scale(mesh: TetMesh) -> None:
    """Raise ``MeshInputError`` if the mesh is too large or too small for float64 quality."""
    used = np.zeros(mesh.n_points, bool)  # a mask, not np.unique: no sort of 4m ids
    used[mesh.tets.reshape(-1)] = True
    extent = float(np.ptp(mesh.points[used], axis=0).max())
    if not MIN_EXTENT <= extent <= MAX_EXTENT:
        raise MeshInputError(
            f"the mesh spans {extent:.3g} length units; jtet computes quality in float64 and "
            f"needs extents in [{MIN_EXTENT:g}, {MAX_EXTENT:g}]: rescale the coordinates"
        )


def _require_conforming(mesh: TetMesh) -> None:
    """Raise ``MeshInputError`` unless every face lies in at most two tets, on opposite
    sides (consistent vertex orders) and no tet is repeated. Inverted and degenerate
    tets and a non-manifold boundary are accepted (never made worse)."""
    from ._mesh import topology_face_conflicts

    # faces in > 2 tets, protected entities missing: the build raises MeshInputError;
    # the orientation and duplicate checks then read its faces (no second face sort)
    mis, dup = topology_face_conflicts(mesh.tets, mesh.topology)
    if len(dup):
        i, j = dup[0].tolist()
        raise MeshInputError(f"the mesh has {len(dup)} duplicate tet(s): tets {i} and {j}")
    if len(mis):
        i, j = mis[0].tolist()
        raise MeshInputError(
            f"the tets' vertex orders are inconsistent: {len(mis)} face(s) whose two tets "
            f"induce the same orientation on it (first: tets {i} and {j}); list every tet "
            "with positive volume (VTK order), or load it with TetMesh.from_arrays / "
            "jtet.load, which reorder tets listed inside out"
        )


# From this many tets, the first smoothing passes fill colours with large batches
# (``_smooth.LARGE_BATCHES_MIN``): a 31k-tet mesh has at most ~460 stars per colour, a
# 169k-tet one ~2500.
LARGE_SMOOTHING_TETS = 50_000


def _pass_kernel_specs(opts: Options, n_tets: int = 0) -> list[tuple]:
    """``_aot.prefetch`` specs of the kernels the run's passes call first on a mesh of
    ``n_tets`` tets (their other shapes share these specs' (name, settings) groups)."""
    specs = []
    if "smooth" in opts.ops:  # the largest kernel first
        from ._smooth import pass_kernel_specs

        specs += pass_kernel_specs(opts.quality, n_tets >= LARGE_SMOOTHING_TETS)
    if "edge" in opts.ops:
        from ._kernels.klincsek import kernel_specs

        specs += kernel_specs(range(3, opts.max_ring + 1), opts.quality)
    if "face" in opts.ops:
        from ._multiface import tree_kernel_specs

        specs += tree_kernel_specs(opts.quality, opts.max_faces)
    return specs


def _updated_tet_measures(step: StepResult, measure: str, q, lo, hi):
    """(quality, min dihedral, max dihedral) per tet (m_new,) of ``step.mesh`` from those
    of the mesh before the step: only the tets the step created or moved are evaluated
    (per-tet values do not depend on the batch they are computed in)."""
    mesh = step.mesh
    if step.keep is not None and (len(step.keep) != len(q) or step.keep.sum() > mesh.n_tets):
        # not "kept tets first, then new ones" (a broken step): evaluate everything
        return _tet_measures(mesh.points, mesh.tets, measure)
    if step.keep is not None:  # kept tets first, in order, then the new ones
        start = int(step.keep.sum())
        redo = np.arange(start, mesh.n_tets)
        q, lo, hi = (np.concatenate([a[step.keep], np.empty(len(redo))]) for a in (q, lo, hi))
    else:  # same tets: those with a moved vertex changed
        redo = np.flatnonzero(step.changed)
        q, lo, hi = q.copy(), lo.copy(), hi.copy()
        if step.measures:
            q[redo], lo[redo], hi[redo] = step.measures
            return q, lo, hi
    if len(redo):
        q[redo], lo[redo], hi[redo] = _tet_measures(mesh.points, mesh.tets[redo], measure)
    return q, lo, hi


def _tet_measures(points, tets, measure: str):
    """(quality ``measure``, min dihedral, max dihedral) of ``tets``, one kernel call."""
    from ._quality import tet_all_measures

    _, lo, hi, qualities = tet_all_measures(points, tets)
    return qualities[measure], lo, hi


def _log(entry: dict) -> None:
    print(
        f"pass {entry['pass']:3d} {entry['op']:6s} attempts {entry['attempts']:8d} "
        f"successes {entry['successes']:7d}  worst q {entry['worst_quality']:.4f}  "
        f"dihedral {entry['min_dihedral']:6.2f}/{entry['max_dihedral']:6.2f}  "
        f"{entry['seconds']:.2f}s",
        file=sys.stderr,
    )
