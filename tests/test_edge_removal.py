"""Edge removal passes: invariants after every pass, protection, the three edge cases."""

import numpy as np
import pytest
from helpers import delaunay_mesh, grid_mesh

import jtet
from jtet._edge_removal import edge_removal_pass
from jtet._invariants import InvariantChecker


def _edge_set(edges):
    return {tuple(e) for e in np.sort(edges, axis=1)}


def _run_passes(mesh, n_passes=6, **kw):
    checker = InvariantChecker(mesh)
    totals = {"boundary": 0, "interior": 0, "surface": 0}
    subsegs = _edge_set(mesh.topology.edges[mesh.topology.subsegment])
    for p in range(n_passes):
        q_before = mesh.quality(kw.get("measure", "min_sine")).min()
        new, stats, keep = edge_removal_pass(mesh, **kw)
        if keep is None:
            break
        checker.check(new, p, "edge")
        # worst quality never decreases; no tet created inverted
        assert new.quality(kw.get("measure", "min_sine")).min() >= q_before
        created = new.tets[keep.sum() :]
        assert (new.quality()[keep.sum() :] > 0).all() or q_before <= 0
        assert len(created) and stats.successes > 0
        # subsegments are never removed
        assert subsegs <= _edge_set(new.topology.edges)
        for k, v in stats.by_kind.items():
            totals[k] += v
        mesh = new
    return mesh, totals


@pytest.mark.parametrize("measure", sorted(jtet.MEASURES))
def test_invariants_on_random_delaunay(measure):
    mesh = delaunay_mesh(120, seed=7)
    out, totals = _run_passes(mesh, measure=measure, max_ring=7)
    assert totals["interior"] > 0
    # the worst tet may sit on the cube's corners where no edge is removable; the worst
    # tets as a whole must improve (thresholded mean, the optimizer's progress measure)
    assert (
        np.minimum(out.quality(measure), 0.3).mean() > np.minimum(mesh.quality(measure), 0.3).mean()
    )


def test_exterior_boundary_flips_keep_the_surface():
    # random points on the cube's flat faces: boundary edges there are removable (2-2)
    mesh = delaunay_mesh(100, seed=5, surface_points=60)
    _, totals = _run_passes(mesh, max_ring=8)
    assert totals["boundary"] > 0


def test_interface_flips_keep_the_interface():
    # a flat interface x = 0.5 whose points were moved within the plane: its triangles
    # are poor and 4-4 flips of interface edges improve them
    mesh = grid_mesh(4, perturb=0.9, seed=1, two_regions=True)
    assert len(np.unique(mesh.region)) == 2
    _, totals = _run_passes(mesh, n_passes=4, max_ring=7)
    assert totals["surface"] > 0


def test_clustered_points_and_large_rings():
    mesh = delaunay_mesh(150, seed=3, clustered=True)
    _run_passes(mesh, n_passes=3, max_ring=12)


def test_protected_edges_are_kept():
    mesh = delaunay_mesh(100, seed=11)
    T = mesh.topology
    # protect every edge the first pass would remove
    new, _, keep = edge_removal_pass(mesh)
    removed = _edge_set(T.edges) - _edge_set(new.topology.edges)
    prot = np.array(sorted(removed))
    pm = mesh.replace(protected_edges=prot)
    new2, stats2, _ = edge_removal_pass(pm)
    assert _edge_set(prot) <= _edge_set(new2.topology.edges)


def test_improve_edge_only_through_the_api():
    mesh = delaunay_mesh(150, seed=2)
    result = jtet.improve(mesh, ops=("edge",), check=True)
    assert result.status == "converged"
    assert result.stats_after.quality_min["min_sine"] > result.stats_before.quality_min["min_sine"]
    # the climb's edge removal passes, then perturbation rounds that kick with it only
    assert result.history and all(
        h["op"] == "edge" or (h["op"] == "perturb" and h["kick"] == "edge") for h in result.history
    )
    # the input mesh is untouched
    np.testing.assert_array_equal(mesh.tets, delaunay_mesh(150, seed=2).tets)


def test_inverted_tet_repaired_by_edge_removal():
    # three tets around edge ab with a ring point pushed across so that one tet inverts;
    # the 3-2 flip removes the inverted tet when the two new tets are positive
    a, b = np.array([0, 0, 1.0]), np.array([0, 0, -1.0])
    ring = np.array([[1, 0, 0], [-0.5, 0.8, 0], [-0.5, -0.8, 0.0]])
    pts = np.vstack([a, b, ring])
    # tets (a, b, v_{i+1}, v_i): positive for a counterclockwise ring
    tets = np.array([[0, 1, 3, 2], [0, 1, 4, 3], [0, 1, 2, 4]])
    good = jtet.TetMesh(pts, tets)
    assert (good.volumes > 0).all()
    # move a so that ab leaves the ring's triangle: one tet inverts, the flip fixes it
    pts2 = pts.copy()
    pts2[0] = [1.2, 0.0, 1.0]
    pts2[1] = [0.9, 0.0, -1.0]
    bad = jtet.TetMesh(pts2, tets)
    assert (bad.volumes < 0).sum() >= 1
    new, stats, keep = edge_removal_pass(bad)
    assert keep is not None and not keep.any()  # all three tets replaced by two
    assert new.n_tets == 2 and (new.volumes > 0).all()
    # same polyhedron: the volume is conserved (signed volumes add up)
    assert np.isclose(new.volumes.sum(), bad.volumes.sum(), rtol=1e-12)


@pytest.mark.parametrize("fraction", [0.02, 0.3, 1.0])
def test_candidates_and_worst_tet_per_edge_match_brute_force(fraction):
    """edge_candidates' dirty filter and the worst tet around each candidate edge (both
    the few-edges and the most-edges paths) against a loop over every edge's tets."""
    from jtet._edge_removal import _worst_around, edge_candidates

    mesh = delaunay_mesh(300, seed=4)
    T = mesh.topology
    rng = np.random.default_rng(4)
    dirty = rng.random(mesh.n_tets) < fraction
    q = rng.random(mesh.n_tets)
    got = edge_candidates(mesh, 7, dirty)
    everything = edge_candidates(mesh, 7, None)
    tp = T.edge_tets_ptr
    want = [e for e in everything if dirty[T.edge_tets[tp[e] : tp[e + 1]]].any()]
    assert np.array_equal(got, want)
    for edges in (got, everything):
        ref = [q[T.edge_tets[tp[e] : tp[e + 1]]].min() for e in edges]
        assert np.array_equal(_worst_around(q, T, edges), ref)
