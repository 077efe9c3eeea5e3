"""Applying a step's winners (jtet._apply): the conformity guard against a brute force."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from helpers import delaunay_mesh

from jtet import _apply

# faces of a tet opposite each vertex, listed outward for a positive tet (as VTK does)
OUTWARD = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]


def _inversions(row) -> int:
    return sum(a > b for a, b in itertools.combinations(row, 2))


def reference_nonconforming(mesh, remove, new_tets, new_owner, n_cand) -> np.ndarray:
    """Candidates one of whose new tets has a face lying in more than two tets of the new
    mesh, or in two tets that list it with the same orientation: a loop over the new
    mesh's faces with a dictionary."""
    tets = np.concatenate([mesh.tets[~remove], new_tets])
    owner = np.concatenate([np.full((~remove).sum(), -1), new_owner])
    sides: dict[tuple, list] = {}
    for t, tet in enumerate(tets.tolist()):
        for local in OUTWARD:
            face = [tet[i] for i in local]
            sides.setdefault(tuple(sorted(face)), []).append((t, _inversions(face) % 2))
    reject = np.zeros(n_cand, bool)
    for entries in sides.values():
        parities = [p for _, p in entries]
        if len(entries) > 2 or (len(entries) == 2 and parities[0] == parities[1]):
            for t, _ in entries:
                if owner[t] >= 0:
                    reject[owner[t]] = True
    return reject


def _random_step(mesh, rng, n_cand: int):
    """Candidates that each remove a few tets and add back tets that conform (the same
    tets), repeat a kept tet, list a removed tet inside out, or join random vertices."""
    m = mesh.n_tets
    claims = rng.permutation(m)[: 2 * n_cand].reshape(n_cand, 2)
    remove = np.zeros(m, bool)
    remove[claims.reshape(-1)] = True
    kept = np.flatnonzero(~remove)
    new, owner = [], []
    for c in range(n_cand):
        kind = rng.integers(4)
        if kind == 0:  # the removed tets themselves: conforming
            add = mesh.tets[claims[c]]
        elif kind == 1:  # a kept tet again: a duplicate
            add = mesh.tets[rng.choice(kept, 1)]
        elif kind == 2:  # a removed tet inside out: its faces face the wrong way
            add = mesh.tets[claims[c, :1]][:, [1, 0, 2, 3]]
        else:  # four random vertices
            add = rng.choice(mesh.n_points, (1, 4), replace=False)
        new.append(add)
        owner.append(np.full(len(add), c))
    return remove, np.concatenate(new), np.concatenate(owner)


@pytest.mark.parametrize("seed", range(6))
def test_nonconforming_owners_against_brute_force(seed):
    mesh = delaunay_mesh(60, seed=seed)
    rng = np.random.default_rng(seed)
    n_cand = 12
    remove, new_tets, new_owner = _random_step(mesh, rng, n_cand)
    expected = reference_nonconforming(mesh, remove, new_tets, new_owner, n_cand)
    got = _apply.nonconforming_owners(mesh, remove, new_tets, new_owner, n_cand)
    np.testing.assert_array_equal(got, expected)
    assert expected.any() and not expected.all()  # both kinds of candidate occur
    # meshes of more than ~1.66M points, whose face keys are per-call ranks, agree
    ranked = delaunay_mesh(60, seed=seed)
    ranked.topology.__dict__["face_keys"] = None
    got = _apply.nonconforming_owners(ranked, remove, new_tets, new_owner, n_cand)
    np.testing.assert_array_equal(got, expected)


def test_nonconforming_owners_of_no_new_tets():
    mesh = delaunay_mesh(30, seed=1)
    remove = np.zeros(mesh.n_tets, bool)
    empty = np.zeros((0, 4), np.int64)
    got = _apply.nonconforming_owners(mesh, remove, empty, np.zeros(0, np.int64), 3)
    assert got.shape == (3,) and not got.any()


@pytest.mark.parametrize("seed", range(4))
def test_recreating_owners_against_vertex_sets(seed):
    """Candidates whose new tets include a forbidden tet in any vertex order, against a
    loop over Python sets; no forbidden tets (None or empty) reject nothing."""
    rng = np.random.default_rng(seed)
    forbidden = rng.choice(40, (5, 4), replace=True)
    forbidden = forbidden[[len(set(r)) == 4 for r in forbidden.tolist()]]
    n_cand = 10
    new, owner = [], []
    for c in range(n_cand):
        for _ in range(rng.integers(1, 4)):
            if rng.random() < 0.3:  # a forbidden tet, its vertices shuffled
                new.append(rng.permutation(forbidden[rng.integers(len(forbidden))]))
            else:
                new.append(rng.choice(40, 4, replace=False))
            owner.append(c)
    new, owner = np.array(new), np.array(owner)
    sets = {frozenset(r) for r in forbidden.tolist()}
    expected = np.zeros(n_cand, bool)
    for t, c in zip(new.tolist(), owner.tolist()):
        expected[c] |= frozenset(t) in sets
    got = _apply.recreating_owners(new, owner, forbidden, n_cand)
    np.testing.assert_array_equal(got, expected)
    assert expected.any() and not expected.all()
    for none in (None, np.zeros((0, 4), np.int64)):
        assert not _apply.recreating_owners(new, owner, none, n_cand).any()


@pytest.mark.parametrize("kept_share", [0.0, 0.5, 0.99, 1.0])
@pytest.mark.parametrize("shape", [(4,), ()])
def test_kept_then_new_matches_concatenate(kept_share, shape):
    """``kept_then_new`` is ``np.concatenate([rows[keep], new])`` in the rows' dtype, for
    (m, 4) tets and (m,) labels, new rows of a narrower type, no kept or no new rows."""
    rng = np.random.default_rng(11)
    rows = rng.integers(0, 1000, (500, *shape)).astype(np.int64)
    keep = rng.random(500) < kept_share
    for k in (0, 37):
        new = rng.integers(0, 1000, (k, *shape)).astype(np.int32)
        got = _apply.kept_then_new(rows, keep, new)
        assert got.dtype == np.int64
        assert np.array_equal(got, np.concatenate([rows[keep], new.astype(np.int64)]))
