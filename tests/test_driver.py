"""jtet.improve / jtet.Options / ImproveResult: the optimizer's happy paths.

The demo mesh (6,209 tets, worst dihedral ~1.14 deg) is improved once with the default
options (module fixture); most checks read that one result. Other runs use one operation
or few passes: the schedule, stop rules and options are what they test, not the quality.
"""

import json
import math

import numpy as np
import pytest
from helpers import delaunay_mesh, grid_mesh, shifted

import jtet
from jtet._driver import _objective
from jtet._invariants import InvariantChecker

HISTORY_KEYS = {
    "pass",
    "op",
    "attempts",
    "successes",
    "worst_quality",
    "min_dihedral",
    "max_dihedral",
    "n_tets",
    "seconds",
}

# A pass counts as progress when an objective entry rises by more than this fraction
# (Options.min_progress default), or by more than min_improvement when it is ~0.
MIN_PROGRESS, MIN_IMPROVEMENT = 1e-3, 1e-9


def _arrays(mesh):
    return mesh.points.copy(), mesh.tets.copy(), mesh.region.copy()


def _same_mesh(a, b) -> bool:
    return (
        np.array_equal(a.points, b.points)
        and np.array_equal(a.tets, b.tets)
        and np.array_equal(a.region, b.region)
    )


def _passes(history) -> list[int]:
    return sorted({e["pass"] for e in history})


def _worst_per_pass(history) -> list[float]:
    """Worst quality at the end of each pass (the last entry of the pass)."""
    return [[e for e in history if e["pass"] == p][-1]["worst_quality"] for p in _passes(history)]


def _no_progress(before: float, after: float) -> bool:
    """The worst quality did not rise enough to count as progress."""
    return after - before <= max(MIN_PROGRESS * abs(before), MIN_IMPROVEMENT)


@pytest.fixture(scope="module")
def demo():
    return jtet.demo_mesh()


@pytest.fixture(scope="module")
def demo_run(demo):
    """(input copies, callback entries, result) of improve(demo) with default options."""
    before = _arrays(demo)
    seen = []
    result = jtet.improve(demo, callback=seen.append)
    return before, seen, result


# --- the default run on the demo mesh ---------------------------------------------------


def test_demo_quality_rises(demo, demo_run):
    _, _, r = demo_run
    q0, q1 = demo.quality("min_sine"), r.mesh.quality("min_sine")
    s0 = jtet.stats(demo)
    assert s0.n_tets == 6209 and s0.min_dihedral == pytest.approx(1.14, abs=0.01)
    # measured: worst min_sine 0.021 -> 0.53, min dihedral 1.14 -> 30.0 deg; the bounds
    # are far below that so a slightly different schedule still passes, but a run that
    # only nudges the slivers fails
    assert q1.min() > q0.min()
    assert q1.min() > 0.3
    assert r.stats_after.min_dihedral > s0.min_dihedral
    assert r.stats_after.min_dihedral > 20.0
    assert r.stats_after.max_dihedral < s0.max_dihedral
    assert r.stats_after.n_inverted == 0 and r.stats_after.n_degenerate == 0


def test_demo_result_valid_and_input_untouched(demo, demo_run):
    before, _, r = demo_run
    assert r.mesh.is_valid().ok
    assert r.mesh is not demo
    for a, b in zip(before, _arrays(demo), strict=True):
        assert np.array_equal(a, b)
    # the boundary is fixed by default: total volume is kept (the flips regroup the same
    # space; 1e-12 relative is float64 round-off over ~6k signed terms)
    assert r.mesh.volumes.sum() == pytest.approx(demo.volumes.sum(), rel=1e-12)
    InvariantChecker(demo).check(r.mesh, 0, "demo")


def test_default_measure_lowers_the_largest_angles(demo, demo_run):
    """The default biased_min_sine pulls the largest dihedral angles down: measured on
    the demo 177.75 -> 129.91 degrees max (min_sine alone, good_quality 0.7: 144.97)
    with the worst angle 1.14 -> 29.97 (131.33 / 30.05 before the smoother climbed the six biased pieces)."""
    _, _, r = demo_run
    assert r.options.quality == "biased_min_sine" and r.options.good_quality == 0.6
    assert r.stats_after.max_dihedral < 135.0
    assert r.stats_after.min_dihedral > 29.0
    # the biased measure never exceeds min_sine: its worst value bounds min_sine's
    assert r.mesh.quality("biased_min_sine").min() <= r.mesh.quality("min_sine").min()


