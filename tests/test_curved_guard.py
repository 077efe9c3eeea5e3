"""The guard on curved tets (``jtet._curved_guard``): no flip, split or vertex move leaves
a tet with a curved edge whose scaled Jacobian is below both ``min_scaled_jacobian`` and
the worst of the tets it replaced.

The reference is the quadratic output itself: ``quadratic_mesh`` puts each curved edge's
node on the tets that still have that edge with both ends in place, and
``jacobian_ratios`` (Gmsh's minSJ, tet for tet: ``test_quadratic_output.py``) measures
them. The guard must keep min over the output >= min(floor, min over the input).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from helpers import delaunay_mesh, grid_mesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

import jtet
from jtet._curved_guard import scaled_jacobians
from jtet._driver import STEPS
from jtet._perturb import kick_step
from jtet._quadratic import MID_EDGES, jacobian_ratios, quadratic_mesh
from jtet._topology import TET_FACES, match_rows

# the ratios are quotients of float64 determinants of O(1) coordinates: equal up to a
# few ulps of 1 whichever way they are summed
TOL = 1e-9


def bent_mesh(seed: int, bend: float = 0.02, n: int = 5) -> jtet.TetMesh:
    """A perturbed grid mesh (no slivers) whose every edge has a node off its midpoint
    by a random vector of ``bend`` times the edge's length: tets bent a little, a few
    of them folded, for careless operations to fold more."""
    mesh = grid_mesh(n, perturb=0.3, seed=seed)
    edges = np.unique(np.sort(mesh.tets[:, MID_EDGES[4]].reshape(-1, 2), axis=1), axis=0)
    ends = mesh.points[edges]
    length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    rng = np.random.default_rng(seed)
    offset = rng.normal(size=(len(edges), 3)) * (bend * length)[:, None]
    return mesh.replace(curved_edges=(edges, ends.mean(axis=1) + offset))


def ratios(mesh: jtet.TetMesh) -> np.ndarray:
    """(m,) scaled Jacobian of each tet of ``mesh``'s quadratic output."""
    quad = quadratic_mesh(mesh)
    return jacobian_ratios(quad.points, quad.tets)


def worst_ratio(mesh: jtet.TetMesh) -> float:
    return float(ratios(mesh).min())


def _changed(a: jtet.TetMesh, b: jtet.TetMesh) -> np.ndarray:
    """(m_a,) bool: the tets of ``a`` that ``b`` does not have (as vertex sets), or
    that have a vertex at other coordinates in ``b``."""
    gone = match_rows(b.tets, a.tets, max(a.n_points, b.n_points)) < 0
    k = min(a.n_points, b.n_points)
    moved = np.zeros(a.n_points, bool)
    moved[:k] = (a.points[:k] != b.points[:k]).any(axis=1)
    return gone | moved[a.tets].any(axis=1)


def bent_cavities(before: jtet.TetMesh, after: jtet.TetMesh, floor: float) -> int:
    """How many of the changed places break the guard's rule: the tets ``before`` lost
    and ``after`` gained, grouped by shared faces (a flip's cavity is bounded by faces
    that one old and one new tet hold; adjacent cavities merge, for which the rule
    holds as well), whose new tets' smallest scaled Jacobian is below min(``floor``,
    their old tets' smallest)."""
    lost, gained = _changed(before, after), _changed(after, before)
    tets = np.concatenate([before.tets[lost], after.tets[gained]])
    ratio = np.concatenate([ratios(before)[lost], ratios(after)[gained]])
    new = np.arange(len(tets)) >= lost.sum()
    faces = np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1)
    _, key = np.unique(faces, axis=0, return_inverse=True)
    order = np.argsort(key.ravel(), kind="stable")
    holder = np.repeat(np.arange(len(tets)), 4)[order]
    same = key.ravel()[order][1:] == key.ravel()[order][:-1]
    link = coo_matrix(
        (np.ones(same.sum()), (holder[1:][same], holder[:-1][same])), shape=(len(tets),) * 2
    )
    k, label = connected_components(link, directed=False)
    worst_old, worst_new = np.full(k, np.inf), np.full(k, np.inf)
    np.minimum.at(worst_old, label[~new], ratio[~new])
    np.minimum.at(worst_new, label[new], ratio[new])
    return int((worst_new < np.minimum(worst_old, floor) - TOL).sum())


