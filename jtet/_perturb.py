"""Perturbation: leaving the local optimum the hill climb converged to.

Where the climb stops, the worst tets often have all four vertices pinned (boundary
fixed) and every flip that removes one creates a tet that is a little worse, so no
single operation raises the worst quality. A perturbation round (iterated local search)
makes such a change on purpose (a "kick"), lets the climb run again from there, and
keeps the result only if it is better (``better``); otherwise the mesh goes back to
where it was. The mesh a run returns is never worse than the one the climb converged to.
The climb after a flip kick may not create again the tets the kick removed (tabu, as in
iterated local search): the flip back is usually its first improving move, and then the
attempt ends where it began. On holeplate seed 14, all 8 attempts of the one round
ended so, and the run stopped at 29.51 degrees.
A climb whose worst tet, at its current rate, would not reach the round's worst for many
passes is given up (``attempt_give_up``): the attempt fails without its long tail.

The kicks, in the order they are tried (``kicks``): edge removals around the tets
within ``window`` of the worst quality (the wide window: those next to the narrow
window's, ``LOCAL_RINGS``), allowed to lower the worst tet they touch by up to
``slack``, gentlest first; then a new vertex at the centroid of each of those tets (1-4
split), which the climb then moves and connects; then random moves of the free vertices
around them ("jiggle"), a random restart of the climb there; then each flip around the
worst tets on its own, with a deep slack (``SITES``); last, multi-face removals with the
same slacks as the edge removals. A round works on a submesh, the tets within
``RINGS`` vertex rings of the worst ones with the cut faces pinned, and splices back the
attempts it keeps, so an attempt costs the neighbourhood, not the mesh. The submesh's
places (``places``: its parts that share no vertex, the worst tets of a large mesh lie
in several) each run the ladder on their own, worst first, and the round splices the
first kept attempt of every place at once. A place's attempts all start from its part
of the submesh: a helper process (``_helper_process``) runs some of them beside this
one, and they are judged in the ladder's order all the same.

Measured on the Gmsh holeplate with the boundary fixed, where the climb alone converges
at 29.10 degrees (Stellar's flips + smoothing reach 31.4): 33.14 / 128.64 with 8 kept
rounds, seeds 0-9 33.04-34.41 (experiments/results/bench_improve.md, session 25).
"""

from __future__ import annotations

import itertools
import time

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ._submesh import Submesh
from ._topology import corner_counts

# Slack and window in quality units (regular tet = 1), gentlest first. A narrow window
# kicks only the worst tet or two, a wide one its neighbours within 0.03 too. Measured on
# the four reference meshes: kept kicks had slacks of 0.05-0.2; 0.02 was never kept and
# 0.3 / 0.4 added nothing.
SLACKS = (0.05, 0.1, 0.2)
WINDOWS = (0.005, 0.03)
# The wide window takes only tets within this many vertex rings of the narrow window's:
# the worst tets' neighbours, not every tet of the mesh within 0.03 of the worst (as the
# worst rises, more and more of them: up to 39 on the holeplate, 171 on a 9k-tet fTetWild
# sphere, scattered). A far tet kicked along only makes the attempt (and its submesh)
# larger and its acceptance less likely. Seeds 0-9 of the four reference meshes and the
# demo, one process, no helper: 76.9 -> 60.8 s (holeplate 24.7 -> 16.0 s), worst angle
# better in 9 runs, worse in 13, the same in 28; holeplate 33.26 -> 33.22 degrees on
# average (min 32.48 -> 32.05), demo 32.48 -> 32.11 (experiments/results/bench_improve.md,
# session 23).
LOCAL_RINGS = 1
# The climb after a kick stops at its first pass without progress: the kick's repair is
# done in a pass or two, and an idle pass per attempt is a set of fixed kernel costs.
# Holeplate, 8 / 16 kept rounds: patience 1 33.28 / 33.64 degrees, patience 2 33.15 /
# 33.66 with 6-20 % more attempts.
CLIMB_PATIENCE = 1
# A kept round must raise the worst quality by at least this much (or fix one of the
# tets tied near it). Rounds that raised it by ~4e-5 each spent the whole budget on the
# sphere with seed 1 (8 kept rounds, 25.38 degrees); with this floor the ladder goes on
# to the kick that frees it (34.00), and seeds 0-4 of the four reference meshes all end
# at 32 degrees or more.
MIN_RAISE = 1e-3
# A round's submesh splits into places that share no vertex (``places``), and each runs
# the ladder on its own. On the 983k-tet cube the late rounds' seeds lie in 4-12 places
# on submeshes of 3k-8k tets; judged as one, an attempt failed when one place ended
# worse, and the round ended on a single-site kick that fixed one place after 12-13
# attempts. Per place, a kick is judged where it acts, on a part of hundreds of tets.
# No helper, whole runs: 983k cube seeds 0 / 1: 33.25 / 33.26 -> 33.55 / 33.73 degrees,
# 57 / 84 -> 78 / 76 attempts; 182k cube seeds 0-3: 32.98 / 33.80 / 32.60 / 32.98 ->
# 34.29 / 33.41 / 33.46 / 33.94; the reference meshes and the demo over seeds 0-4: 20
# runs end at the same angle, 4 up to 0.39 degrees higher, the demo's seed 2 0.08
# lower, in 43.0 s instead of 38.8 s (experiments/results/bench_improve.md, session 55).
# Small meshes gain little for that time (their rounds rarely have two places), so
# meshes under PLACES_MIN_TETS judge a round's submesh as one place, as before.
PLACES = True
PLACES_MIN_TETS = 100_000