def test_demo_stats_match_jtet_stats(demo, demo_run):
    _, _, r = demo_run
    # same functions on the same arrays: equal to the last bit
    assert r.stats_before.as_dict() == jtet.stats(demo).as_dict()
    assert r.stats_after.as_dict() == jtet.stats(r.mesh).as_dict()
    assert r.stats_after.n_tets == r.mesh.n_tets
    # statistics evaluate all measures in one fused kernel: equal up to an ulp
    assert r.stats_after.quality_min["min_sine"] == pytest.approx(
        r.mesh.quality("min_sine").min(), rel=1e-15, abs=1e-300
    )


def test_demo_history(demo, demo_run):
    _, _, r = demo_run
    everything = r.history
    assert everything, "no history"
    for e in everything:
        assert HISTORY_KEYS <= set(e), set(HISTORY_KEYS) - set(e)
        assert 0 <= e["successes"] <= e["attempts"]
    # the climb's passes, then the perturbation rounds (tests/test_perturb.py)
    h = [e for e in everything if e["op"] != "perturb"]
    rounds = everything[len(h) :]
    assert all(e["op"] == "perturb" for e in rounds)
    ops = r.options.ops
    assert ops == ("edge", "face", "smooth")
    n_passes = len(h) // len(ops)
    assert len(h) == n_passes * len(ops)
    assert [e["op"] for e in h] == list(ops) * n_passes
    assert [e["pass"] for e in h] == [i // len(ops) for i in range(len(h))]
    worst = [e["worst_quality"] for e in everything]
    assert worst == sorted(worst), "the worst quality went down"
    measure = r.options.quality
    assert worst[0] >= demo.quality(measure).min()
    last = everything[-1]
    assert last["worst_quality"] == r.mesh.quality(measure).min()
    assert last["n_tets"] == r.mesh.n_tets
    assert last["min_dihedral"] == pytest.approx(r.stats_after.min_dihedral, abs=1e-12)
    assert last["max_dihedral"] == pytest.approx(r.stats_after.max_dihedral, abs=1e-12)
    assert r.status in ("converged", "max passes")
    if r.status == "converged":
        assert n_passes < r.options.max_passes
        # stopped after `patience` passes without progress of (at least) the worst quality
        w = [demo.quality(measure).min(), *_worst_per_pass(h)]
        for p in range(1, r.options.patience + 1):
            assert _no_progress(w[-p - 1], w[-p])
    else:
        assert n_passes == r.options.max_passes
        assert not rounds  # perturbation only after a converged climb


def test_demo_as_dict_and_summary(demo_run):
    _, _, r = demo_run
    d = json.loads(json.dumps(r.as_dict()))
    assert d["status"] == r.status
    assert d["options"] == jtet.Options().as_dict()
    assert d["options"]["ops"] == ["edge", "face", "smooth"]
    assert len(d["history"]) == len(r.history)
    assert d["history"][-1]["worst_quality"] == r.history[-1]["worst_quality"]
    assert d["stats_before"]["n_tets"] == 6209
    assert d["stats_after"]["min_dihedral"] == r.stats_after.min_dihedral
    s = r.summary()
    assert isinstance(s, str)
    assert "dihedral" in s
    assert f"{r.stats_before.min_dihedral:.3f}" in s
    assert f"{r.stats_after.min_dihedral:.3f}" in s


def test_summary_splits_the_climb_from_the_rounds(demo_run):
    """The phase lines add up the history's own entries: the climb is everything before
    the first perturbation attempt."""
    _, _, r = demo_run
    ops = [e["op"] for e in r.history]
    first = ops.index("perturb")
    assert set(ops[first:]) == {"perturb"}
    climb, kicks = r.history[:first], r.history[first:]
    lines = r.summary().splitlines()
    passes = len({e["pass"] for e in climb})
    assert (
        f"climb: {passes} passes in {sum(e['seconds'] for e in climb):.2f} s, "
        f"min dihedral -> {climb[-1]['min_dihedral']:.2f} deg"
    ) in lines
    kept = sum(e["successes"] > 0 for e in kicks)
    gave_up = sum(e["gave_up"] for e in kicks)
    given_up = f"; {gave_up} climb{'s' if gave_up != 1 else ''} given up" if gave_up else ""
    assert (
        f"perturbation rounds: {kept} of {len(kicks)} kicks kept (at most "
        f"{r.perturb_rounds} rounds{given_up}) in "
        f"{sum(e['seconds'] for e in kicks):.2f} s, min dihedral -> "
        f"{r.stats_after.min_dihedral:.2f} deg"
    ) in lines
    none = jtet.improve(grid_mesh(2), goal_min_dihedral=1.0)
    assert none.history == [] and "climb" not in none.summary()


def test_callback_receives_every_entry_in_order(demo_run):
    _, seen, r = demo_run
    assert len(seen) == len(r.history)
    assert all(a is b for a, b in zip(seen, r.history, strict=True))


def test_dirty_set_schedule(demo_run):
    # failed attempts are not repeated: pass 1 re-attempts only edges whose neighbourhood
    # changed (measured 5246 -> 4782 edges)
    _, _, r = demo_run
    edge = [e for e in r.history if e["op"] == "edge"]
    assert len(edge) >= 2
    assert edge[1]["attempts"] < edge[0]["attempts"]


# --- options: Options(...) and **kw ------------------------------------------------------


def test_options_object_and_kwargs_are_equivalent(demo):
    kw = dict(ops=("edge", "face"), max_ring=5, max_passes=1)
    a = jtet.improve(demo, jtet.Options(**kw))
    b = jtet.improve(demo, **kw)
    c = jtet.improve(demo, jtet.Options(ops=("edge", "face")), max_ring=5, max_passes=1)
    assert a.options == b.options == c.options == jtet.Options(**kw)
    assert a.mesh.n_tets != demo.n_tets  # the runs did change the mesh
    assert _same_mesh(a.mesh, b.mesh) and _same_mesh(a.mesh, c.mesh)
    strip = [{k: v for k, v in e.items() if k != "seconds"} for e in a.history]
    assert strip == [{k: v for k, v in e.items() if k != "seconds"} for e in b.history]


def test_ops_run_in_the_order_given(demo):
    r = jtet.improve(demo, ops=("face", "edge"), max_passes=2)
    assert [(e["pass"], e["op"]) for e in r.history] == [
        (0, "face"),
        (0, "edge"),
        (1, "face"),
        (1, "edge"),
    ]


def test_unknown_option_name_raises(demo):
    with pytest.raises(jtet.JtetError, match="max_rings"):
        jtet.improve(demo, max_rings=5)
    with pytest.raises(jtet.JtetError, match="unknown option"):
        jtet.Options().replace(bogus=1)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(ops=("flip",)), "operation"),
        (dict(ops=()), "operation"),
        (dict(quality="aspect"), "quality measure"),
        (dict(max_ring=2), "max_ring"),
        (dict(max_ring=17), "max_ring"),
        (dict(max_faces=0), "max_faces"),
        (dict(boundary="free"), "boundary"),
        (dict(feature_angle=90.0), "feature_angle"),
        (dict(max_passes=-1), "max_passes"),
        (dict(patience=0), "patience"),
        (dict(min_progress=1.0), "min_progress"),
        (dict(good_quality=0.0), "good_quality"),
        (dict(good_quality=1.5), "good_quality"),
        (dict(good_quality=-0.1), "good_quality"),
        (dict(time_limit=0), "time_limit"),
        # wrong types and values that used to pass and fail later (or never stop)
        (dict(seed=-1), "seed"),
        (dict(max_ring=7.5), "max_ring"),
        (dict(max_ring="7"), "max_ring"),
        (dict(max_passes=True), "max_passes"),
        (dict(time_limit=float("nan")), "time_limit"),
        (dict(min_improvement=float("inf")), "min_improvement"),
        (dict(smooth_threshold="x"), "smooth_threshold"),
        (dict(check=1), "check"),
        (dict(goal_min_dihedral=0.0), "goal_min_dihedral"),
        (dict(goal_max_dihedral=180.0), "goal_max_dihedral"),
        (dict(goal_min_dihedral=float("nan")), "goal_min_dihedral"),
        (dict(goal_max_dihedral="138"), "goal_max_dihedral"),
    ],
)
def test_bad_option_values_raise(demo, kw, match):
    with pytest.raises(jtet.JtetError, match=match):
        jtet.Options(**kw)
    with pytest.raises(jtet.JtetError, match=match):
        jtet.improve(demo, **kw)


