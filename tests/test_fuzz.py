"""Fuzzing: random meshes and options through each operation and the whole optimizer.

Every case runs with the invariant checks on (``jtet._invariants.InvariantChecker``: valid,
volumes per region, boundary and interfaces, no new inverted / degenerate tets) and also
checks the promises of ``jtet.improve`` (worst quality never decreases, the input is not
modified, the status is not an invariant violation).

Case counts: ``JTET_FUZZ_CASES`` (default 1600, split over the tests by ``WEIGHTS``; these
replays are a fifth of the default test run's time, which must stay under ~10 minutes);
``JTET_FUZZ_PROFILE=long`` draws fresh random cases (CI replays a fixed derandomized set)
and defaults to 100,000 cases: ``python experiments/fuzz.py --cases 100000``. A failure
prints its ``MeshSpec``; rebuild it with ``strategies.build_mesh`` and add it to
tests/test_regressions.py as an explicit mesh.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from helpers import brute_force_interpolation
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from strategies import DAMAGE_OPS, build_mesh, mesh_specs, options

import jtet
from jtet._curved_guard import surface_curved_edges
from jtet._edge_removal import edge_removal_pass
from jtet._invariants import InvariantChecker
from jtet._point_data import moved_vertices
from jtet._quadratic import MID_EDGES, curved_edges_kept, folded_tets, quadratic_mesh
from jtet._topology import match_rows

PROFILE = os.environ.get("JTET_FUZZ_PROFILE", "ci")
TOTAL = int(os.environ.get("JTET_FUZZ_CASES", 100_000 if PROFILE == "long" else 1600))
# share of the cases each test gets
WEIGHTS = {
    "edge_pass": 0.15,
    "edge_pass_damaged": 0.15,
    "edge_pass_labels": 0.15,
    "face_pass": 0.15,
    "smooth_pass": 0.05,  # ~10x the cost of an edge pass (JIT per star capacity)
    "improve": 0.15,
    "improve_damaged": 0.10,
    "improve_regions": 0.05,
    "improve_periodic": 0.05,
    "improve_curved": 0.05,
    "improve_merged": 0.05,
    "improve_places": 0.05,
}

settings.register_profile(
    "ci",
    deadline=None,
    derandomize=True,  # CI replays the same cases; the long profile explores
    database=None,
    print_blob=True,
    suppress_health_check=list(HealthCheck),
)
settings.register_profile(
    "long", deadline=None, print_blob=True, suppress_health_check=list(HealthCheck)
)
settings.load_profile(PROFILE)


def _cases(name: str) -> settings:
    return settings(max_examples=max(1, round(TOTAL * WEIGHTS[name])))


def _bad(mesh) -> int:
    from jtet._predicates import orient3d_tets

    return int((orient3d_tets(mesh.points, mesh.tets) <= 0).sum())


def _edge_passes(spec, measure, max_ring, n_passes=2):
    mesh = build_mesh(spec)
    assume(mesh is not None)
    checker = InvariantChecker(mesh)
    T = mesh.topology
    subsegments = T.edges[T.subsegment]
    for p in range(n_passes):
        q = mesh.quality(measure)
        out, stats, keep = edge_removal_pass(mesh, measure=measure, max_ring=max_ring, quality=q)
        if keep is None:
            assert out is mesh and stats.successes == 0
            return
        checker.check(out, p, "edge")
        assert out.quality(measure).min() >= q.min()
        assert stats.successes > 0 and stats.attempts >= stats.successes
        # kept tets come first, in order
        np.testing.assert_array_equal(out.tets[: keep.sum()], mesh.tets[keep])
        # subsegments (incl. protected edges) are never removed
        e = out.topology.edges
        key = e[:, 0] * out.n_points + e[:, 1]
        assert np.isin(subsegments[:, 0] * out.n_points + subsegments[:, 1], key).all()
        mesh = out


measures = st.sampled_from(sorted(jtet.MEASURES))
rings = st.integers(3, 12)


@_cases("edge_pass")
@given(mesh_specs(damage=False, labels=False), measures, rings)
def test_edge_pass(spec, measure, max_ring):
    _edge_passes(spec, measure, max_ring)


@_cases("edge_pass_damaged")
@given(mesh_specs(damage=True), measures, rings)
def test_edge_pass_inverted_input(spec, measure, max_ring):
    _edge_passes(spec, measure, max_ring)


@_cases("edge_pass_labels")
@given(mesh_specs(labels=True), measures, rings)
def test_edge_pass_regions_and_protection(spec, measure, max_ring):
    _edge_passes(spec, measure, max_ring)


def _face_passes(spec, measure, max_faces, n_passes=2):
    from jtet._multiface import multiface_removal_pass

    mesh = build_mesh(spec)
    assume(mesh is not None)
    checker = InvariantChecker(mesh)
    for p in range(n_passes):
        q = mesh.quality(measure)
        out, stats, keep = multiface_removal_pass(
            mesh, measure=measure, max_faces=max_faces, quality=q
        )
        if keep is None:
            assert out is mesh
            return
        checker.check(out, p, "face")
        assert out.quality(measure).min() >= q.min()
        np.testing.assert_array_equal(out.tets[: keep.sum()], mesh.tets[keep])
        mesh = out


@_cases("face_pass")
@given(mesh_specs(), measures, st.sampled_from([4, 16]))
def test_face_pass(spec, measure, max_faces):
    _face_passes(spec, measure, max_faces)


@_cases("smooth_pass")
@given(mesh_specs(), measures, st.sampled_from(["fixed", "slide"]))
def test_smooth_pass(spec, measure, boundary):
    from jtet._smooth import smooth_pass

    mesh = build_mesh(spec)
    assume(mesh is not None)
    q = mesh.quality(measure)
    out, stats = smooth_pass(mesh, measure=measure, boundary=boundary)
    InvariantChecker(mesh).check(out, 0, "smooth")
    np.testing.assert_array_equal(out.tets, mesh.tets)
    assert out.quality(measure).min() >= q.min()
    moved = np.flatnonzero((out.points != mesh.points).any(axis=1))
    np.testing.assert_array_equal(np.sort(np.asarray(stats.moved)), moved)


def _signed_volumes(mesh: jtet.TetMesh) -> np.ndarray:
    p = mesh.points[mesh.tets]
    return np.linalg.det(p[:, 1:] - p[:, :1]) / 6


def _improve(spec, opts):
    mesh = build_mesh(spec)
    assume(mesh is not None)
    # a linear field of O(1) values over the mesh: what the run carries to its moved and
    # new vertices must be that field there (interpolation linear in a tet is exact)
    lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    unit = (mesh.points - lo) / np.where(hi > lo, hi - lo, 1.0)
    # and an integer cell array (the side of a plane the tets' centroids are on): the run
    # keeps the faces where it changes value, so each side keeps its volume
    side = (unit[mesh.tets].mean(axis=1) @ [1.0, 0.5, 0.0] > 0.7).astype(np.int16)
    # and a curved field, which only the tet holding a point interpolates right
    curved = np.sin(3 * unit[:, 0]) * np.exp(unit[:, 1]) + unit[:, 2] ** 2
    mesh = mesh.replace(
        point_data={"f": unit @ [1.0, -2.0, 0.5], "g": curved}, cell_data={"side": side}
    )
    tets, points = mesh.tets.copy(), mesh.points.copy()
    result = jtet.improve(mesh, opts)
    assert not result.status.startswith("invariant violation"), (spec, opts, result.status)
    assert result.status in ("converged", "max passes", "goal reached")
    # the run stops for its goals exactly when its mesh meets them
    after = result.stats_after
    goal_min, goal_max = opts.goal_min_dihedral, opts.goal_max_dihedral
    meets = (goal_min is not None or goal_max is not None) and (
        (goal_min is None or after.min_dihedral >= goal_min)
        and (goal_max is None or after.max_dihedral <= goal_max)
    )
    assert (result.status == "goal reached") == meets, (opts, result.status, after.as_dict())
    # the input is untouched; the result passes the checks against it once more
    np.testing.assert_array_equal(mesh.tets, tets)
    np.testing.assert_array_equal(mesh.points, points)
    # checked as the run checks itself: with a feature angle, bent subfacets may be
    # flipped (the surfaces keep their vertices; their shape and the volumes change)
    InvariantChecker(mesh._with_feature_angle(opts.feature_angle)).check(result.mesh, -1, "improve")
    q0, q1 = mesh.quality(opts.quality), result.mesh.quality(opts.quality)
    assert q1.min() >= q0.min()
    before, after = result.stats_before, result.stats_after
    assert after.n_inverted + after.n_degenerate <= before.n_inverted + before.n_degenerate
    assert _bad(result.mesh) <= _bad(mesh)
    climb = [h for h in result.history if h["op"] != "perturb"]
    # whole passes of the ops in their order (a goal may stop a pass after any op)
    assert [h["op"] for h in climb] == [opts.ops[i % len(opts.ops)] for i in range(len(climb))]
    if result.status != "goal reached":
        assert len(climb) == len(opts.ops) * len({h["pass"] for h in climb})
    # perturbation rounds only after a converged climb; each reports a kept or restored mesh
    rounds = [h for h in result.history if h["op"] == "perturb"]
    assert result.perturb_rounds == opts.perturb_rounds(mesh.n_tets)
    assert not rounds or result.perturb_rounds > 0
    assert len({h["round"] for h in rounds if h["successes"]}) <= result.perturb_rounds
    assert all(h["worst_quality"] >= q0.min() for h in rounds)
    # insert=False: no insertion kick, exactly the input's points
    if not opts.insert:
        assert "insert" not in {h["kick"] for h in rounds}
        assert result.mesh.n_points == mesh.n_points
    # the point data: the input's values where vertices stayed, the field elsewhere (but
    # at positions in no input tet, which the notes count: the nearest vertex's value)
    f = result.mesh.point_data["f"]
    n = mesh.n_points
    stayed = (result.mesh.points[:n] == mesh.points).all(axis=1)
    np.testing.assert_array_equal(f[:n][stayed], mesh.point_data["f"][stayed])
    if not any("lie in no tet" in note for note in result.notes):
        pts = (result.mesh.points - lo) / np.where(hi > lo, hi - lo, 1.0)
        np.testing.assert_allclose(f, pts @ [1.0, -2.0, 0.5], rtol=0, atol=1e-9)
        # where the input's tets do not overlap (none inverted or flat), the tet
        # holding a point is unique: the curved field is its interpolation there
        if before.n_inverted + before.n_degenerate == 0:
            moved = np.flatnonzero(moved_vertices(mesh, result.mesh))
            ref, weight = brute_force_interpolation(mesh, curved, result.mesh.points[moved])
            inside = weight >= 0  # not a vertex slid out of the input (feature angle)
            g = result.mesh.point_data["g"][moved]
            np.testing.assert_allclose(g[inside], ref[inside], rtol=0, atol=1e-9)
    # the cell data: one value per tet; with the boundary's and interfaces' shape kept
    # (no feature angle) and no inverted or flat input tet, each side's volume is kept to
    # rounding (sums of signed volumes: ~1e-15 relative per term)
    side_after = result.mesh.cell_data["side"]
    assert side_after.dtype == np.int16 and len(side_after) == result.mesh.n_tets
    if opts.feature_angle == 0 and before.n_inverted + before.n_degenerate == 0:
        v0, v1 = _signed_volumes(mesh), _signed_volumes(result.mesh)
        for k in (0, 1):
            assert abs(v0[side == k].sum() - v1[side_after == k].sum()) <= 1e-11 * np.abs(v0).sum()


@_cases("improve")
@given(mesh_specs(damage=False, seam=None), options())
def test_improve(spec, opts):
    _improve(spec, opts)


@_cases("improve_damaged")
@given(mesh_specs(damage=True, seam=None), options(DAMAGE_OPS))
def test_improve_inverted_input(spec, opts):
    _improve(spec, opts)


def _improve_at_any_size(module, threshold: str, spec, opts) -> None:
    """``_improve`` with ``module.threshold``, a mesh size from which a run works
    differently, at 0: the fuzz meshes are small."""
    before = getattr(module, threshold)
    setattr(module, threshold, 0)
    try:
        _improve(spec, opts)
    finally:
        setattr(module, threshold, before)


@_cases("improve_merged")
@given(mesh_specs(seam=None), options())
def test_improve_with_merged_flip_steps(spec, opts):
    # a pass after the first applies its edge and face steps together
    # (``_driver._flip_steps``): the face plans made beside edge plans meet inverted
    # tets, protection and regions too
    from jtet import _driver

    _improve_at_any_size(_driver, "MERGE_FLIP_STEPS", spec, opts)


@_cases("improve_places")
@given(mesh_specs(seam=None), options())
def test_improve_with_round_places(spec, opts):
    # a perturbation round runs the ladder per place of its submesh
    # (``_perturb.places``): rounds with several places meet inverted tets, protection,
    # regions and curved edges too
    from jtet import _perturb

    _improve_at_any_size(_perturb, "PLACES_MIN_TETS", spec, opts)


@_cases("improve_regions")
@given(mesh_specs(labels=True), options(), st.data())
def test_improve_some_regions(spec, opts, data):
    # Options.regions: the unselected tets, their vertices and the faces they share with
    # the selected ones stay exactly; the whole result passes the run's checks
    mesh = build_mesh(spec)
    assume(mesh is not None)
    labels = np.unique(mesh.region).tolist()
    chosen = data.draw(st.lists(st.sampled_from(labels), min_size=1, unique=True))
    if _bad(mesh) and len(chosen) < len(labels):  # a part of a mesh with inverted tets
        with pytest.raises(jtet.MeshInputError, match="inverted or degenerate"):
            jtet.improve(mesh, opts.replace(regions=chosen))
        return
    result = jtet.improve(mesh, opts.replace(regions=chosen))
    assert not result.status.startswith("invariant violation"), (spec, opts, result.status)
    frozen = ~np.isin(mesh.region, chosen)
    k = int(frozen.sum())
    out = result.mesh
    np.testing.assert_array_equal(out.tets[:k], mesh.tets[frozen])
    verts = np.unique(mesh.tets[frozen])
    np.testing.assert_array_equal(out.points[verts], mesh.points[verts])
    assert np.isin(out.region[k:], chosen).all()
    InvariantChecker(mesh._with_feature_angle(opts.feature_angle)).check(out, -1, "regions")
    assert out.quality(opts.quality).min() >= mesh.quality(opts.quality).min()
    assert _bad(out) <= _bad(mesh)


@_cases("improve_periodic")
@given(mesh_specs(), options(), st.data())
def test_improve_keeps_periodic_vertices_and_boundary_edges(spec, opts, data):
    # periodic links (TetMesh.periodic) on random boundary vertices: none of them moves,
    # every boundary edge between two of them stays, the links come back unchanged
    mesh = build_mesh(spec)
    assume(mesh is not None)
    T = mesh.topology
    boundary = np.unique(T.faces[T.boundary_face])
    assume(len(boundary) >= 4)
    k = data.draw(st.integers(2, len(boundary) // 2 * 2))
    seed = data.draw(st.integers(0, 2**32 - 1))
    chosen = np.random.default_rng(seed).choice(boundary, k - k % 2, replace=False)
    linked = mesh.replace(periodic=[(2, (2, 1), None, chosen.reshape(-1, 2))])
    on = np.zeros(mesh.n_points, bool)
    on[chosen] = True
    kept = T.edges[T.edge_boundary & on[T.edges].all(axis=1)]
    result = jtet.improve(linked, opts)
    assert not result.status.startswith("invariant violation"), (spec, opts, result.status)
    out = result.mesh
    np.testing.assert_array_equal(out.points[chosen], mesh.points[chosen])
    T2 = out.topology
    edges = {tuple(e) for e in np.sort(T2.edges[T2.edge_boundary], axis=1).tolist()}
    assert {tuple(e) for e in np.sort(kept, axis=1).tolist()} <= edges
    assert len(out.periodic) == 1 and np.array_equal(out.periodic[0].pairs, chosen.reshape(-1, 2))
    np.testing.assert_array_equal(out.protected_vertices, mesh.protected_vertices)
    np.testing.assert_array_equal(out.protected_edges, mesh.protected_edges)


@_cases("improve_curved")
@given(mesh_specs(), options(), st.data())
def test_improve_guards_curved_tets(spec, opts, data):
    # random edges bent by a random fraction of their length (TetMesh.curved_edges): the
    # quadratic output's curved tets end no worse than min(floor, the input's worst)
    mesh = build_mesh(spec)
    assume(mesh is not None)
    edges = np.unique(np.sort(mesh.tets[:, MID_EDGES[4]].reshape(-1, 2), axis=1), axis=0)
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    edges = edges[rng.random(len(edges)) < data.draw(st.sampled_from([0.2, 0.5, 1.0]))]
    assume(len(edges) > 0)
    ends = mesh.points[edges]
    length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    bend = data.draw(st.sampled_from([0.01, 0.05, 0.2]))
    mids = ends.mean(axis=1) + rng.normal(size=(len(edges), 3)) * (bend * length)[:, None]
    floor = data.draw(st.sampled_from([0.0, 0.3, 0.6, 1.0]))
    bent = mesh.replace(curved_edges=(edges, mids))
    result = jtet.improve(bent, opts.replace(min_scaled_jacobian=floor))
    assert not result.status.startswith("invariant violation"), (spec, opts, result.status)
    # the ratios are quotients of float64 determinants: the same up to round-off
    (_, before), (_, after) = (folded_tets(quadratic_mesh(m)) for m in (bent, result.mesh))
    assert after >= min(floor, before) - 1e-9, (spec, opts, floor, before, after)
    # the curved edges bending a bounding surface all come out with their nodes, and the
    # run's pins on them do not stay protected
    pinned = match_rows(bent.curved_edges.edges, surface_curved_edges(bent), bent.n_points)
    assert curved_edges_kept(bent, result.mesh)[pinned].all(), (spec, opts)
    np.testing.assert_array_equal(result.mesh.protected_edges, bent.protected_edges)