# After the batched kicks, the insertions and the jiggles, one flip at a time: the edge /
# face ``site`` (0 .. SITES - 1) of the worst tets, allowed to lower the worst tet by up
# to SITE_SLACK. A batched kick applies one flip per group of conflicting ones, picked by
# id among candidates around the same worst tet, so the other flips there are never
# tried (a larger slack only changes which one is picked). Holeplate seed 1 converges at
# 29.51 degrees on two tets joining the hole's top seam to the wall vertex below: the
# flip out is removing top-face edge 1648-1776 (or 1776-3667), whose new worst tet is
# 0.10 (slack 0.43); the climb then moves a free vertex into the corner (0.5225 ->
# 0.547, worst elsewhere). Seeds 1-4 went 29.51 -> 32.68-34.41 degrees (seed 0: 33.28 as
# before); the kept sites were 0-4. 5 sites of each kind gave the same as 8 on seeds
# 0-4, 3 lost two of them (31.13): the round that ends the search tries 10, not 16.
SITES = 5
SITE_SLACK = 0.6


def kicks(
    ops: tuple[str, ...], insert: bool = True
) -> list[tuple[float | None, float, str, int | None]]:
    """(slack, window, kick, site) of every attempt of a round, in the order they are
    tried: edge removal at each slack (site None: every site at once), then vertex
    insertion ("insert", no slack) when ``insert`` and ``ops`` also smooth, then the
    jiggles ("jiggle0" ..., random moves of free vertices) when ``ops`` smooth, then each
    flip site of the worst tets on its own, then multi-face removal at each slack."""
    flips = [op for op in ("edge", "face") if op in ops]

    def batched(op):  # gentlest slack first, the narrow window before the wide one
        return [(s, w, op, None) for s in SLACKS for w in WINDOWS] if op in flips else []

    ladder = batched("edge")
    if insert and flips and "smooth" in ops:  # a new vertex pays off once smoothed, connected
        ladder += [(None, w, "insert", None) for w in WINDOWS]
    if "smooth" in ops:  # random restarts of the smoothing around the worst tets
        ladder += [(None, WINDOWS[-1], f"jiggle{draw}", None) for draw in range(JIGGLES)]
    ladder += [(SITE_SLACK, WINDOWS[0], op, i) for i in range(SITES) for op in flips]
    # Batched multi-face removals come last: over seeds 0-4 of the four reference meshes
    # and the demo they were kept in 9 of 178 tries, against 22-39 % for the other kicks
    # but the last jiggle (17 % of the rounds' time). Against the old order (interleaved
    # with the edge removals), 50 runs (seeds 0-9) ended as before in 44 and better in 6
    # (holeplate seed 5: 32.68 -> 33.12 degrees), with 937 attempts instead of 1274 in
    # 0.87x the time in one process (experiments/results/bench_improve.md, session 21).
    ladder += batched("face")
    return ladder


def insert_step(mesh, opts, quality, workable):
    """A step function (``_driver.STEPS`` signature): a new vertex at the centroid of
    every ``workable`` tet (1-4 split), for the climb to move and connect."""
    from ._apply import split_tets
    from ._driver import _replaced
    from ._edge_removal import PassStats

    out, keep = split_tets(mesh, workable, opts.min_scaled_jacobian)
    n = int((~keep).sum())
    return _replaced(mesh, out, PassStats("insert", n, n), keep if n else None)