def test_good_quality_accepted_values():
    assert jtet.Options().good_quality == 0.6
    assert jtet.Options(good_quality=1.0).good_quality == 1.0
    assert jtet.Options(good_quality=None).good_quality is None
    assert jtet.Options(good_quality=0.01).good_quality == 0.01


# --- stop rules ----------------------------------------------------------------------


def test_max_passes_one(demo, demo_run):
    _, _, full = demo_run
    r = jtet.improve(demo, max_passes=1)
    assert r.status == "max passes"
    assert _passes(r.history) == [0]
    assert [e["op"] for e in r.history] == ["edge", "face", "smooth"]
    # same input, options and seed: pass 0 is the default run's pass 0, count for count
    for a, b in zip(r.history, full.history[:3], strict=True):
        for k in ("attempts", "successes", "worst_quality", "n_tets", "min_dihedral"):
            assert a[k] == b[k], k
    assert r.mesh.quality().min() > demo.quality().min()


def test_max_passes_zero_returns_input(demo):
    r = jtet.improve(demo, max_passes=0)
    assert r.history == []
    assert r.status == "max passes"
    assert _same_mesh(r.mesh, demo)
    assert r.stats_after.as_dict() == r.stats_before.as_dict()


def _without_seconds(history) -> list[dict]:
    return [{k: v for k, v in e.items() if k != "seconds"} for e in history]


