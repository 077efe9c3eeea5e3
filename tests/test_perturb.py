"""Perturbation rounds (``Options.perturb``): acceptance rule, restore, invariants."""

from __future__ import annotations

import numpy as np
import pytest

import jtet
from jtet import _driver
from jtet._perturb import SLACKS, WINDOWS, better, kicks


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


def test_kicks_order_and_ops():
    ladder = kicks(("edge", "face", "smooth"))
    assert len(ladder) == len(SLACKS) * len(WINDOWS) * 2
    # gentlest slack first, each slack with the narrow window before the wide one
    assert [k[0] for k in ladder] == sorted(k[0] for k in ladder)
    assert ladder[0] == (SLACKS[0], WINDOWS[0], "edge")
    assert {k[2] for k in kicks(("face", "smooth"))} == {"face"}
    assert kicks(("smooth",)) == []


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
    assert all(e["attempts"] == 1 and e["kick"] in ("edge", "face") for e in rounds)
    assert rounds[-1]["worst_quality"] == q_after.min()
    assert rounds[-1]["n_tets"] == perturbed.mesh.n_tets
    kept = sum(e["successes"] for e in rounds)
    assert 0 < kept <= perturbed.options.perturb
    assert perturbed.mesh.is_valid().ok


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

    def climb_then_interrupt(self, t0, record=True, patience=None):
        calls.append(record)
        if not record:  # the perturbation's climb, right after a kick was applied
            raise KeyboardInterrupt
        return climb(self, t0, record, patience)

    monkeypatch.setattr(_driver._Run, "climb", climb_then_interrupt)
    r = jtet.improve(demo, perturb=8)
    assert calls == [True, False]
    assert r.status == "interrupted"
    assert np.array_equal(r.mesh.tets, plain.mesh.tets)
    assert np.array_equal(r.mesh.points, plain.mesh.points)


def test_perturb_option_validated():
    with pytest.raises(jtet.JtetError, match="perturb"):
        jtet.Options(perturb=-1)
    with pytest.raises(jtet.JtetError, match="perturb"):
        jtet.Options(perturb=1.5)