# Jiggle kicks: the free vertices around the worst tets move at random, up to this many
# mean edge lengths, and the climb smooths and flips from there (a random restart of the
# neighbourhood). The climb's local optimum depends on the order it smooths vertices in:
# with seeds 1-4 instead of 0 the sphere's climb ended at 25.0-34.4 degrees.
JIGGLE = 0.25
JIGGLES = 3


def jiggle_step(draw: int):
    """A step function (``_driver.STEPS`` signature): the movable vertices of the tets
    sharing a vertex with a ``workable`` tet move by a random vector of length up to
    ``JIGGLE`` times their mean edge length (seeded by the run's seed and ``draw``). A
    move that leaves one of its tets not positive (exact orient3d) is undone."""

    def run(mesh, opts, quality, workable):
        from ._curved_guard import below, scaled_jacobians
        from ._driver import StepResult
        from ._edge_removal import PassStats
        from ._predicates import orient3d_tets
        from ._smooth import motion_bases, star_tets

        topo, pts0 = mesh.topology, mesh.points
        _, movable, _ = motion_bases(mesh, "fixed")
        if not movable[mesh.tets[workable]].any():
            # every vertex of the worst tets is pinned: moving their neighbours changed
            # nothing on the 182k-tet cube (3 attempts, ~0.3 s); flips are their only way
            return StepResult(mesh, PassStats("jiggle"), None, np.zeros(mesh.n_tets, bool))
        near = np.zeros(mesh.n_points, bool)
        near[mesh.tets[_neighbourhood(mesh, workable, 1)].reshape(-1)] = True
        ids = np.flatnonzero(near & movable)
        edges = topo.edges
        length = np.linalg.norm(pts0[edges[:, 0]] - pts0[edges[:, 1]], axis=1)
        total = np.bincount(edges.reshape(-1), np.repeat(length, 2), mesh.n_points)
        h = total[ids] / np.maximum(np.bincount(edges.reshape(-1), minlength=mesh.n_points)[ids], 1)
        rng = np.random.default_rng([opts.seed, draw])
        u = rng.normal(size=(len(ids), 3))
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
        r = JIGGLE * h * rng.random(len(ids)) ** (1 / 3)  # uniform in the ball
        pts = pts0.copy()
        pts[ids] += r[:, None] * u
        while True:  # undo the moves around tets that are no longer positive
            stars = star_tets(topo, ids, mesh.n_tets)
            tets = mesh.tets[stars]
            bad = orient3d_tets(pts, tets) <= 0
            if opts.min_scaled_jacobian is not None and mesh.has_curved_edges:
                # the guard on curved tets, tet by tet (``_curved_guard``)
                own = np.arange(len(tets))
                bad |= below(
                    opts.min_scaled_jacobian,
                    scaled_jacobians(mesh, pts0, tets),
                    own,
                    scaled_jacobians(mesh, pts, tets),
                    own,
                    len(tets),
                )
            if not bad.any():
                break
            back = np.unique(tets[bad])
            pts[back] = pts0[back]
            ids = np.setdiff1d(ids, back)
        out = mesh.replace(points=pts)
        out.__dict__["topology"] = topo  # the same tets: the topology stays valid
        # ``stars``: the tets of the vertices that kept their moves (the loop's last pass)
        return StepResult(out, PassStats("jiggle", len(ids), len(ids)), None, stars)

    return run


def _sites(op: str, mesh, opts, quality, workable) -> np.ndarray:
    """(k,) the edge ids (op "edge") or face ids (op "face") the pass would try around
    the ``workable`` (m,) tets."""
    if op == "edge":
        from ._edge_removal import edge_candidates

        return edge_candidates(mesh, opts.max_ring, workable)
    from ._multiface import candidate_faces

    return candidate_faces(mesh, quality, workable)


def kick_step(op: str, slack: float | None, site: int | None = None):
    """A step function (``_driver.STEPS`` signature) of edge or multi-face removal whose
    winners may lower the worst tet they touch by up to ``slack``, or ``insert_step``, or
    a ``jiggle_step`` (op "jiggle<draw>").
    With ``site`` i, only the i-th candidate edge / face is tried (no change if fewer)."""
    from ._driver import _edge_step, _face_step, _replaced
    from ._edge_removal import PassStats

    if op == "insert":
        return insert_step
    if op.startswith("jiggle"):
        return jiggle_step(int(op[len("jiggle") :]))

    def run(mesh, opts, quality, workable):
        kick_opts = opts.replace(min_improvement=-slack)
        sites = None
        if site is not None:
            sites = _sites(op, mesh, opts, quality, workable)[site : site + 1]
            if not len(sites):
                return _replaced(mesh, mesh, PassStats(op), None)
        if op == "edge":
            # unpruned: the pruning bound assumes a winner must beat the old worst tet
            return _edge_step(mesh, kick_opts, quality, workable, prune=False, sites=sites)
        return _face_step(mesh, kick_opts, quality, workable, sites=sites)

    return run


