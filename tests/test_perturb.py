"""Perturbation rounds (``Options.perturb``): acceptance rule, restore, invariants."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import delaunay_mesh, shared_mesh_path

import jtet
from jtet import _driver
from jtet._apply import split_tets
from jtet._invariants import InvariantChecker
from jtet._perturb import (
    GIVE_UP_PASSES,
    GIVE_UP_SPAN,
    JIGGLE,
    JIGGLES,
    MIN_RAISE,
    SITE_SLACK,
    SITES,
    SLACKS,
    WINDOWS,
    _Baseline,
    _neighbourhood,
    attempt_give_up,
    better,
    jiggle_step,
    kicks,
)
from jtet._predicates import orient3d_tets
from jtet._submesh import Submesh
from jtet._topology import FREE


def reference_better(new_q, old_q, near, tol):
    """``better``'s rule written out on whole arrays (the independent reference)."""
    old_worst, new_worst = old_q.min(), new_q.min()
    if new_worst > old_worst + tol:
        return True
    limit = old_worst + near
    return new_worst >= old_worst and (new_q < limit).sum() < (old_q < limit).sum()


def test_better_worst_rose():
    old = np.array([0.50, 0.52, 0.9])
    assert better(np.array([0.51, 0.52, 0.9]), old, near=0.005, tol=1e-9)
    # within the tolerance: not a rise; the count near the old worst is the same
    assert not better(old + 1e-12, old, near=0.005, tol=1e-9)
    assert not better(old, old, near=0.005, tol=1e-9)


def test_better_fewer_tied_worst():
    old = np.array([0.50, 0.50, 0.50, 0.7])
    new = np.array([0.50, 0.50, 0.61, 0.6])  # one of three equal worst tets fixed
    assert better(new, old, near=0.005, tol=1e-9)
    # the same count, a better 4th tet: not enough (only tets near the worst count)
    assert not better(np.array([0.50, 0.50, 0.50, 0.8]), old, near=0.005, tol=1e-9)


def test_better_never_accepts_a_lower_worst():
    old = np.array([0.50, 0.50, 0.50])
    # fewer tets near the old worst, but the worst itself fell by 1e-12 (below tol)
    new = np.array([0.50 - 1e-12, 0.9, 0.9])
    assert not better(new, old, near=0.005, tol=1e-9)


def test_rounds_judge_with_the_raise_floor(demo, monkeypatch):
    """Every attempt is judged with a raise floor of at least MIN_RAISE: without it the
    demo keeps rounds that raise its worst tet by 1e-7 to 7e-5 (measured), which spend
    the budget. The decisions are those of ``better`` with that tolerance, on the whole
    mesh's qualities after the attempt."""
    from jtet import _perturb

    calls = []
    init, beaten_by = _perturb._Baseline.__init__, _perturb._Baseline.beaten_by

    def spy_init(self, old_q, outside, near):
        init(self, old_q, outside, near)
        self.arrays = (old_q.copy(), outside.copy(), near)

    def spy(self, sub_q, tol):
        old_q, outside, near = self.arrays
        want = reference_better(np.concatenate([outside, sub_q]), old_q, near, tol)
        calls.append((tol, beaten_by(self, sub_q, tol), want))
        return calls[-1][1]

    monkeypatch.setattr(_perturb._Baseline, "__init__", spy_init)
    monkeypatch.setattr(_perturb._Baseline, "beaten_by", spy)
    r = jtet.improve(demo, perturb=8)
    assert calls and {tol for tol, _, _ in calls} == {max(r.options.min_improvement, MIN_RAISE)}
    assert all(got == want for _, got, want in calls)
    # a round is kept only where ``better`` said so (the splice may still refuse it)
    kept = sum(e["successes"] for e in r.history if e["op"] == "perturb")
    assert 0 < kept <= sum(want for _, _, want in calls)


@pytest.mark.parametrize("seed", range(3))
def test_round_seeds_are_the_narrow_window_and_its_wide_neighbours(seed):
    from jtet._perturb import LOCAL_RINGS, round_seeds

    assert LOCAL_RINGS == 1  # the reference below is one ring
    mesh = delaunay_mesh(300, seed=seed)
    rng = np.random.default_rng(seed)
    # three worst tets (the narrow window), and tets within the wide window everywhere
    q = 0.31 + 0.04 * rng.random(mesh.n_tets)
    q[rng.choice(mesh.n_tets, 3, replace=False)] = 0.3
    good = 0.34
    seeds = round_seeds(mesh, q, good)
    # reference: one Python loop over the tets
    worst = q.min()
    narrow = [t for t in range(mesh.n_tets) if q[t] < min(worst + WINDOWS[0], good)]
    near_vertices = {int(v) for t in narrow for v in mesh.tets[t]}
    expect = np.zeros(mesh.n_tets, bool)
    for t in range(mesh.n_tets):
        in_wide = q[t] < min(worst + WINDOWS[1], good)
        touches = any(int(v) in near_vertices for v in mesh.tets[t])
        expect[t] = t in narrow or (in_wide and touches)
    np.testing.assert_array_equal(seeds, expect)
    wide = q < min(worst + WINDOWS[1], good)
    assert (wide & ~seeds).any()  # far tets of the wide window are left out
    # nothing below the good-enough quality: no seeds
    assert not round_seeds(mesh, q, float(q.min())).any()


