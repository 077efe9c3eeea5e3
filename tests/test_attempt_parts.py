"""The parts of a perturbation attempt kept on their own (``_attempt_parts``), against a
brute-force grouping of 1-4 splits and against the split of the kept parents alone."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import delaunay_mesh

from jtet._apply import split_tets
from jtet._attempt_parts import Parts
from jtet._invariants import InvariantChecker

WORST, LIMIT = 0.3, 0.35  # the round's worst quality and its near-worst bound


def kept_parts(start, start_q, end, end_q, worst, limit):
    """(result, qualities, parts kept, parts judged) of one attempt's parts, or None."""
    parts = Parts(start, start_q)
    if not parts.add(end, end_q, worst, limit):
        return None
    return parts.result(), parts.qualities(), parts.kept, parts.seen


def _tet_set(mesh, q=None) -> dict:
    """{sorted corner coordinates: quality or None}: a mesh's tets, whatever the ids."""
    keys = [tuple(sorted(map(tuple, mesh.points[t]))) for t in mesh.tets]
    return dict(zip(keys, [None] * len(keys) if q is None else q.tolist(), strict=True))


def _groups(tets: np.ndarray) -> list[list[int]]:
    """Brute force: tets chained by shared vertices, one Python loop over pairs."""
    label = list(range(len(tets)))

    def root(i):
        while label[i] != i:
            i = label[i]
        return i

    for i in range(len(tets)):
        for j in range(i):
            if set(tets[i]) & set(tets[j]):
                label[root(i)] = root(j)
    groups: dict[int, list[int]] = {}
    for i in range(len(tets)):
        groups.setdefault(root(i), []).append(i)
    return list(groups.values())


@pytest.mark.parametrize("seed", range(6))
def test_split_parts_kept_against_brute_force(seed):
    """Random 1-4 splits with random qualities: the parts kept are the groups of split
    parents (chained by shared vertices) whose children are all at least the round's
    worst and have no more tets below the near bound than the parents; the result is
    the start with those parents alone split, with the qualities of each side."""
    rng = np.random.default_rng(seed)
    mesh = delaunay_mesh(120, seed=seed)
    which = rng.random(mesh.n_tets) < 0.06
    end, keep = split_tets(mesh, which)
    parents = np.flatnonzero(~keep)
    start_q = rng.uniform(0.28, 1.0, mesh.n_tets)
    end_q = np.concatenate([start_q[keep], rng.uniform(0.29, 1.0, 4 * len(parents))])
    children_q = end_q[int(keep.sum()) :].reshape(-1, 4)  # split_tets: 4 per parent, in order

    good = []
    for group in _groups(mesh.tets[parents]):
        new_q, old_q = children_q[group].reshape(-1), start_q[parents[group]]
        if new_q.min() >= WORST and (new_q < LIMIT).sum() <= (old_q < LIMIT).sum():
            good += group
    got = kept_parts(mesh, start_q, end, end_q, WORST, LIMIT)
    if not good:
        assert got is None
        return
    composite, q, n_kept, n_parts = got
    assert n_parts == len(_groups(mesh.tets[parents])) and 0 < n_kept <= n_parts
    expected, _ = split_tets(mesh, np.isin(np.arange(mesh.n_tets), parents[good]))
    expected_q = dict(_tet_set(mesh, start_q))
    for i, parent in enumerate(parents):
        if i in good:
            del expected_q[tuple(sorted(map(tuple, mesh.points[mesh.tets[parent]])))]
    split_children = _tet_set(end, end_q)
    for key in _tet_set(expected):
        if key not in expected_q:  # a kept parent's child
            expected_q[key] = split_children[key]
    assert _tet_set(composite, q) == expected_q
    # the kept centroids only, after the start's points
    assert composite.n_points == mesh.n_points + len(good)
    np.testing.assert_array_equal(composite.points[: mesh.n_points], mesh.points)
    InvariantChecker(mesh).check(composite, 0, "perturb")


def _far_apart(tets: np.ndarray, candidates: np.ndarray, count: int) -> np.ndarray:
    """``count`` of the ``candidates`` tets no two of which share a vertex or a
    neighbour's vertex."""
    chosen, taken = [], np.zeros(tets.max() + 1, bool)
    for t in candidates:
        if not taken[tets[t]].any():
            chosen.append(t)
            near = np.isin(tets, tets[t]).any(axis=1)
            taken[tets[near].reshape(-1)] = True
            if len(chosen) == count:
                return np.array(chosen)
    raise AssertionError("mesh too small")