def better(new_q: np.ndarray, old_q: np.ndarray, near: float, tol: float) -> bool:
    """Whether qualities ``new_q`` beat ``old_q``: the worst rose by more than ``tol``, or
    it did not fall and fewer tets are within ``near`` of the old worst.

    The second clause counts fixing one of several equally bad tets (four pinned tets
    at 28.5 degrees on the 182k-tet cube) as progress. A full lexicographic order was
    measured too: it keeps rounds that only raise the 10th-worst tet, spends the
    ``perturb`` budget on them and ended the holeplate at 29.52 degrees, not 31.13.
    """
    return _Baseline(old_q, np.zeros(0), near).beaten_by(new_q, tol)


class _Baseline:
    """``better``'s view of a round: the worst of the qualities ``old_q`` before it, how
    many are within ``near`` of it, and the same of the qualities ``outside`` the
    submesh, which no attempt changes. Reduced once per round, so judging an attempt
    reads its submesh's qualities only (not two passes over a 983k-tet mesh each)."""

    def __init__(self, old_q: np.ndarray, outside: np.ndarray, near: float):
        self.worst = float(old_q.min())
        self.limit = self.worst + near
        self.near_worst = int((old_q < self.limit).sum())
        self.outside_worst = float(outside.min(initial=np.inf))
        self.outside_near = int((outside < self.limit).sum())

    def beaten_by(self, sub_q: np.ndarray, tol: float) -> bool:
        """``better(concatenate([outside, sub_q]), old_q, near, tol)``."""
        new_worst = min(self.outside_worst, float(sub_q.min(initial=np.inf)))
        if new_worst > self.worst + tol:
            return True
        new_near = self.outside_near + int((sub_q < self.limit).sum())
        return new_worst >= self.worst and new_near < self.near_worst


def _change_key(step) -> bytes:
    """What a kick did to the mesh: the old tets it removed and the tets it added (a
    kick that moved vertices: their new coordinates)."""
    if step.keep is None:
        return step.mesh.points.tobytes()
    start = int(step.keep.sum())
    return np.flatnonzero(~step.keep).tobytes() + step.mesh.tets[start:].tobytes()


# A round works on the tets within this many vertex rings of the worst ones: the kicks
# and the climbs after them then cost in proportion to that neighbourhood, not to the
# mesh (an attempt on the whole 983k-tet cube was ~2 s, mostly O(m) bookkeeping).
# Holeplate, 16 kept rounds: 2 rings 33.62, 3 rings 33.64, 4 rings 33.65 degrees.
RINGS = 3


def _neighbourhood(mesh, seeds: np.ndarray, rings: int) -> np.ndarray:
    """(m,) bool: tets sharing a vertex with a ``seeds`` tet, grown ``rings`` times."""
    sel = seeds.copy()
    for _ in range(rings):  # a few vectorized sweeps over the tets
        marked = np.zeros(mesh.n_points, bool)
        marked[mesh.tets[sel].reshape(-1)] = True
        sel = corner_counts(marked, mesh.tets) > 0
    return sel


_ROUND_IDS = itertools.count()


class Outcome:
    """What one attempt of a round did, wherever it ran (``RoundState.attempt``).

    ``key`` is the kick's change (None: nothing to kick, or no change); ``mesh`` the
    submesh after the climb (None for a kick already tried) and ``q`` its qualities;
    ``stop`` the status of a climb that stopped (time limit, Ctrl-C); ``gave_up`` whether
    the climb was given up (``attempt_give_up``)."""

    def __init__(
        self, key=None, mesh=None, q=None, stats=None, seconds=0.0, stop=None, gave_up=False
    ):
        self.key, self.mesh, self.q, self.stats = key, mesh, q, stats
        self.seconds, self.stop, self.gave_up = seconds, stop, gave_up

    def for_pipe(self) -> Outcome:
        """This outcome with the submesh as plain arrays (``submesh`` rebuilds it)."""
        mesh = self.mesh
        if mesh is not None:
            mesh = (_arrays(mesh), mesh._feature_angle)
        return Outcome(self.key, mesh, self.q, self.stats, self.seconds, self.stop, self.gave_up)

    def submesh(self):
        """The submesh after the climb, as a ``TetMesh``."""
        if not isinstance(self.mesh, tuple):
            return self.mesh

        arrays, angle = self.mesh
        return _from_arrays(arrays)._with_feature_angle(angle)