def test_round_baseline_judges_as_better_on_the_whole_mesh():
    """``_Baseline`` reduces the tets outside the submesh once per round; its verdicts
    are the rule's on the concatenated qualities (seeded random cases with ties, tets
    near the worst on either side, and empty parts)."""
    rng = np.random.default_rng(7)
    for trial in range(300):
        n_out, n_sub = rng.integers(0, 6), rng.integers(1, 6)
        levels = np.array([0.5, 0.5 + 1e-12, 0.502, 0.51, 0.7])  # ties and near-ties
        outside = rng.choice(levels, n_out)
        old_sub = rng.choice(levels, n_sub)
        new_sub = rng.choice(levels, rng.integers(1, 7))  # an attempt may add tets
        old_q = rng.permutation(np.concatenate([outside, old_sub]))
        for tol in (1e-9, 1e-3):
            want = reference_better(np.concatenate([outside, new_sub]), old_q, 0.005, tol)
            got = _Baseline(old_q, outside, 0.005).beaten_by(new_sub, tol)
            assert got == want, (trial, outside, old_sub, new_sub, tol)
            assert better(np.concatenate([outside, new_sub]), old_q, 0.005, tol) == want


def test_kicks_order_and_ops():
    ladder = kicks(("edge", "face", "smooth"))
    batched = [k for k in ladder if k[3] is None]
    # each batched flip: every slack, gentlest first, the narrow window before the wide one
    by_slack = [(s, w) for s in SLACKS for w in WINDOWS]
    edge = [(s, w, "edge", None) for s, w in by_slack]
    face = [(s, w, "face", None) for s, w in by_slack]
    inserts = [(None, w, "insert", None) for w in WINDOWS]
    jiggles = [(None, WINDOWS[-1], f"jiggle{d}", None) for d in range(JIGGLES)]
    sites = [(SITE_SLACK, WINDOWS[0], op, i) for i in range(SITES) for op in ("edge", "face")]
    # edge removals, vertex insertion (once per window), the jiggles (wide window), each
    # site of the worst tets on its own (edge and face in turn), and last the batched
    # multi-face removals, which are kept least often
    assert batched == edge + inserts + jiggles + face
    assert ladder == edge + inserts + jiggles + sites + face
    face_sites = [k for k in sites if k[2] == "face"]
    assert kicks(("face", "smooth")) == inserts + jiggles + face_sites + face
    assert kicks(("edge", "face")) == edge + sites + face  # no smoothing
    assert kicks(("smooth",)) == jiggles
    # insert=False: the same ladder without the insertions
    assert kicks(("edge", "face", "smooth"), insert=False) == edge + jiggles + sites + face
    assert kicks(("edge", "face"), insert=False) == kicks(("edge", "face"))


def _jiggled(mesh, workable, draw, seed=0):
    step = jiggle_step(draw)(mesh, jtet.Options(seed=seed), None, workable)
    return step, np.flatnonzero((step.mesh.points != mesh.points).any(axis=1))


@pytest.mark.parametrize("seed", range(3))
def test_jiggle_moves_free_vertices_near_the_worst_tets_and_keeps_tets_positive(seed):
    """Against a NumPy reference: only interior vertices of tets sharing a vertex with a
    workable tet move, by at most JIGGLE times their mean edge length; every tet stays
    positive (exact orient3d); the changed tets are exactly those with a moved vertex;
    the draw and the seed pick the moves, the same ones every time."""
    mesh = delaunay_mesh(300, seed=seed, surface_points=40)
    q = mesh.quality("min_sine")
    workable = q < np.quantile(q, 0.05)
    step, moved = _jiggled(mesh, workable, draw=1, seed=seed)
    assert len(moved) > 0 and step.keep is None
    # reference: vertices of tets that share a vertex with a workable tet, interior only
    near_verts = np.unique(mesh.tets[workable])
    near_tets = np.isin(mesh.tets, near_verts).any(axis=1)
    T = mesh.topology
    on_boundary = np.unique(T.faces[T.boundary_face])
    allowed = np.setdiff1d(np.unique(mesh.tets[near_tets]), on_boundary)
    assert np.isin(moved, allowed).all()
    edges = mesh.topology.edges
    length = np.linalg.norm(mesh.points[edges[:, 0]] - mesh.points[edges[:, 1]], axis=1)
    mean_length = np.array([length[(edges == v).any(axis=1)].mean() for v in moved])
    shift = np.linalg.norm(step.mesh.points[moved] - mesh.points[moved], axis=1)
    assert (shift <= JIGGLE * mean_length * (1 + 1e-12)).all()
    assert (orient3d_tets(step.mesh.points, mesh.tets) > 0).all()
    np.testing.assert_array_equal(step.changed, np.isin(mesh.tets, moved).any(axis=1))
    again, _ = _jiggled(mesh, workable, draw=1, seed=seed)
    np.testing.assert_array_equal(again.mesh.points, step.mesh.points)
    other, _ = _jiggled(mesh, workable, draw=2, seed=seed)
    assert not np.array_equal(other.mesh.points, step.mesh.points)