def test_a_part_that_does_not_fill_its_space_is_not_kept():
    """A tet missing from the attempt's end (a part with nothing to fill it) is not
    separable: the split parts around it are kept, the missing tet stays."""
    mesh = delaunay_mesh(200, seed=3)
    interior = np.flatnonzero(mesh.topology.boundary_face[mesh.topology.tet_faces].sum(axis=1) == 0)
    a, b, c = _far_apart(mesh.tets, interior, 3)
    split, keep = split_tets(mesh, np.isin(np.arange(mesh.n_tets), [a, b]))
    holed = np.ones(split.n_tets, bool)
    holed[np.cumsum(keep)[c] - 1] = False  # tet c in the split mesh (kept tets first)
    end = split.replace(tets=split.tets[holed], region=split.region[holed])
    start_q, end_q = np.ones(mesh.n_tets), np.ones(end.n_tets)
    composite, q, n_kept, n_parts = kept_parts(mesh, start_q, end, end_q, WORST, LIMIT)
    assert (n_kept, n_parts) == (2, 3)
    assert composite.n_tets == mesh.n_tets + 6
    assert tuple(sorted(map(tuple, mesh.points[mesh.tets[c]]))) in _tet_set(composite)
    np.testing.assert_allclose(composite.volumes.sum(), mesh.volumes.sum(), rtol=1e-12)


@pytest.mark.parametrize("good_move", [True, False])
def test_a_moved_vertex_goes_back_with_its_part(good_move):
    """A vertex moved by the attempt keeps its new place only if its star's new
    qualities are kept; a split far from it is kept either way."""
    mesh = delaunay_mesh(200, seed=5)
    T = mesh.topology
    free = np.flatnonzero(~np.isin(np.arange(mesh.n_points), T.faces[T.boundary_face]))
    v = int(free[0])
    star = np.flatnonzero((mesh.tets == v).any(axis=1))
    near = np.isin(mesh.tets, mesh.tets[star]).any(axis=1)
    far = int(np.flatnonzero(~near & ~np.isin(mesh.tets, mesh.tets[near]).any(axis=1))[0])
    split, keep = split_tets(mesh, np.arange(mesh.n_tets) == far)
    points = split.points.copy()
    points[v] += 1e-3 * (points[mesh.tets[star]].mean(axis=(0, 1)) - points[v])
    end = split.replace(points=points)
    assert (end.volumes > 0).all()
    start_q = np.ones(mesh.n_tets)
    end_q = np.ones(end.n_tets)
    moved = np.flatnonzero((end.tets == v).any(axis=1))
    end_q[moved] = 0.9 if good_move else 0.1
    composite, q, n_kept, n_parts = kept_parts(mesh, start_q, end, end_q, WORST, LIMIT)
    assert n_parts == 2 and n_kept == (2 if good_move else 1)
    np.testing.assert_array_equal(
        composite.points[v], end.points[v] if good_move else mesh.points[v]
    )
    assert composite.n_tets == mesh.n_tets + 3 and (composite.volumes > 0).all()
    np.testing.assert_allclose(composite.volumes.sum(), mesh.volumes.sum(), rtol=1e-12)


def test_nothing_kept_when_every_part_is_worse():
    mesh = delaunay_mesh(100, seed=1)
    end, keep = split_tets(mesh, np.arange(mesh.n_tets) < 3)
    got = kept_parts(mesh, np.ones(mesh.n_tets), end, np.full(end.n_tets, 0.1), WORST, LIMIT)
    assert got is None
    same = kept_parts(mesh, np.ones(mesh.n_tets), mesh, np.ones(mesh.n_tets), WORST, LIMIT)
    assert same is None  # no change at all


def test_parts_of_several_attempts_combine_unless_they_touch():
    """Two attempts from the same start: the second's part far from the first's is
    kept beside it, its part on the same tet is refused (it touches a kept part); the
    result is the start with both far splits, a valid mesh of the same volume."""
    mesh = delaunay_mesh(200, seed=7)
    interior = np.flatnonzero(mesh.topology.boundary_face[mesh.topology.tet_faces].sum(axis=1) == 0)
    a, b = _far_apart(mesh.tets, interior, 2)
    first, _ = split_tets(mesh, np.arange(mesh.n_tets) == a)
    second, _ = split_tets(mesh, np.isin(np.arange(mesh.n_tets), [a, b]))
    parts = Parts(mesh, np.ones(mesh.n_tets))
    assert parts.add(first, np.ones(first.n_tets), WORST, LIMIT) == 1
    assert parts.add(second, np.ones(second.n_tets), WORST, LIMIT) == 1  # b only
    assert (parts.kept, parts.seen) == (2, 3)
    result = parts.result()
    expected, _ = split_tets(mesh, np.isin(np.arange(mesh.n_tets), [a, b]))
    assert _tet_set(result) == _tet_set(expected)
    assert result.n_points == mesh.n_points + 2 and len(parts.qualities()) == result.n_tets
    InvariantChecker(mesh).check(result, 0, "perturb")