def _arrays(mesh) -> tuple:
    """A round's submesh as plain arrays for a pipe to a helper process
    (``_from_arrays`` rebuilds it); its curved edges go with it (``_curved_guard``)."""
    return (mesh.points, mesh.tets, mesh.region, mesh.protected_faces,
            mesh.protected_edges, mesh.protected_face_labels, mesh.protected_vertices,
            mesh.protected_edge_labels, mesh.protected_vertex_labels,
            mesh.curved_edges.edges, mesh.curved_edges.points)  # fmt: skip


def _from_arrays(arrays: tuple):
    """The ``TetMesh`` of ``_arrays``."""
    from ._mesh import TetMesh

    *fields, curved_edges, curved_points = arrays
    return TetMesh(*fields, curved_edges=(curved_edges, curved_points))


class RoundState:
    """A round's submesh and the climb state of its start; ``attempt`` runs one kick and
    the climb after it from there, and goes back to the start. Attempts depend only on
    this state, so any process may run any of them (``_helper_process``)."""

    def __init__(self, mesh, q, lo, hi, opts, worst: float, good: float, t0: float, kickable):
        """``kickable`` (m,) bool: the tets of ``mesh`` a kick may work around (the
        round's seeds); ``worst``: the mesh's worst quality; ``good``: the good-enough
        quality (tets at or above it are never kicked)."""
        from ._driver import _Run

        self.sub = _Run(opts, mesh, q, lo, hi, None)
        # the climb after a kick looks at what the kick changed (and what it changes in
        # turn). Letting it work on the whole submesh was measured too: holeplate 33.28
        # -> 33.67 degrees (8 rounds), but the 983k-tet cube 30.22 -> 28.76 (16 rounds)
        self.sub.dirty = {op: np.zeros(len(q), bool) for op in opts.ops}
        self.start_state = self.sub.snapshot()
        self.worst, self.good, self.t0 = worst, good, t0
        self.kickable = kickable

    def for_pipe(self) -> tuple:
        """The round's start, for ``start`` in another process (from the snapshot: an
        attempt may be changing ``sub`` on another thread meanwhile)."""
        m, q, lo, hi, _ = self.start_state
        mesh = _arrays(m)
        elapsed = time.perf_counter() - self.t0
        return (mesh, m._feature_angle, q, lo, hi, self.sub.opts, self.worst, self.good,
                elapsed, self.kickable)  # fmt: skip

    @classmethod
    def start(cls, piped: tuple, received: float) -> RoundState:
        """The state ``for_pipe`` sent, which arrived at ``received`` (``perf_counter``
        seconds): the helper's run clock starts where the optimizer's was."""

        mesh, angle, q, lo, hi, opts, worst, good, elapsed, kickable = piped
        sub = _from_arrays(mesh)._with_feature_angle(angle)
        return cls(sub, q, lo, hi, opts, worst, good, received - elapsed, kickable)

    def attempt(self, attempt: tuple, tried=frozenset()) -> Outcome:
        """Attempt ``(slack, window, kick, site)``: the kick, then (unless its change is
        in ``tried``) the climb. The state is back at the round's start afterwards."""
        from ._driver import _Stop

        slack, window, op, site = attempt
        ts = time.perf_counter()
        sub = self.sub
        # the worst tets, and only those below the good-enough quality
        workable = (sub.q < min(self.worst + window, self.good)) & self.kickable
        if not workable.any():
            return Outcome()
        try:
            # op "perturb": the kick leaves every operation's dirty tets to retry
            step = sub.step("perturb", kick_step(op, slack, site), workable, record=False)
            if step.keep is None and not step.changed.any():  # no change: nothing to undo
                return Outcome()
            # another slack or window often picks the same flips: climbing from the
            # same kicked mesh again would end where the last attempt ended
            key = _change_key(step)
            if key in tried:
                return Outcome(key)
            if step.keep is not None:  # the climb may not undo the kick's flips
                sub.forbidden = self.start_state[0].tets[~step.keep]
            # an inserted vertex is connected by flips after it has been smoothed: its
            # climb's worst can sit flat for passes and then jump (GIVE_UP_SPAN)
            give_up = None if op == "insert" else attempt_give_up(float(sub.q.min()), self.worst)
            status = sub.climb(self.t0, record=False, patience=CLIMB_PATIENCE, give_up=give_up)
            seconds = time.perf_counter() - ts
            return Outcome(key, sub.current, sub.q, step.stats, seconds, None, status == "gave up")
        except _Stop as stop:
            return Outcome(stop=stop.status)
        finally:
            sub.forbidden = None
            sub.restore(self.start_state)