def test_jiggle_leaves_worst_tets_with_only_pinned_vertices_alone():
    """Worst tets whose four vertices are on the fixed boundary: no move (flips are their
    only way out; moving their neighbours was measured useless)."""
    mesh = delaunay_mesh(300, seed=0, surface_points=40)
    T = mesh.topology
    pinned = np.isin(mesh.tets, np.unique(T.faces[T.boundary_face])).all(axis=1)
    assert pinned.any()
    step, moved = _jiggled(mesh, pinned, draw=0)
    assert len(moved) == 0 and not step.changed.any()


@pytest.mark.parametrize("seed", range(4))
def test_split_tets_against_numpy(seed):
    """1-4 splits of random tets: centroids appended in order, volumes kept per tet
    (the four children sum to the parent, to round-off), a valid mesh, faces kept."""
    rng = np.random.default_rng(seed)
    mesh = delaunay_mesh(150, seed=seed, surface_points=20)
    mesh = mesh.replace(region=rng.integers(0, 3, mesh.n_tets))
    which = rng.random(mesh.n_tets) < 0.2
    out, keep = split_tets(mesh, which)
    split = np.flatnonzero(~keep)
    np.testing.assert_array_equal(keep, ~which)  # no tet of a Delaunay mesh is near flat
    k = len(split)
    assert out.n_points == mesh.n_points + k and out.n_tets == mesh.n_tets + 3 * k
    np.testing.assert_array_equal(out.points[: mesh.n_points], mesh.points)
    np.testing.assert_allclose(
        out.points[mesh.n_points :], mesh.points[mesh.tets[split]].mean(axis=1), rtol=0, atol=0
    )
    np.testing.assert_array_equal(out.tets[: keep.sum()], mesh.tets[keep])
    np.testing.assert_array_equal(out.region[keep.sum() :], np.repeat(mesh.region[split], 4))
    children = out.volumes[keep.sum() :].reshape(k, 4)
    assert (children > 0).all()
    # 1e-12 relative: four float64 determinants of rounded centroid coordinates
    np.testing.assert_allclose(children.sum(axis=1), mesh.volumes[split], rtol=1e-12)
    assert out.is_valid().ok
    InvariantChecker(mesh).check(out, 0, "insert")  # surfaces, volumes per region
    # every face of the old mesh is still a face (subfacets untouched)
    assert (out.topology.face_ids(mesh.topology.faces) >= 0).all()