def _meets(entry, goal_min, goal_max) -> bool:
    return (goal_min is None or entry["min_dihedral"] >= goal_min) and (
        goal_max is None or entry["max_dihedral"] <= goal_max
    )


@pytest.mark.parametrize("phase", ["climb", "perturb"])
def test_goal_stops_the_default_run_where_it_is_first_met(demo, demo_run, phase):
    """With goals the run is the default run cut at its first history entry whose mesh
    meets them (the same seed makes the same choices): a goal taken from the default
    run's own history, in its climb or after its first kept perturbation round."""
    _, _, full = demo_run
    kept = [i for i, e in enumerate(full.history) if e["op"] == "perturb" and e["successes"]]
    assert kept, "the default demo run keeps perturbation rounds"
    at = full.history[kept[0] if phase == "perturb" else 4]
    goal_min, goal_max = at["min_dihedral"], at["max_dihedral"] + 1e-9
    first = next(i for i, e in enumerate(full.history) if _meets(e, goal_min, goal_max))
    assert 0 < first < len(full.history) - 1  # a real cut, not the end of the run
    r = jtet.improve(demo, goal_min_dihedral=goal_min, goal_max_dihedral=goal_max)
    assert r.status == "goal reached"
    assert _without_seconds(r.history) == _without_seconds(full.history[: first + 1])
    assert r.stats_after.min_dihedral == pytest.approx(full.history[first]["min_dihedral"])
    assert r.stats_after.min_dihedral >= goal_min - 1e-9
    assert r.stats_after.max_dihedral <= goal_max
    assert InvariantChecker(demo).check(r.mesh, 0, "goal") is None


def test_goal_met_by_the_input_returns_it(demo):
    r = jtet.improve(demo, goal_min_dihedral=0.5, goal_max_dihedral=179.0)
    assert r.status == "goal reached"
    assert r.history == []
    assert not any("goal" in n for n in r.notes)
    assert _same_mesh(r.mesh, demo)
    # one goal alone: the other one is not a condition
    assert jtet.improve(demo, goal_max_dihedral=179.0).status == "goal reached"


def test_unmet_goal_changes_nothing(demo, demo_run):
    _, _, full = demo_run
    r = jtet.improve(demo, max_passes=1, goal_min_dihedral=89.0, goal_max_dihedral=179.0)
    assert r.status == "max passes"
    assert _without_seconds(r.history) == _without_seconds(full.history[:3])
    # the summary says which goal was missed, by how much (the met one is not named)
    (note,) = [n for n in r.notes if "goals were not reached" in n]
    assert f"smallest dihedral angle {r.stats_after.min_dihedral:.2f} deg (goal >= 89)" in note
    assert "largest" not in note
    assert f"note: {note}" in r.summary()


def test_patience(demo):
    # edge removal alone: a cheap run that needs several passes on the demo
    # (measured: patience=1 stops after 4 passes, patience=3 after 6)
    # (no perturbation rounds: they would follow each converged climb)
    p1 = jtet.improve(demo, ops=("edge",), patience=1, perturb=0)
    p3 = jtet.improve(demo, ops=("edge",), patience=3, perturb=0)
    assert p1.status == p3.status == "converged"
    n1, n3 = len(_passes(p1.history)), len(_passes(p3.history))
    assert 2 <= n1 <= n3
    # both runs make the same passes until patience=1 stops
    strip = [{k: v for k, v in e.items() if k != "seconds"} for e in p1.history]
    assert strip == [{k: v for k, v in e.items() if k != "seconds"} for e in p3.history[:n1]]
    # patience=1 stopped at its first pass without progress: the last pass did not raise
    # the worst quality enough (a necessary condition: the objective has more entries)
    w1 = [demo.quality().min(), *_worst_per_pass(p1.history)]
    assert _no_progress(w1[-2], w1[-1])
    # patience=3: the last three passes made no progress
    w3 = [demo.quality().min(), *_worst_per_pass(p3.history)]
    for p in (1, 2, 3):
        assert _no_progress(w3[-p - 1], w3[-p])
    assert p3.mesh.quality().min() >= p1.mesh.quality().min()