@pytest.mark.parametrize("seed", [0, 1])
def test_scaled_jacobians_match_the_quadratic_output(seed):
    """``scaled_jacobians`` at the mesh's points and at moved points (the curved edges
    with a moved end straight) against the quadratic mesh of the same points."""
    mesh = bent_mesh(seed)
    quad = quadratic_mesh(mesh)
    expected = jacobian_ratios(quad.points, quad.tets)
    np.testing.assert_allclose(scaled_jacobians(mesh, mesh.points, mesh.tets), expected, atol=TOL)
    rng = np.random.default_rng(seed)
    moved = mesh.points.copy()
    which = rng.choice(mesh.n_points, mesh.n_points // 5, replace=False)
    moved[which] += rng.normal(size=(len(which), 3)) * 1e-3
    quad = quadratic_mesh(mesh.replace(points=moved))
    np.testing.assert_allclose(
        scaled_jacobians(mesh, moved, mesh.tets), jacobian_ratios(quad.points, quad.tets), atol=TOL
    )
    # a tet without a curved edge (all dropped) is straight: exactly 1
    straight = mesh.replace(curved_edges=None)
    assert (scaled_jacobians(straight, straight.points, straight.tets) == 1.0).all()


def _step(op: str):
    if op in STEPS:
        return STEPS[op]
    return kick_step(op, None)


@pytest.mark.parametrize("op", ["edge", "face", "insert", "jiggle0"])
def test_no_flip_split_or_jiggle_bends_a_curved_tet_below_the_floor(op):
    """One step of each operation on bent meshes: with the guard (floor 0.3) no changed
    place has new tets worse than min(0.3, its old tets); without it (None) some do
    (so the check can fail)."""
    unguarded = 0
    for seed in range(4):
        mesh = bent_mesh(seed)
        for floor in (0.3, None):
            opts = jtet.Options(min_scaled_jacobian=floor, seed=seed, good_quality=None)
            q = mesh.quality(opts.quality)
            out = _step(op)(mesh, opts, q, q < np.quantile(q, 0.3)).mesh
            assert out is not mesh
            bent = bent_cavities(mesh, out, 0.3)
            if floor is None:
                unguarded += bent
            else:
                assert bent == 0, seed
    assert unguarded > 0


def test_no_smoothing_move_bends_a_curved_tet_below_the_floor():
    """Smoothing one vertex at a time (the stars of one pass's vertices overlap): with
    the guard, no star ends worse than min(0.3, its worst before); without it, some do."""
    from jtet._smooth import smooth_pass

    unguarded = guarded_moves = 0
    for seed in range(3):
        mesh = bent_mesh(seed, bend=0.04)
        r = ratios(mesh)
        star_worst = np.full(mesh.n_points, np.inf)
        np.minimum.at(star_worst, mesh.tets.reshape(-1), np.repeat(r, 4))
        for v in np.argsort(star_worst)[:12]:
            only = np.zeros(mesh.n_points, bool)
            only[v] = True
            for floor in (0.3, None):
                out, stats = smooth_pass(mesh, candidates=only, min_scaled_jacobian=floor)
                bent = bent_cavities(mesh, out, 0.3)
                if floor is None:
                    unguarded += bent
                else:
                    assert bent == 0, (seed, v)
                    guarded_moves += stats.successes
    assert unguarded > 0 and guarded_moves > 0


@pytest.mark.parametrize("boundary", ["fixed", "slide"])
def test_improve_keeps_curved_tets_above_the_floor(boundary):
    """Whole runs (climb and perturbation rounds): the improved mesh's quadratic output
    keeps min(floor, the input's) as its smallest scaled Jacobian, and the note says
    both values."""
    for seed, floor in [(0, 0.3), (1, 0.5), (2, 0.0)]:
        mesh = bent_mesh(seed)
        before = worst_ratio(mesh)
        result = jtet.improve(mesh, seed=seed, boundary=boundary, min_scaled_jacobian=floor)
        after = worst_ratio(result.mesh)
        assert after >= min(floor, before) - TOL, (seed, before, after)
        note = [n for n in result.notes if n.startswith("smallest scaled Jacobian")]
        assert note == [
            f"smallest scaled Jacobian of the curved tets: {before:.3f} -> {after:.3f} "
            f"(no change could take a tet below min({floor:g}, the tets it replaced))"
        ]


def test_guard_option_and_cli(tmp_path):
    """The option is checked; ``jtet improve --linear --quadratic`` takes the floor
    (a number or 'none') and its quadratic output keeps it."""
    import json

    from jtet.cli import main

    for bad in (1.5, float("nan")):
        with pytest.raises(jtet.JtetError, match="min_scaled_jacobian"):
            jtet.Options(min_scaled_jacobian=bad)
    assert jtet.Options().min_scaled_jacobian == 0.3
    src = tmp_path / "bent.vtu"
    mesh = bent_mesh(0)  # some of its tets fold already
    with pytest.warns(UserWarning, match="non-positive Jacobian"):
        jtet.save(mesh, src, quadratic=True)
    before = worst_ratio(mesh)
    for text, floor in [("0.5", 0.5), ("none", None)]:
        out, report = tmp_path / f"out_{text}.vtu", tmp_path / f"r_{text}.json"
        argv = ["improve", str(src), str(out), "--linear", "--quadratic", "-q"]
        assert main([*argv, "--min-scaled-jacobian", text, "--report", str(report)]) == 0
        assert json.loads(report.read_text())["options"]["min_scaled_jacobian"] == floor
        with pytest.warns(UserWarning):
            after = worst_ratio(jtet.load(out, linear=True))
        if floor is not None:
            assert after >= min(floor, before) - TOL


def test_perturbation_rounds_see_the_curved_edges():
    """A round works on a submesh, maybe in a helper process: the submesh has the curved
    edges between its vertices (renumbered), and so has its piped copy."""
    from jtet._perturb import Outcome, RoundState
    from jtet._submesh import Submesh

    mesh = bent_mesh(1)
    sel = np.random.default_rng(0).random(mesh.n_tets) < 0.4
    part = Submesh(mesh, sel)
    sub = part.mesh
    local = {int(v): i for i, v in enumerate(part.verts)}
    expected = sorted(
        (tuple(sorted((local[a], local[b]))), tuple(p))
        for (a, b), p in zip(mesh.curved_edges.edges.tolist(), mesh.curved_edges.points.tolist())
        if a in local and b in local
    )
    assert 0 < len(expected) < len(mesh.curved_edges.edges)

    def pairs(m):
        c = m.curved_edges
        return sorted((tuple(e), tuple(p)) for e, p in zip(c.edges.tolist(), c.points.tolist()))

    assert pairs(sub) == expected
    assert pairs(Outcome(mesh=sub).for_pipe().submesh()) == expected
    q = sub.quality("biased_min_sine")
    state = RoundState(sub, q, q, q, jtet.Options(), 0.0, 0.6, 0.0, q < 0.3)
    received = time.perf_counter()
    assert pairs(RoundState.start(state.for_pipe(), received).sub.current) == expected


def test_sliding_keeps_the_ends_of_curved_edges():
    """With the boundary sliding, a flat face's vertices move, but not the ends of its
    curved edges: every curved edge on the boundary comes out of improve with its node
    (the same run without curved edges slides some of those ends, so the check bites)."""
    mesh = delaunay_mesh(150, seed=5, surface_points=80)
    topo = mesh.topology
    faces = topo.faces[topo.subfacet]
    edges = np.unique(np.sort(faces[:, [[0, 1], [1, 2], [0, 2]]].reshape(-1, 2), axis=1), axis=0)
    rng = np.random.default_rng(5)
    edges = edges[rng.choice(len(edges), 60, replace=False)]
    bent = mesh.points[edges].mean(axis=1) + 1e-4
    curved = mesh.replace(curved_edges=(edges, bent))
    ends = np.unique(edges)
    plain = jtet.improve(mesh, boundary="slide", seed=0, perturb=0, max_passes=4).mesh
    slid = (plain.points[ends] != mesh.points[ends]).any(axis=1)
    assert slid.any()
    out = jtet.improve(curved, boundary="slide", seed=0, perturb=0, max_passes=4).mesh
    np.testing.assert_array_equal(out.points[ends], mesh.points[ends])


@pytest.mark.parametrize("seed", [0, 3])
def test_surface_curved_edges_are_the_curved_edges_bending_a_subfacet(seed):
    """Against a brute force over the whole-mesh topology's subfacets (boundary faces,
    faces between the two regions, protected faces): a curved edge is pinned iff its node
    is off the plane of one of the subfacets holding it. Curved edges drawn at random
    among all edges, inside and on surfaces; half of those on surfaces bent within the
    plane of one of their subfacets (flat boundary faces: within both)."""
    from jtet._curved_guard import surface_curved_edges
    from jtet._quadratic import CURVED_TOL

    mesh = bent_mesh(seed, n=6)
    rng = np.random.default_rng(seed)
    region = (mesh.points[mesh.tets].mean(axis=1)[:, 0] < 0.45).astype(np.int64)
    inner = mesh.topology.faces[~mesh.topology.subfacet]
    protected = inner[rng.choice(len(inner), 10, replace=False)]
    c = mesh.curved_edges
    some = rng.random(len(c.edges)) < 0.5
    mesh = mesh.replace(region=region, protected_faces=protected)
    topo = mesh.topology
    edges, nodes = c.edges[some], c.points[some].copy()
    sub = topo.faces[topo.subfacet]
    holding = [sub[(sub == a).any(axis=1) & (sub == b).any(axis=1)] for a, b in edges.tolist()]
    for i, faces in enumerate(holding):
        if len(faces) and rng.random() < 0.5:  # bend it towards its first face's corner
            a, b = edges[i]
            x = (set(faces[0].tolist()) - {a, b}).pop()
            mid = mesh.points[[a, b]].mean(axis=0)
            nodes[i] = mid + 0.05 * (mesh.points[x] - mid)
    mesh = mesh.replace(curved_edges=(edges, nodes))

    def bends(i: int) -> bool:
        a, b = mesh.points[edges[i]]
        for face in holding[i]:
            p = mesh.points[face]
            normal = np.cross(p[1] - p[0], p[2] - p[0])
            height = abs(np.dot(nodes[i] - p[0], normal)) / np.linalg.norm(normal)
            if height > CURVED_TOL * np.linalg.norm(b - a):
                return True
        return False

    expected = edges[[bends(i) for i in range(len(edges))]]
    on_surface = sum(len(f) > 0 for f in holding)
    assert 0 < len(expected) < on_surface < len(edges)
    got = surface_curved_edges(mesh)
    np.testing.assert_array_equal(np.unique(got, axis=0), np.unique(expected, axis=0))


@pytest.mark.parametrize("boundary", ["fixed", "slide"])
def test_curved_edges_on_flat_boundary_faces_are_never_flipped(boundary):
    """Every boundary edge of a cube mesh carries a node off its midpoint and off the
    cube's faces. Their faces are coplanar, so without the curved nodes the run 2-2 flips
    some of them (the check bites); with them, the run keeps every one (a flip would cut
    straight across the curved surface) and gives back the input's own protected edges
    (none). Bent within the cube's faces, they may be flipped."""
    from jtet._curved_guard import surface_curved_edges
    from jtet._quadratic import curved_edges_kept

    mesh = delaunay_mesh(150, seed=0, surface_points=80)
    topo = mesh.topology
    faces = topo.faces[topo.subfacet]
    edges = np.unique(np.sort(faces[:, [[0, 1], [1, 2], [0, 2]]].reshape(-1, 2), axis=1), axis=0)
    curved = mesh.replace(curved_edges=(edges, mesh.points[edges].mean(axis=1) + 1e-4))
    plain = jtet.improve(mesh, boundary=boundary, seed=0).mesh
    assert (plain.topology.edge_ids(edges) < 0).any()
    result = jtet.improve(curved, boundary=boundary, seed=0)
    out = result.mesh
    assert curved_edges_kept(curved, out).all()
    assert any(f"{len(edges)} bend a bounding surface and were never" in n for n in result.notes)
    assert len(out.protected_edges) == 0 and len(out.protected_edge_labels) == 0
    assert out.curved_edges.edges.shape == edges.shape
    # bent within the cube's faces instead (towards a corner of a boundary face holding
    # the edge): the faces cover the same planes either way, so such edges are flipped
    sides = faces[:, [[0, 1], [0, 2], [1, 2]]].reshape(-1, 2)
    holder = faces[match_rows(sides, edges, mesh.n_points) // 3]
    third = holder.sum(axis=1) - edges.sum(axis=1)
    mid = mesh.points[edges].mean(axis=1)
    flat = mesh.replace(curved_edges=(edges, mid + 0.05 * (mesh.points[third] - mid)))
    # pinned: the cube's 12 edges only, bent within one face and off the other (no flip
    # removes such an edge anyway: a subsegment)
    pinned = surface_curved_edges(flat)
    assert len(pinned) == 12 and topo.subsegment[topo.edge_ids(pinned)].all()
    out = jtet.improve(flat, boundary=boundary, seed=0).mesh
    assert not curved_edges_kept(flat, out).all()