def test_split_tets_skips_tets_whose_children_would_not_be_positive():
    """Nearly flat tets (the 4th vertex 1e-16 off the plane of the others): the rounded
    centroid lands on or outside a face for some; those are left whole, and every tet
    of the result is positive by the exact orient3d."""
    rng = np.random.default_rng(0)
    k = 400
    base = rng.random((k, 3, 3))
    w = rng.random((k, 3))
    w /= w.sum(axis=1, keepdims=True)
    normal = np.cross(base[:, 1] - base[:, 0], base[:, 2] - base[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    apex = (w[:, :, None] * base).sum(axis=1) + 1e-16 * normal
    points = np.concatenate([base, apex[:, None]], axis=1).reshape(-1, 3)
    tets = np.arange(4 * k).reshape(k, 4)
    tets = tets[orient3d_tets(points, tets) > 0]  # disjoint tets, each positive
    mesh = jtet.TetMesh(points, tets)
    out, keep = split_tets(mesh, np.ones(mesh.n_tets, bool))
    assert 0 < keep.sum() < mesh.n_tets  # some split, some too flat (seed 0: 121 of 386)
    assert out.n_points == mesh.n_points + (~keep).sum()
    assert (orient3d_tets(out.points, out.tets) > 0).all()
    out_none, keep_none = split_tets(mesh, keep.copy() & False)
    assert out_none is mesh and keep_none.all()


@pytest.fixture(scope="module")
def demo():
    return jtet.demo_mesh()


@pytest.fixture(scope="module")
def demo_runs(demo):
    """The demo improved without and with perturbation, invariants checked."""
    plain = jtet.improve(demo, perturb=0, check=True)
    perturbed = jtet.improve(demo, perturb=8, check=True)
    return plain, perturbed


def test_perturbation_starts_from_the_converged_mesh_and_never_loses(demo_runs):
    plain, perturbed = demo_runs
    assert plain.status == perturbed.status == "converged"
    climb = [e for e in perturbed.history if e["op"] != "perturb"]
    # the climb is deterministic: the same passes as the run without perturbation
    assert [(e["op"], e["successes"]) for e in climb] == [
        (e["op"], e["successes"]) for e in plain.history
    ]
    rounds = [e for e in perturbed.history if e["op"] == "perturb"]
    assert rounds, "the demo's worst tets leave work for the perturbation"
    measure = perturbed.options.quality
    q_plain = plain.mesh.quality(measure)
    q_after = perturbed.mesh.quality(measure)
    assert q_after.min() >= q_plain.min()
    # each entry reports the mesh after the round: restored (0) or kept (1)
    worst = [plain.history[-1]["worst_quality"]] + [e["worst_quality"] for e in rounds]
    assert worst == sorted(worst)
    assert {e["successes"] for e in rounds} <= {0, 1}
    # a climb given up ends below the round's worst: its attempt is never kept
    assert all(isinstance(e["gave_up"], bool) for e in rounds)
    assert not any(e["gave_up"] and e["successes"] for e in rounds)
    assert all(
        e["attempts"] == 1 and e["kick"] in {k[2] for k in kicks(("edge", "face", "smooth"))}
        for e in rounds
    )
    assert all(e["site"] is None or e["kick"] in ("edge", "face") for e in rounds)
    # inserted vertices: one per split tet of a kept insertion round, at most
    inserted = perturbed.mesh.n_points - plain.mesh.n_points
    assert 0 <= inserted <= sum(e["changes"] for e in rounds if e["kick"] == "insert")
    assert rounds[-1]["worst_quality"] == q_after.min()
    assert rounds[-1]["n_tets"] == perturbed.mesh.n_tets
    kept = sum(e["successes"] for e in rounds)
    assert 0 < kept <= perturbed.options.perturb
    assert perturbed.mesh.is_valid().ok


def reference_give_up(trace, worst):
    """Whether the climb is given up after the last entry of ``trace`` (the kicked
    worst, then the worst after each pass): the rise over the last GIVE_UP_SPAN passes,
    extrapolated linearly GIVE_UP_PASSES passes on, stays below ``worst``."""
    if len(trace) <= GIVE_UP_SPAN:
        return False
    rise = trace[-1] - trace[-1 - GIVE_UP_SPAN]
    return trace[-1] + rise * GIVE_UP_PASSES / GIVE_UP_SPAN < worst


@pytest.mark.parametrize("seed", range(20))
def test_attempt_give_up_against_its_extrapolation(seed):
    rng = np.random.default_rng(seed)
    worst = 0.5
    # non-decreasing worst qualities (the climb never lowers it), from well below to
    # around the round's worst, with flat stretches, creeping rises and jumps
    trace = [worst - rng.uniform(0.01, 0.4)]
    for _ in range(12):
        trace.append(trace[-1] + rng.choice([0.0, rng.uniform(0, 0.002), rng.uniform(0, 0.1)]))
    give_up = attempt_give_up(trace[0], worst)
    for k in range(1, len(trace)):
        q = np.array([trace[k], 0.9, 1.0])  # the submesh's qualities after pass k
        expected = reference_give_up(trace[: k + 1], worst)
        assert give_up(q) == expected
        if expected:
            break


def test_attempt_give_up_cases():
    worst = 0.5
    # never before GIVE_UP_SPAN passes, however flat and far below
    give_up = attempt_give_up(0.1, worst)
    assert not any(give_up(np.array([0.1])) for _ in range(GIVE_UP_SPAN - 1))
    assert give_up(np.array([0.1]))
    # a climb at or above the round's worst is never given up
    give_up = attempt_give_up(0.1, worst)
    assert not any(give_up(np.array([w])) for w in (0.3, 0.5, 0.5, 0.5, 0.5))
    # a slow rise that reaches the worst within GIVE_UP_PASSES passes goes on
    step = 0.3 / GIVE_UP_PASSES * 1.01
    give_up = attempt_give_up(0.2, worst)
    assert not any(give_up(np.array([0.2 + k * step])) for k in range(1, 6))


def test_climb_stops_when_it_gives_up(demo):
    opts = jtet.Options(perturb=0)
    q, lo, hi = _driver._tet_measures(demo.points, demo.tets, opts.quality)
    run = _driver._Run(opts, demo, q, lo, hi, None)
    seen = []

    def give_up(q):
        seen.append(float(q.min()))
        return len(seen) == 2

    assert run.climb(0.0, record=True, give_up=give_up) == "gave up"
    assert run.passes == 2
    assert seen == sorted(seen)  # the climb never lowers the worst
    assert {e["pass"] for e in run.history} == {0, 1}


def test_a_climb_that_converges_is_not_counted_as_given_up(demo):
    """On a pass that both ends the climb (no progress, patience 1) and fails the give-up
    test, the climb converged: it was not cut short, so it is not a climb given up."""
    opts = jtet.Options(perturb=0)
    q, lo, hi = _driver._tet_measures(demo.points, demo.tets, opts.quality)
    run = _driver._Run(opts, demo, q, lo, hi, None)
    run.progressed = lambda before: False
    assert run.climb(0.0, patience=1, give_up=lambda q: True) == "converged"
    assert run.passes == 1


def test_perturb_zero_and_no_flips_mean_no_rounds(demo, demo_runs):
    plain, _ = demo_runs
    assert not [e for e in plain.history if e["op"] == "perturb"]
    smooth_only = jtet.improve(demo, ops=("smooth",), max_passes=3)
    assert not [e for e in smooth_only.history if e["op"] == "perturb"]


def test_stop_inside_a_round_returns_the_converged_mesh(demo, demo_runs, monkeypatch):
    """Ctrl-C during the climb that follows a kick: the kicked mesh (possibly worse)
    must not be returned; the run returns the mesh the climb had converged to."""
    plain, _ = demo_runs
    calls = []
    climb = _driver._Run.climb

    def climb_then_interrupt(self, t0, record=True, patience=None, give_up=None):
        calls.append(record)
        if not record:  # the perturbation's climb, right after a kick was applied
            raise KeyboardInterrupt
        return climb(self, t0, record, patience, give_up)

    monkeypatch.setattr(_driver._Run, "climb", climb_then_interrupt)
    r = jtet.improve(demo, perturb=8)
    assert calls == [True, False]
    assert r.status == "interrupted"
    assert np.array_equal(r.mesh.tets, plain.mesh.tets)
    assert np.array_equal(r.mesh.points, plain.mesh.points)


def test_perturb_option_validated():
    for bad in (-1, 1.5, "Auto", "8", True, None):
        with pytest.raises(jtet.JtetError, match="perturb"):
            jtet.Options(perturb=bad)
    assert jtet.Options().perturb == "auto"
    assert jtet.Options(perturb=np.int64(3)).perturb == 3
    assert jtet.Options(perturb=3).perturb_rounds(10**7) == 3  # a count is exact


def test_auto_perturb_rounds_grow_with_the_fourth_root_of_the_size():
    """8 rounds up to 100k tets (the reference meshes' runs as before), then 8 times the
    fourth root of the size in units of 100k, rounded (closed form)."""
    from jtet._options import auto_perturb_rounds

    auto = jtet.Options(perturb="auto")
    for n in (0, 1, 4, 10_000, 33_271, 100_000):
        assert auto.perturb_rounds(n) == auto_perturb_rounds(n) == 8
    for n, expected in ((182_000, 9), (500_000, 12), (983_140, 14), (2_901_815, 19)):
        assert auto.perturb_rounds(n) == expected == round(8 * (n / 1e5) ** 0.25)
    sizes = np.unique(np.geomspace(1, 1e8, 200).astype(int))
    counts = [auto_perturb_rounds(int(n)) for n in sizes]
    assert counts == sorted(counts)  # never fewer rounds for a larger mesh


def test_improve_runs_the_auto_rounds_of_its_input_size(demo, monkeypatch):
    """``improve`` hands the perturbation the limit of its input's size (here made to
    exceed 8 by a smaller reference size), reports it and names it in the limit note."""
    from jtet import _options

    monkeypatch.setattr(_options, "PERTURB_AUTO_TETS", 1000)
    limit = jtet.Options().perturb_rounds(demo.n_tets)
    assert limit == round(8 * (demo.n_tets / 1000) ** 0.25) > 8
    seen = []

    def rounds_seen(run, t0, rounds):
        seen.append(rounds)
        return "converged"

    monkeypatch.setattr(jtet._perturb, "perturb", rounds_seen)
    r = jtet.improve(demo, patience=1)  # the climb converges: the rounds start
    assert seen == [limit] and r.perturb_rounds == limit
    assert r.as_dict()["perturb_rounds"] == limit
    assert jtet.improve(demo, patience=1, perturb=3).perturb_rounds == 3
    assert seen == [limit, 3]


def _protected_area(mesh) -> float:
    corners = mesh.points[mesh.protected_faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return float(np.linalg.norm(cross, axis=1).sum()) / 2


@pytest.mark.parametrize(("seed", "kick"), [(3, "edge"), (6, "insert")])
def test_kept_rounds_with_regions_and_protected_faces(seed, kick):
    """Delaunay meshes of a cube (their worst tets are pinned to the flat hull), two
    regions and protected interior faces: rounds that flip or insert vertices are kept
    (seeds picked for that), with every invariant checked after every step
    (``check=True``), and the protected faces' surface is still there."""
    rng = np.random.default_rng(seed)
    mesh = delaunay_mesh(300, seed=seed, surface_points=40)
    centroids = mesh.points[mesh.tets].mean(axis=1)
    mesh = mesh.replace(region=(centroids[:, 0] < 0.5).astype(np.int64))
    T = mesh.topology
    inner = np.flatnonzero(~T.boundary_face & ~T.interface_face)
    mesh = mesh.replace(protected_faces=T.faces[rng.choice(inner, 10, replace=False)])
    plain = jtet.improve(mesh, perturb=0)
    r = jtet.improve(mesh, perturb=6, check=True)
    assert r.status == "converged"
    rounds = [e for e in r.history if e["op"] == "perturb"]
    kept = [e for e in rounds if e["successes"]]
    assert kept and {kick} <= {e["kick"] for e in kept}
    assert (r.mesh.n_points > mesh.n_points) == (kick == "insert")
    q0, q1 = plain.mesh.quality(r.options.quality), r.mesh.quality(r.options.quality)
    assert q1.min() >= q0.min()
    # protected triangles may be flipped only into triangles covering the same area
    assert _protected_area(r.mesh) == pytest.approx(_protected_area(mesh), rel=1e-12)
    assert r.mesh.topology.subfacet.sum() >= 1  # the protected faces are faces (build ok)


def test_no_insert_keeps_the_points():
    """``insert=False`` on the mesh whose rounds keep an insertion (seed 6 above): no
    insertion is tried, the output has exactly the input's points, the fixed boundary
    ones where they were, and it is never worse than the climb alone."""
    mesh = delaunay_mesh(300, seed=6, surface_points=40)
    plain = jtet.improve(mesh, perturb=0)
    r = jtet.improve(mesh, perturb=6, insert=False, check=True)
    rounds = [e for e in r.history if e["op"] == "perturb"]
    assert rounds and "insert" not in {e["kick"] for e in rounds}
    assert r.options.insert is False
    assert r.mesh.n_points == mesh.n_points
    fixed = mesh.topology.vertex_kind != FREE  # only free vertices may move
    np.testing.assert_array_equal(r.mesh.points[fixed], mesh.points[fixed])
    q0, q1 = plain.mesh.quality(r.options.quality), r.mesh.quality(r.options.quality)
    assert q1.min() >= q0.min()
    assert r.mesh.is_valid().ok


def test_insert_option_validated():
    with pytest.raises(jtet.JtetError, match="insert must be True or False"):
        jtet.Options(insert=1)


def _tet_set(mesh) -> set:
    return {tuple(sorted(t)) for t in mesh.tets.tolist()}


@pytest.mark.parametrize("seed", range(3))
def test_neighbourhood_against_breadth_first_search(seed):
    rng = np.random.default_rng(seed)
    mesh = delaunay_mesh(150, seed=seed)
    seeds = rng.random(mesh.n_tets) < 0.02
    got = _neighbourhood(mesh, seeds, 2)
    # reference: vertex rings grown one at a time with Python sets
    tets = [set(t) for t in mesh.tets.tolist()]
    chosen = {i for i in range(mesh.n_tets) if seeds[i]}
    for _ in range(2):
        verts = set().union(*(tets[i] for i in chosen))
        chosen = {i for i, t in enumerate(tets) if t & verts}
    assert set(np.flatnonzero(got).tolist()) == chosen


def test_submesh_splice_round_trip_and_boundary_guard():
    mesh = delaunay_mesh(150, seed=4, surface_points=20)
    sel = _neighbourhood(mesh, np.arange(mesh.n_tets) == 7, 2)
    part = Submesh(mesh, sel)
    assert part.mesh.n_tets == sel.sum() and len(part.verts) == part.mesh.n_points

    # the cut faces: brute force, the faces that a tet inside and one outside share
    def faces(tets):
        return {tuple(sorted(t[i] for i in range(4) if i != j)) for t in tets for j in range(4)}

    shared = faces(mesh.tets[sel].tolist()) & faces(mesh.tets[~sel].tolist())
    assert {tuple(f) for f in np.sort(part.verts[part.cut], axis=1).tolist()} == shared
    # the ghosts: faces of outside tets on three submesh vertices that no submesh tet has
    inside = set(part.verts.tolist())
    outside = {f for f in faces(mesh.tets[~sel].tolist()) if set(f) <= inside}
    ghosts = outside - faces(mesh.tets[sel].tolist())
    assert {tuple(f) for f in np.sort(part.verts[part.ghosts], axis=1).tolist()} == ghosts
    out, keep = part.splice(mesh, part.mesh)
    np.testing.assert_array_equal(keep, ~sel)
    np.testing.assert_array_equal(out.points, mesh.points)
    assert _tet_set(out) == _tet_set(mesh)
    # a submesh that lost a tet on a cut face no longer fits the mesh around it
    T = part.mesh.topology
    t = T.face_tets[T.face_ids(part.cut[:1]), 0]
    smaller = part.mesh.replace(
        tets=np.delete(part.mesh.tets, t, 0), region=np.delete(part.mesh.region, t)
    )
    assert part.splice(mesh, smaller) is None
    # a submesh tet with a face an outside tet has (here: made so) does not splice
    part.ghosts = np.sort(part.mesh.tets[:1, :3], axis=1)
    assert part.splice(mesh, part.mesh) is None


def _two_cubes():
    """Two unit cubes side by side along x, 6 tets each around their (0,0,0)-(1,1,1)
    diagonal: every square face is two coplanar triangles, and the shared square x = 1
    has the same diagonal on both sides."""
    corners = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], float)
    cube = np.array([[0, a, b, 7] for a, b in [(1, 3), (1, 5), (2, 3), (2, 6), (4, 5), (4, 6)]])
    points, ids = np.unique(
        np.concatenate([corners, corners + [1.0, 0.0, 0.0]]), axis=0, return_inverse=True
    )
    tets = ids.reshape(-1)[np.concatenate([cube, cube + 8])]
    inside_out = orient3d_tets(points, tets) < 0
    tets[inside_out] = tets[inside_out][:, [0, 2, 1, 3]]
    return jtet.TetMesh(points, tets)


def _flip(mesh, p, q):
    """``mesh`` after removing its edge between points ``p`` and ``q`` (a 2-2 flip)."""
    from jtet._edge_removal import edge_removal_pass

    ids = [int(np.flatnonzero((mesh.points == x).all(axis=1))[0]) for x in (p, q)]
    e = np.flatnonzero((np.sort(mesh.topology.edges, axis=1) == sorted(ids)).all(axis=1))
    out, stats, keep = edge_removal_pass(mesh, min_improvement=-1.0, sites=e)
    assert stats.successes == 1
    return out


def test_splice_keeps_flips_of_the_mesh_boundary_and_refuses_cut_ones():
    """The left cube as the submesh: a 2-2 flip of two coplanar faces of the mesh's
    hull (which the climb makes on the whole mesh too) splices back into a valid mesh
    with the same surfaces; a flip of the two coplanar cut faces at x = 1 does not."""
    mesh = _two_cubes()
    part = Submesh(mesh, mesh.points[mesh.tets].mean(axis=1)[:, 0] < 1)
    assert len(part.cut) == 2
    hull = _flip(part.mesh, [0, 0, 0], [0, 1, 1])  # diagonal of the face x = 0
    out, keep = part.splice(mesh, hull)
    assert out.is_valid().ok and (~keep).sum() == 6 and out.n_tets == 12
    InvariantChecker(mesh).check(out, 0, "perturb")
    assert part.splice(mesh, _flip(part.mesh, [1, 0, 0], [1, 1, 1])) is None
    # with the cut pinned (Options.regions), that flip is not even tried
    from jtet._edge_removal import edge_candidates

    pinned = part.pinned_cut()
    assert len(pinned.protected_edges) == 5 and len(pinned.protected_vertices) == 4
    ids = [int(np.flatnonzero((pinned.points == x).all(axis=1))[0]) for x in ([1, 0, 0], [1, 1, 1])]
    e = np.flatnonzero((np.sort(pinned.topology.edges, axis=1) == sorted(ids)).all(axis=1))
    assert len(e) == 1 and e[0] in edge_candidates(part.mesh, 7, None)
    assert e[0] not in edge_candidates(pinned, 7, None)
    assert part.splice(mesh, _flip(pinned, [0, 0, 0], [0, 1, 1])) is not None


@pytest.mark.parametrize("op", ["edge", "face"])
def test_single_site_kick_changes_only_around_its_candidate(op):
    """A kick with ``site`` i flips at most the i-th candidate edge / face of the worst
    tets: every tet it removes contains that edge (both end points), or, for a face,
    the removed tets include the face's two tets; past the last candidate, no change."""
    from jtet._edge_removal import edge_candidates
    from jtet._multiface import candidate_faces
    from jtet._perturb import kick_step

    mesh = delaunay_mesh(300, seed=1, surface_points=40)
    opts = jtet.Options()
    q = mesh.quality(opts.quality)
    workable = q < np.quantile(q, 0.1)
    if op == "edge":
        candidates = edge_candidates(mesh, opts.max_ring, workable)
    else:
        candidates = candidate_faces(mesh, q, workable)
    changed = 0
    for site in range(min(len(candidates), 12)):  # seed 1: faces 7, 8, 9, 11 flip
        step = kick_step(op, 1.0, site)(mesh, opts, q, workable)
        if step.keep is None:
            continue
        changed += 1
        removed = mesh.tets[~step.keep]
        T = mesh.topology
        if op == "edge":
            a, b = T.edges[candidates[site]]
            assert ((removed == a).any(axis=1) & (removed == b).any(axis=1)).all()
        else:
            two = T.face_tets[candidates[site]]
            assert (~step.keep[two[two >= 0]]).all()
    assert changed > 0
    past = kick_step(op, 1.0, len(candidates))(mesh, opts, q, workable)
    assert past.keep is None and not past.changed.any()


@pytest.fixture(scope="module")
def converged_by_flips():
    """A small mesh the flips alone have converged on: kicks there are often undone by
    the next improving flip."""
    mesh = delaunay_mesh(300, seed=1, surface_points=40)
    return jtet.improve(mesh, ops=("edge", "face"), perturb=0).mesh


def _as_sets(tets) -> set:
    return {tuple(sorted(t)) for t in np.asarray(tets).tolist()}


# (kick, its site, the operation of the step after it): cases of this mesh where that
# step, left alone, creates again tets the kick removed
UNDONE = [("edge", 3, "edge"), ("edge", 10, "face"), ("face", 9, "face")]


@pytest.mark.parametrize("kick, site, op", UNDONE)
def test_the_step_after_a_kick_does_not_create_the_removed_tets_again(
    converged_by_flips, kick, site, op
):
    """With ``forbidden`` (what ``RoundState.attempt`` passes to the climb after a kick),
    a flip step creates none of the kicked-out tets again, and its mesh is valid;
    without it, the same step undoes (part of) the kick."""
    from jtet._perturb import kick_step

    mesh = converged_by_flips
    opts = jtet.Options()
    q = mesh.quality(opts.quality)
    workable = q < np.quantile(q, 0.1)
    kicked = kick_step(kick, 1.0, site)(mesh, opts, q, workable)
    assert kicked.keep is not None
    removed = mesh.tets[~kicked.keep]
    after = kicked.mesh
    q_after = after.quality(opts.quality)
    step = _driver.STEPS[op]
    free = step(after, opts, q_after, kicked.changed)
    assert _as_sets(removed) & _as_sets(free.mesh.tets)  # the premise: undone
    tabu = step(after, opts, q_after, kicked.changed, forbidden=removed)
    assert not _as_sets(removed) & _as_sets(tabu.mesh.tets)
    assert tabu.mesh.is_valid().ok
    InvariantChecker(after).check(tabu.mesh, 0, op)


def _demo_round(demo_runs):
    """(options, ``RoundState``) of a round on the demo's converged mesh."""
    from jtet._perturb import RoundState, round_seeds

    plain, _ = demo_runs
    mesh, opts = plain.mesh, jtet.Options(perturb=0)
    q = mesh.quality(opts.quality)
    lo, hi = np.zeros_like(q), np.full_like(q, 180.0)
    seeds = round_seeds(mesh, q, opts.good_quality)
    state = RoundState(mesh, q, lo, hi, opts, float(q.min()), opts.good_quality, 0.0, seeds)
    return opts, state


def test_only_insertions_climb_without_giving_up(demo_runs, monkeypatch):
    """Every attempt's climb gets a give-up test (``attempt_give_up``) but those after a
    vertex insertion, which may sit flat for passes before a flip connects the vertex."""
    opts, state = _demo_round(demo_runs)
    given = []
    climb = _driver._Run.climb

    def recording_climb(self, t0, record=True, patience=None, give_up=None):
        given.append(give_up is not None)
        return climb(self, t0, record, patience, give_up)

    monkeypatch.setattr(_driver._Run, "climb", recording_climb)
    climbed = set()
    for attempt in [a for a in kicks(opts.ops) if a[2] in ("edge", "insert")][:8]:
        given.clear()
        outcome = state.attempt(attempt)
        if outcome.key is not None:  # the kick changed the submesh: its climb ran
            assert given == [attempt[2] != "insert"]
            assert not (outcome.gave_up and attempt[2] == "insert")
            climbed.add(attempt[2])
    assert climbed == {"edge", "insert"}


def test_attempts_forget_their_forbidden_tets(demo_runs):
    """The forbidden tets last for one attempt's climb only: the round's state has none
    before or after an attempt."""
    opts, state = _demo_round(demo_runs)
    assert state.sub.forbidden is None
    outcomes = [state.attempt(a) for a in kicks(opts.ops)[:6]]
    assert any(o.key is not None for o in outcomes)
    assert state.sub.forbidden is None


def test_holeplate_seed_14_leaves_the_seam_trap():
    """Gmsh holeplate, seed 14: the climb converges at 29.51 degrees on two tets whose
    four vertices are all on the fixed boundary, and every kick of the first round used
    to be undone by the climb after it (0 of 8 attempts kept, 29.51 degrees). With the
    kicked-out tets forbidden the rounds go on (33.93 degrees measured)."""
    result = jtet.improve(jtet.load(shared_mesh_path("gmsh_holeplate.vtu")), seed=14)
    kept = sum(e["successes"] for e in result.history if e["op"] == "perturb")
    assert kept >= 2
    assert result.stats_after.min_dihedral > 32.0