# --- good_quality ----------------------------------------------------------------------


def test_objective_thresholds():
    q = np.random.default_rng(0).uniform(-0.2, 1.0, 500)
    o = _objective(q, 0.7)
    assert len(o) == 1 + 7  # worst, then thresholds 0.1 .. 0.6 and 0.7
    assert o[0] == q.min()
    assert o[-1] == pytest.approx(np.minimum(q, 0.7).mean(), rel=1e-15)
    for i, t in enumerate((0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)):
        assert o[1 + i] == pytest.approx(np.minimum(q, t).mean(), rel=1e-14)
    o = _objective(q, None)
    assert len(o) == 1 + 10  # thresholds 0.1 .. 0.9 and 1.0
    assert o[-1] == pytest.approx(np.minimum(q, 1.0).mean(), rel=1e-15)
    # a threshold that is not a multiple of 0.1 ends the list, once
    o = _objective(q, 0.55)
    assert len(o) == 1 + 6
    assert o[-1] == pytest.approx(np.minimum(q, 0.55).mean(), rel=1e-15)


def _assert_nothing_attempted(mesh, **kw):
    r = jtet.improve(mesh, **kw)
    assert r.history
    assert {e["op"] for e in r.history} == {"edge", "face", "smooth"}
    for e in r.history:
        assert e["attempts"] == 0, e
        assert e["successes"] == 0, e
    assert _same_mesh(r.mesh, mesh)
    # nothing to do is no progress: the run stops after `patience` passes
    assert r.status == "converged"
    assert len(_passes(r.history)) == r.options.patience


def test_good_quality_kuhn_grid_untouched():
    mesh = grid_mesh(3)
    # every Kuhn tet has dihedral angles 45..90 deg: min_sine is sin(45) normalized by the
    # regular tet's sine 2 sqrt(2) / 3, i.e. 0.75 >= 0.7 (1e-12: float64 round-off)
    kuhn = math.sqrt(0.5) / (2 * math.sqrt(2) / 3)
    assert kuhn == pytest.approx(0.75, abs=1e-15)
    assert mesh.quality("min_sine").min() == pytest.approx(kuhn, abs=1e-12)
    _assert_nothing_attempted(mesh)


@pytest.mark.parametrize("good", [0.01, 0.5])
def test_good_quality_improved_demo_untouched(demo_run, good):
    _, _, r = demo_run
    assert r.mesh.quality("min_sine").min() > good  # measured 0.53
    _assert_nothing_attempted(r.mesh, good_quality=good)


def test_good_quality_none_attempts_at_least_as_much(demo, demo_run):
    _, _, full = demo_run  # good_quality=0.7 (default)
    r = jtet.improve(demo, good_quality=None, max_passes=1)
    for a, b in zip(r.history, full.history[:3], strict=True):
        assert a["op"] == b["op"]
        assert a["attempts"] >= b["attempts"], a["op"]
    # most tets of the demo are better than 0.7: their edges are only tried with None
    # (measured 8097 vs 5246 edges)
    assert r.history[0]["attempts"] > full.history[0]["attempts"]


# --- single operations, boundary sliding, every measure -------------------------------


@pytest.mark.parametrize("op", ["edge", "face", "smooth"])
def test_single_op_never_lowers_worst_quality(demo, op):
    q0 = demo.quality().min()
    r = jtet.improve(demo, ops=(op,), max_passes=2)
    assert {e["op"] for e in r.history} == {op}
    worst = [q0] + [e["worst_quality"] for e in r.history]
    assert worst == sorted(worst)
    assert r.mesh.quality().min() >= q0
    assert r.mesh.is_valid().ok
    assert r.history[0]["successes"] > 0  # each operation finds work on the demo
    if op == "smooth":
        # smoothing moves vertices, never changes the connectivity
        assert np.array_equal(r.mesh.tets, demo.tets)
        assert not np.array_equal(r.mesh.points, demo.points)
    else:
        assert np.array_equal(r.mesh.points, demo.points)


