"""A perturbation round's places (``_perturb.places``, ``with_places``, ``_round``):
the parts of a round's submesh that share no vertex, each with its own ladder, kept
together in one splice."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import delaunay_mesh, shared_mesh_path

import jtet
from jtet import _perturb
from jtet._apply import split_tets
from jtet._invariants import InvariantChecker
from jtet._perturb import places, with_places
from jtet._submesh import Submesh


def _brute_places(tets: np.ndarray) -> list[frozenset]:
    """Groups of tet indices chained by shared vertices, one Python loop over pairs."""
    root = list(range(len(tets)))

    def find(i):
        while root[i] != i:
            i = root[i]
        return i

    for i in range(len(tets)):
        for j in range(i):
            if set(tets[i]) & set(tets[j]):
                root[find(i)] = find(j)
    groups: dict[int, set] = {}
    for i in range(len(tets)):
        groups.setdefault(find(i), set()).add(i)
    return sorted(map(frozenset, groups.values()), key=min)


def _grouped(label: np.ndarray) -> list[frozenset]:
    return sorted((frozenset(np.flatnonzero(label == v).tolist()) for v in set(label)), key=min)


@pytest.mark.parametrize("seed", range(5))
def test_places_against_brute_force(seed):
    """Random tets of a Delaunay mesh as a submesh: its places are the groups of tets
    chained by shared vertices."""
    rng = np.random.default_rng(seed)
    mesh = delaunay_mesh(300, seed=seed)
    sub = Submesh(mesh, rng.random(mesh.n_tets) < 0.03).mesh
    label = places(sub, _perturb.PLACES_MIN_TETS)  # as in a large mesh
    assert label.shape == (sub.n_tets,)
    assert _grouped(label) == _brute_places(sub.tets)
    assert len(set(label)) > 1  # the case has several places


def _tet_set(mesh) -> set:
    return {tuple(sorted(map(tuple, mesh.points[t]))) for t in mesh.tets}


def test_with_places_against_the_places_changed_in_place():
    """Two places of a submesh, each changed on its own (a 1-4 split of one of its
    tets): the submesh with both applied is the submesh with both tets split; with one
    place that is the whole submesh, its end is the result."""
    mesh = delaunay_mesh(300, seed=2)
    rng = np.random.default_rng(2)
    sub = Submesh(mesh, rng.random(mesh.n_tets) < 0.03).mesh
    label = places(sub, _perturb.PLACES_MIN_TETS)  # as in a large mesh
    first, second = (int(v) for v in np.unique(label)[:2])
    kept, split = [], np.zeros(sub.n_tets, bool)
    for place in (first, second):
        mask = label == place
        part, verts, _ = sub._part(mask)
        end, _ = split_tets(part, np.arange(part.n_tets) == 0)
        kept.append((mask, verts, end))
        split[np.flatnonzero(mask)[0]] = True
    both = with_places(sub, kept)
    expected, _ = split_tets(sub, split)
    assert _tet_set(both) == _tet_set(expected)
    assert both.n_points == sub.n_points + 2 and (both.volumes > 0).all()
    np.testing.assert_allclose(both.volumes.sum(), sub.volumes.sum(), rtol=1e-12)
    InvariantChecker(sub).check(both, 0, "perturb")
    whole, _ = split_tets(sub, split)
    assert with_places(sub, [(np.ones(sub.n_tets, bool), None, whole)]) is whole


def test_a_round_keeps_several_places_and_never_loses(monkeypatch):
    """On the holeplate (seed 0, places at any size) some rounds keep kicks in several
    places at once: the run passes the invariant checks after every step, its kept
    rounds stay within the limit, and the rounds end no lower than the climb."""
    monkeypatch.setattr(_perturb, "PLACES_MIN_TETS", 0)
    mesh = jtet.load(shared_mesh_path("gmsh_holeplate.vtu"))
    result = jtet.improve(mesh, seed=0, check=True)
    assert result.status == "converged"
    kicks = [e for e in result.history if e["op"] == "perturb"]
    kept = [e["round"] for e in kicks if e["successes"]]
    assert len(kept) > len(set(kept))  # a round kept more than one place
    assert len(set(kept)) <= result.perturb_rounds
    climb = [e for e in result.history if e["op"] != "perturb"]
    assert result.stats_after.min_dihedral >= climb[-1]["min_dihedral"]
    assert all(e["worst_quality"] >= climb[-1]["worst_quality"] for e in kicks)


@pytest.mark.parametrize("switch", ["off", "small mesh"])
def test_without_places_each_round_keeps_one_kick(monkeypatch, switch):
    """Places off, or a mesh under ``PLACES_MIN_TETS`` (the holeplate's 33k tets): one
    kick kept per round, as many as the automatic limit (8)."""
    if switch == "off":
        monkeypatch.setattr(_perturb, "PLACES", False)
        monkeypatch.setattr(_perturb, "PLACES_MIN_TETS", 0)
    result = jtet.improve(jtet.load(shared_mesh_path("gmsh_holeplate.vtu")), seed=0)
    kept = [e["round"] for e in result.history if e["op"] == "perturb" and e["successes"]]
    assert len(kept) == len(set(kept)) == 8