# The climb after a kick is given up once its worst tet, rising at its mean rate of the
# last GIVE_UP_SPAN passes, would still be below the round's worst GIVE_UP_PASSES passes
# later: such an attempt is almost never kept (``better`` wants the worst not to fall),
# and failed attempts are most of a round's time (on coarse TetGen meshes their climbs
# run 6-22 passes, the worst creeping up towards a limit below the round's). Not after
# vertex insertions: every kept attempt the rule lost was one (a new vertex is connected
# by flips once smoothed, and the worst can sit flat for passes and then jump). Offline,
# on the per-pass worst of 429 attempts (holeplate and demo seeds 0-2, six TetGen
# meshes): 14 % of the attempt time saved, none of the 102 kept attempts lost (with the
# insertions: 18 % and 1 lost; a span of 1 lost kept attempts whose worst paused for one
# pass before a jump). Seeds 0-6 of the four reference meshes and the demo, seeds 0-3 of
# five TetGen meshes, the 983k-tet cube seeds 0-2: the same angles in all 58 runs; the
# TetGen runs 195 -> 150 s, the reference meshes within noise
# (experiments/results/bench_improve.md, session 37).
GIVE_UP_SPAN = 2
GIVE_UP_PASSES = 20


def attempt_give_up(start: float, worst: float):
    """A ``_Run.climb`` ``give_up`` test for the climb after a kick (not an insertion,
    see ``GIVE_UP_SPAN``): ``start`` is the kicked submesh's worst quality, ``worst`` the
    round's. Called with the (m,) qualities after each pass; True when the worst, rising
    at its mean rate of the last ``GIVE_UP_SPAN`` passes for ``GIVE_UP_PASSES`` more
    passes, would stay below ``worst``."""
    trace = [start]

    def give_up(q: np.ndarray) -> bool:
        trace.append(float(q.min()))
        if len(trace) <= GIVE_UP_SPAN:
            return False
        rate = max(trace[-1] - trace[-1 - GIVE_UP_SPAN], 0.0) / GIVE_UP_SPAN
        return trace[-1] + GIVE_UP_PASSES * rate < worst

    return give_up


def round_seeds(mesh, q: np.ndarray, good: float) -> np.ndarray:
    """(m,) bool: the tets a round kicks around, for qualities ``q`` (m,) of ``mesh``:
    those below ``good`` within the narrow window of the worst, and those within the wide
    window that lie within ``LOCAL_RINGS`` vertex rings of a narrow one."""
    worst = float(q.min())
    narrow = q < min(worst + min(WINDOWS), good)
    wide = q < min(worst + max(WINDOWS), good)
    return narrow | (wide & _neighbourhood(mesh, narrow, LOCAL_RINGS))


def perturb(run, t0: float, rounds: int) -> str:
    """Perturbation rounds on a converged ``run`` (a ``_driver._Run``), at most
    ``rounds`` kept ones (``Options.perturb_rounds``); returns the run's status,
    "converged", or raises ``_driver._Stop`` (Ctrl-C, time limit, goals met after a kept
    round). Each attempt is one history entry, op "perturb"; its climb may run up to
    ``max_passes`` passes of its own. A round's places (``places``) each judge their
    attempts in the ladder's order; a helper process (``_helper_process``) runs some of
    them side by side, with the same result."""

    opts = run.opts
    attempts = kicks(opts.ops, opts.insert)
    good = np.inf if opts.good_quality is None else opts.good_quality
    # the cut faces pin the submesh's boundary vertices; "slide" would let them move.
    # The goals are the whole mesh's: the submesh's climbs never stop for them
    sub_opts = opts.replace(
        boundary="fixed",
        check=False,
        progress=False,
        goal_min_dihedral=None,
        goal_max_dihedral=None,
    )
    kept_rounds = 0
    began = time.perf_counter()
    for round_no in itertools.count():
        if kept_rounds >= rounds or not attempts:
            break
        worst = float(run.q.min())
        seeds = round_seeds(run.current, run.q, good)
        if not seeds.any():
            return "converged"
        part = Submesh(run.current, _neighbourhood(run.current, seeds, RINGS))
        args = (run, t0, part, seeds, attempts, sub_opts, worst, good, began, round_no)
        if not _round(*args):
            return "converged"  # every attempt of every place failed
        kept_rounds += 1
        run.check_goal()  # the round kept may have reached them
    return "converged"