def test_boundary_slide_keeps_boundary():
    mesh = jtet.demo_mesh("two_regions")
    assert mesh.n_tets == 1928
    r = jtet.improve(mesh, boundary="slide")
    assert r.options.boundary == "slide"
    assert r.mesh.is_valid().ok
    # raises InvariantError if the boundary, the z = 0.45 interface, or a region's volume
    # changed
    InvariantChecker(mesh).check(r.mesh, 0, "x")
    # measured: worst min_sine 0.015 -> 0.65 (0.56 with the boundary fixed)
    assert r.mesh.quality().min() > 0.3
    # sliding was used: some vertex on a face of the unit box moved (within that face)
    p0, p1 = mesh.points, r.mesh.points
    moved = np.any(p0 != p1, axis=1)
    on_box = np.any(np.isclose(p0, 0.0, atol=1e-12) | np.isclose(p0, 1.0, atol=1e-12), axis=1)
    assert (moved & on_box).any()
    for axis in range(3):
        for v in (0.0, 1.0):
            plane = np.isclose(p0[:, axis], v, atol=1e-12)
            assert np.allclose(p1[plane, axis], v, atol=1e-12)


def bent_roof() -> jtet.TetMesh:
    """Two tets under a roof a-x-b-y folded along its diagonal ab: the boundary faces
    abx and aby meet at a bend of 2 atan(0.1) = 11.4 degrees. Flipping ab (a boundary
    2-2 flip to the diagonal xy) raises the worst dihedral angle 29.0 -> 58.1 degrees."""
    points = [[-1, 0, 0], [1, 0, 0], [0, -0.3, 0.03], [0, 0.3, 0.03], [0, 0, -0.6]]
    return jtet.TetMesh.from_arrays(np.array(points, float), [[0, 1, 2, 4], [0, 1, 3, 4]])


def test_feature_angle_lets_flips_replace_bent_boundary_faces():
    mesh = bent_roof()
    for angle in (0.0, 10.0):  # the bend is a feature: ab is a subsegment
        r = jtet.improve(mesh, ops=("edge",), feature_angle=angle, check=True)
        assert r.status == "converged" and r.history[0]["successes"] == 0
        assert np.array_equal(r.mesh.tets, mesh.tets)
    r = jtet.improve(mesh, ops=("edge",), feature_angle=15.0, check=True)
    assert r.status == "converged" and r.history[0]["by_kind"]["boundary"] == 1
    assert r.stats_before.min_dihedral < 29.1 and r.stats_after.min_dihedral > 58.0
    # the new diagonal xy is an edge, ab is not; the roof's four vertices stay on the
    # boundary, but the domain changed: the flip filled the fold
    edges = {tuple(e) for e in r.mesh.topology.edges.tolist()}
    assert (2, 3) in edges and (0, 1) not in edges
    assert r.mesh.volumes.sum() > mesh.volumes.sum() + 1e-3
    # the caller's mesh keeps its own topology (feature angle 0: ab a subsegment)
    ab = mesh.topology.edge_ids(np.array([[0, 1]]))[0]
    assert mesh.topology.subsegment[ab]
    # the exact checker of the input mesh sees the changed surface
    with pytest.raises(jtet.InvariantError, match="volume changed"):
        InvariantChecker(mesh).check(r.mesh, 0, "edge")


@pytest.mark.parametrize("measure", sorted(jtet.MEASURES))
def test_every_measure_edge_pass(demo, measure):
    q0 = jtet.quality(demo, measure).min()
    r = jtet.improve(demo, ops=("edge",), max_passes=1, quality=measure)
    q1 = jtet.quality(r.mesh, measure).min()
    assert r.options.quality == measure
    assert r.history[-1]["worst_quality"] == q1
    assert q1 >= q0
    # the demo's worst tets are interior slivers that edge removal fixes under every
    # measure (measured: worst quality x9 or more)
    assert q1 > q0
    assert r.history[0]["successes"] > 0
    assert r.mesh.is_valid().ok


# --- per-tet measures carried across steps ----------------------------------------------


@pytest.mark.parametrize("op", ["edge", "face", "smooth"])
def test_updated_tet_measures_equal_a_full_evaluation(demo, op):
    """The driver re-evaluates only the tets a step created or moved; the result must be
    the whole-mesh evaluation, bit for bit (per-tet values do not depend on the batch)."""
    from jtet._driver import STEPS, _updated_tet_measures
    from jtet._quality import tet_dihedrals

    opts = jtet.Options()
    q = demo.quality(opts.quality)
    _, lo, hi = tet_dihedrals(demo.points, demo.tets)
    step = STEPS[op](demo, opts, q, None)
    assert step.mesh is not demo  # the demo gives every operation work
    q2, lo2, hi2 = _updated_tet_measures(step, opts.quality, q, lo, hi)
    _, lo_ref, hi_ref = tet_dihedrals(step.mesh.points, step.mesh.tets)
    assert np.array_equal(q2, step.mesh.quality(opts.quality))
    assert np.array_equal(lo2, lo_ref) and np.array_equal(hi2, hi_ref)


def test_vertex_ids_above_2_to_16_change_nothing():
    """The flips and the perturbation rounds' submeshes read the int32 topology; with
    70k unreferenced points first (keys of two vertex ids past int32) the run makes the
    same changes as without them, step for step. Smoothing draws its random vertex order
    for the vertices of tets only: it drew one number per point, and these points then
    changed the order (45 -> 54 passes, another output)."""
    mesh = delaunay_mesh(300, seed=3, surface_points=40)
    a = jtet.improve(mesh, check=True)
    b = jtet.improve(shifted(mesh), check=True)
    assert {h["op"] for h in a.history if h["successes"]} == {"edge", "face", "smooth", "perturb"}
    np.testing.assert_array_equal(b.mesh.tets, a.mesh.tets + 70_000)
    np.testing.assert_array_equal(b.mesh.points[70_000:], a.mesh.points)
    assert [h["successes"] for h in b.history] == [h["successes"] for h in a.history]


def _border_edges(faces: np.ndarray) -> set:
    """Edges in exactly one of the triangles ``faces`` (k, 3): the border of the patch."""
    e = np.sort(faces[:, [[0, 1], [0, 2], [1, 2]]].reshape(-1, 2), axis=1)
    rows, count = np.unique(e, axis=0, return_counts=True)
    return set(map(tuple, rows[count == 1].tolist()))


def _area(mesh, faces: np.ndarray) -> float:
    p = mesh.points[faces]
    return 0.5 * float(np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())


@pytest.mark.parametrize("part", ["all", "half"])
def test_protected_boundary_faces_stay_protected_through_flips(part):
    """A 2-2 flip of two coplanar protected boundary faces removed them from the mesh but
    not from ``protected_faces``: the run stopped at pass 11 with "protected face ... is
    not a face of the mesh". Now a protected patch of the boundary is a surface of its
    own: flips may re-triangulate it (the new faces are protected), never move its
    border, and the run ends where the unprotected one does."""
    mesh = jtet.demo_mesh("two_regions")
    T = mesh.topology
    boundary = np.sort(T.faces[T.boundary_face], axis=1)
    if part == "half":  # a patch whose border crosses flat faces of the box
        boundary = boundary[mesh.points[boundary].mean(axis=1)[:, 0] < 0.5]
    result = jtet.improve(mesh.replace(protected_faces=boundary), check=True)
    assert result.status == "converged"
    out = result.mesh
    To = out.topology
    out_boundary = set(map(tuple, np.sort(To.faces[To.boundary_face], axis=1).tolist()))
    protected = out.protected_faces
    assert set(map(tuple, protected.tolist())) <= out_boundary
    assert _area(out, protected) == pytest.approx(_area(mesh, boundary), rel=1e-12)
    assert _border_edges(protected) == _border_edges(boundary)
    if part == "all":
        # measured: 4 protected faces flipped, so the swap path is tested
        assert set(map(tuple, protected.tolist())) != set(map(tuple, boundary.tolist()))
        # protecting the whole boundary splits no surface: the run is the unprotected one
        plain = jtet.improve(mesh)
        assert [h["successes"] for h in result.history] == [h["successes"] for h in plain.history]
        assert result.stats_after.min_dihedral == plain.stats_after.min_dihedral


def test_protected_vertices_never_move():
    """Interior vertices protected (a point source, a probe): the whole run, perturbation
    rounds included, leaves them where they are; unprotected, most of them move."""
    mesh = jtet.demo_mesh()
    pinned = np.flatnonzero(mesh.topology.vertex_kind == 0)[::5]
    result = jtet.improve(mesh.replace(protected_vertices=pinned), check=True)
    assert result.stats_after.min_dihedral > 25
    np.testing.assert_array_equal(result.mesh.points[pinned], mesh.points[pinned])
    np.testing.assert_array_equal(result.mesh.protected_vertices, pinned)
    free = jtet.improve(mesh)
    moved = (free.mesh.points[pinned] != mesh.points[pinned]).any(axis=1)
    assert moved.mean() > 0.5