def places(mesh, whole_mesh_tets: int = PLACES_MIN_TETS) -> np.ndarray:
    """(m,) a label per tet of ``mesh`` (a round's submesh): tets chained by shared
    vertices share one (the places of the round, which share no vertex). All zero
    (one place) when the whole mesh has fewer than ``PLACES_MIN_TETS`` tets."""
    if not PLACES or whole_mesh_tets < PLACES_MIN_TETS:
        return np.zeros(mesh.n_tets, np.int64)
    tets = mesh.tets
    rows = np.repeat(tets[:, :1], 3, axis=1).reshape(-1)
    graph = coo_matrix(
        (np.ones(len(rows), np.int8), (rows, tets[:, 1:].reshape(-1))),
        shape=(mesh.n_points, mesh.n_points),
    )
    return connected_components(graph, directed=False)[1][tets[:, 0]]


def with_places(mesh, kept: list[tuple]):
    """``mesh`` (a round's submesh) with the tets of each kept place replaced by its
    attempt's: ``kept`` holds (mask (m,) of the place's tets, verts (v,) the place's
    vertex ids in ``mesh``, or None for a place that is all of ``mesh``, end: the
    place's submesh after the attempt). New vertices are appended, place by place."""
    if len(kept) == 1 and kept[0][1] is None:
        return kept[0][2]
    points, keep = mesh.points.copy(), np.ones(mesh.n_tets, bool)
    new_points, new_tets, new_region = [], [], []
    n = mesh.n_points
    for mask, verts, end in kept:
        own = len(verts)
        ids = np.concatenate([verts, n + np.arange(end.n_points - own)])
        points[verts] = end.points[:own]  # only the place's tets hold its vertices
        new_points.append(end.points[own:])
        n += end.n_points - own
        new_tets.append(ids[end.tets])
        new_region.append(end.region)
        keep &= ~mask
    return mesh._derive(
        points=np.concatenate([points, *new_points]),
        tets=np.concatenate([mesh.tets[keep], *new_tets]),
        region=np.concatenate([mesh.region[keep], *new_region]),
        tets_checked=int(keep.sum()),
    )