def test_labelled_boundary_patches_keep_their_borders_and_areas():
    """Boundary faces labelled by x (two labels meeting on flat faces of the box, as two
    Gmsh physical surfaces on one wall): flips may re-triangulate each patch, never move
    the border between them, and every new face carries its patch's label."""
    mesh = jtet.demo_mesh("two_regions")
    T = mesh.topology
    boundary = np.sort(T.faces[T.boundary_face], axis=1)
    labels = np.where(mesh.points[boundary].mean(axis=1)[:, 0] < 0.5, 3, 8)
    labelled = mesh.replace(protected_faces=boundary, protected_face_labels=labels)
    result = jtet.improve(labelled, check=True)  # the checker compares areas per label
    assert result.status == "converged"
    out = result.mesh
    for label in (3, 8):
        before, after = (
            boundary[labels == label],
            out.protected_faces[out.protected_face_labels == label],
        )
        assert _area(out, after) == pytest.approx(_area(mesh, before), rel=1e-12)
        assert _border_edges(after) == _border_edges(before)
    assert len(out.protected_faces) == len(boundary)  # the whole boundary, still labelled


# --- a large mesh's late edge and face steps share one topology update -------------------


def test_step_groups_merge_an_edge_step_and_the_face_step_after_it():
    from jtet._driver import _step_groups

    assert _step_groups(("edge", "face", "smooth"), True) == [("edge", "face"), ("smooth",)]
    assert _step_groups(("smooth", "edge", "face"), True) == [("smooth",), ("edge", "face")]
    for ops in (("face", "edge", "smooth"), ("edge", "smooth", "face"), ("edge",)):
        assert _step_groups(ops, True) == [(op,) for op in ops]
    assert _step_groups(("edge", "face", "smooth"), False) == [("edge",), ("face",), ("smooth",)]


def test_merged_flip_steps_from_the_second_pass(monkeypatch):
    # with the size threshold lowered, the passes after the first apply their edge and
    # face steps together; the run stays valid (checked after every step) and the first
    # pass is the unmerged run's
    from jtet import _driver

    mesh = delaunay_mesh(400, seed=5, surface_points=40)
    kw = dict(perturb=0, check=True, seed=0)
    plain = jtet.improve(mesh, **kw)
    monkeypatch.setattr(_driver, "MERGE_FLIP_STEPS", 0)
    merged = jtet.improve(mesh, **kw)
    assert merged.status == "converged"
    strip = [{k: v for k, v in e.items() if k != "seconds"} for e in merged.history]
    first = [{k: v for k, v in e.items() if k != "seconds"} for e in plain.history]
    n0 = sum(e["pass"] == 0 for e in plain.history)
    assert strip[:n0] == first[:n0]
    late = [e for e in merged.history if e["pass"] >= 1]
    assert [e["op"] for e in late[:3]] == ["edge", "face", "smooth"]
    # an edge entry and the face entry after it show the mesh after both steps
    for edge, face in zip(late[0::3], late[1::3], strict=False):
        assert edge["n_tets"] == face["n_tets"]
        assert edge["worst_quality"] == face["worst_quality"]
    assert sum(e["successes"] for e in late if e["op"] in ("edge", "face")) > 0
    worst = [e["worst_quality"] for e in merged.history]
    assert worst == sorted(worst)
    assert merged.stats_after.quality_min["min_sine"] >= plain.stats_before.quality_min["min_sine"]


@pytest.mark.slow
def test_a_large_mesh_merges_its_later_flip_steps(monkeypatch):
    # a >= 100k-tet Delaunay mesh at the default threshold: the passes after the first
    # go through _flip_steps, and the run, checked after every step, stays valid
    from jtet import _driver

    calls = []
    flip_steps = _driver._flip_steps

    def counted(*args, **kwargs):
        out = flip_steps(*args, **kwargs)
        calls.append(out[0].keep is not None)
        return out

    monkeypatch.setattr(_driver, "_flip_steps", counted)
    mesh = delaunay_mesh(20_000, seed=3)
    assert mesh.n_tets >= _driver.MERGE_FLIP_STEPS
    r = jtet.improve(mesh, perturb=0, check=True, max_passes=4)
    assert r.status in ("converged", "max passes")
    passes = max(e["pass"] for e in r.history) + 1
    assert len(calls) == passes - 1 and any(calls)
    assert r.stats_after.min_dihedral > r.stats_before.min_dihedral