def _round(run, t0, part, seeds, attempts, sub_opts, worst, good, began, round_no) -> bool:
    """One round on ``part`` (a ``Submesh`` around the ``seeds`` (m,) of ``run``'s
    mesh): each place of the submesh (``places``), worst first, runs the ladder from the
    round's start, and the first attempt of each that is better than the start
    (``_Baseline``, with the rest of the mesh as it was) and splices back is kept. The
    kept places are spliced into ``run`` together; returns whether one was."""
    from . import _helper_process
    from ._driver import StepResult

    sel = part.sel
    q, lo, hi, kickable = run.q[sel], run.lo_t[sel], run.hi_t[sel], seeds[sel]
    label = places(part.mesh, run.current.n_tets)
    worst_of = np.full(label.max() + 1, np.inf)
    np.minimum.at(worst_of, label, q)
    labels = np.unique(label)
    rest = run.q[~sel]
    spots, states = [], []  # per place, worst first: (mask, verts, baseline); its state
    for place in labels[np.argsort(worst_of[labels], kind="stable")]:
        mask = label == place
        whole = bool(mask.all())
        mesh, verts = (part.mesh, None) if whole else part.mesh._part(mask)[:2]
        states.append(
            RoundState(mesh, q[mask], lo[mask], hi[mask], sub_opts, worst, good, t0, kickable[mask])
        )
        outside = rest if whole else np.concatenate([rest, q[~mask]])
        spots.append((mask, verts, _Baseline(run.q, outside, WINDOWS[0])))
    # attempts run in each place's ladder order, here or in the helper, and are judged
    # in that order: the outcome is the one of running them all here
    # (round ids are unique in the process: the helper keeps one round)
    tol = max(run.opts.min_improvement, MIN_RAISE)

    def looks_kept(place, outcome):  # ``_judge_round``'s test, without ``fits``
        return outcome.mesh is not None and spots[place][2].beaten_by(outcome.q, tol)

    round_ = _helper_process.Round(next(_ROUND_IDS), attempts, states, looks_kept)
    helper = _helper_process.running()
    if helper is not None:
        helper.serve(round_)
    kept, kept_entries, stats = [], [], None
    try:
        for place, (mask, verts, baseline) in enumerate(spots):

            def fits(end, mask=mask, verts=verts):
                return part.fits(with_places(part.mesh, [(mask, verts, end)]))

            try:
                found = _judge_round(run, t0, round_, place, baseline, began, fits, round_no)
            finally:
                round_.ladders[place].close()
            if found is not None:
                entry, outcome, end = found
                kept.append((mask, verts, end))
                kept_entries.append((entry, outcome.seconds))
                stats = outcome.stats if stats is None else stats
        spliced = part.splice(run.current, with_places(part.mesh, kept)) if kept else None
        if spliced is not None:  # (each place fits, so all of them together do)
            out, keep = spliced
            # tets sharing a vertex with the new ones (through a vertex mask, not the new
            # mesh's adjacency: its topology would be a full build)
            new_tets = np.arange(out.n_tets) >= int(keep.sum())
            result = StepResult(out, stats, keep, _neighbourhood(out, new_tets, 1))
            run.step("perturb", lambda *_, done=result: done, None, record=False)
            for entry, _ in kept_entries:
                entry["successes"] = 1
    finally:  # the kept attempts' entries show the mesh after the round's splice
        round_.close()
        for entry, seconds in kept_entries:
            run.record(entry, seconds)
    return spliced is not None


def _judge_round(run, t0, round_, place, baseline, began, fits, round_no):
    """Judge the attempts of ``round_``'s ``place`` in order, running those nobody has
    started (and starting the helper once the rounds have lasted ``START_AFTER``);
    returns the history entry, the outcome and the submesh after it of the first that
    beats ``baseline`` and ``fits`` (splices back), or None. The other attempts' entries
    are recorded here. While the helper runs the attempt this place needs, this process
    runs another (``Round.claim``)."""
    from . import _helper_process
    from ._driver import _Stop

    opts = run.opts
    helper = _helper_process.running()
    attempts, state, ladder = round_.attempts, round_.states[place], round_.ladders[place]
    tried = set()  # the kicks of this place so far (they all start from one mesh)

    def run_here(claim):
        # the kicks of earlier attempts of that place, judged or not: a repeat is
        # judged without its climb, so it needs none
        other, index = claim
        known = round_.ladders[other].keys_before(index)
        round_.put(claim, round_.states[other].attempt(attempts[index], known))

    for index, (slack, _, op, site) in enumerate(attempts):
        while index not in ladder.outcomes:
            run.check_stop(t0)
            if helper is None and time.perf_counter() - began >= _helper_process.START_AFTER:
                helper = _helper_process.start(opts)
                if helper is not None:
                    helper.serve(round_)
            if ladder.next <= index:  # nobody runs this one yet
                run_here((place, ladder.claim()))
                continue
            # the helper runs it: run another one meanwhile (``Round.claim``)
            claim = round_.claim(from_last=False)
            if claim is not None:
                run_here(claim)
            elif not ladder.wait(index, helper):  # the helper ended: run it here
                ladder.put(index, state.attempt(attempts[index], tried))
        outcome = ladder.outcomes.pop(index)
        if outcome is None:  # the helper failed it: run it here
            outcome = state.attempt(attempts[index], tried)
        if outcome.stop is not None:  # a stop inside the climb leaves ``run`` as it was
            raise _Stop(outcome.stop)
        if outcome.key is None or outcome.key in tried:
            continue
        tried.add(outcome.key)
        kept = baseline.beaten_by(outcome.q, max(opts.min_improvement, MIN_RAISE))
        entry = {
            "pass": run.passes,
            "op": "perturb",
            "round": round_no,
            "attempts": 1,
            "successes": 0,
            "kick": op,
            "site": site,
            "slack": slack,
            "changes": int(outcome.stats.successes),
            "gave_up": outcome.gave_up,
            "tets": len(state.start_state[1]),
        }
        end = outcome.submesh() if kept else None
        if kept and fits(end):
            return entry, outcome, end
        run.record(entry, outcome.seconds)
    return None
