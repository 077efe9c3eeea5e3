"""Incremental topology (jtet._topology_update) against a from-scratch Topology.build.

Every field must be identical (values, shape, dtype) after real edge-removal and
multi-face steps (boundary 2-2, interface 4-4, swapped user-protected faces, inverted
input) and after synthetic changes: tets removed and re-added in another order, holes,
random 2-3 flips with random regions and protected faces.
"""

import dataclasses

import numpy as np
import pytest
from helpers import delaunay_mesh, grid_mesh, orient_positive, shifted
from scipy.spatial import Delaunay

import jtet
import jtet._topology_update as U
from jtet._apply import replace_tets
from jtet._edge_removal import edge_removal_pass
from jtet._errors import MeshInputError
from jtet._multiface import multiface_removal_pass
from jtet._topology import CORNER, Topology


def assert_same(got: Topology, want: Topology):
    for f in dataclasses.fields(Topology):
        a, b = getattr(got, f.name), getattr(want, f.name)
        assert a.dtype == b.dtype and a.shape == b.shape, f.name
        assert np.array_equal(a, b), f.name


def direct_updates(T, old_mesh, new_mesh, keep):
    """``U._update`` with the local recomputation of edge protection and vertex kinds
    forced, then the global one (the size switch picks either on real meshes); the first
    with the update's parts one after the other, the second on the worker threads (the
    test meshes are below the size where real runs use them)."""
    out = []
    for fraction, threaded in ((1.0, 10**9), (0.0, 0)):
        saved = U.LOCAL_FRACTION, U.UPDATE_THREADED_MIN_TETS
        U.LOCAL_FRACTION, U.UPDATE_THREADED_MIN_TETS = fraction, threaded
        try:
            angle = new_mesh._feature_angle
            out.append(U._update(T, old_mesh, new_mesh, np.asarray(keep, bool), angle))
        finally:
            U.LOCAL_FRACTION, U.UPDATE_THREADED_MIN_TETS = saved
    return out


def check_step(old_mesh, new_mesh, keep):
    """The incremental path itself (no size fallback) and the public entry point."""
    want = Topology.build(new_mesh, new_mesh._feature_angle)
    for direct in direct_updates(old_mesh.topology, old_mesh, new_mesh, keep):
        assert direct is not None
        assert_same(direct, want)
        # the key caches the update installs equal the build's own keys
        assert np.array_equal(direct.face_keys, want.face_keys)
        assert np.array_equal(direct.edge_keys, want.edge_keys)
    assert_same(U.update_topology(old_mesh.topology, old_mesh, new_mesh, keep), want)


def run_passes(mesh, n_passes=3, **kw):
    """Alternate edge removal and multi-face removal, checking every step; returns the
    number of steps that changed the mesh."""
    steps = 0
    for _ in range(n_passes):
        for p in (edge_removal_pass, multiface_removal_pass):
            out, _, keep = p(mesh, **({"max_ring": 8} if p is edge_removal_pass else {}), **kw)
            if keep is None:
                continue
            check_step(mesh, out, keep)
            # replace_tets installed the incremental topology on the new mesh
            assert "topology" in out.__dict__ or (~keep).sum() + out.n_tets - keep.sum() > (
                U.max_change(len(keep)) * len(keep)
            )
            steps += 1
            mesh = out
    return steps


def ball_mesh(seed: int) -> jtet.TetMesh:
    """Delaunay mesh of random points in the unit ball and on its sphere: a convex hull
    whose faces meet at small bends (feature angles)."""
    rng = np.random.default_rng(seed)
    sphere = rng.standard_normal((80, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    inside = rng.standard_normal((80, 3)) * 0.3
    pts = np.vstack([sphere, inside])
    tets = orient_positive(pts, Delaunay(pts).simplices.astype(np.int64))
    p = pts[tets]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    return jtet.TetMesh(pts, tets[vol > 1e-12])


def flat_protected_mesh():
    """One region with user-protected faces on the flat plane x = 0.5 (4-4 flips there
    swap protected faces in replace_tets)."""
    m = grid_mesh(4, perturb=0.9, seed=1, two_regions=True)
    T = m.topology
    on_plane = (m.points[T.faces, 0] == 0.5).all(axis=1) & ~T.boundary_face
    return jtet.TetMesh(m.points, m.tets, None, T.faces[on_plane])


@pytest.mark.parametrize(
    "make",
    [
        lambda: delaunay_mesh(100, seed=5, surface_points=60),  # boundary 2-2 flips
        lambda: grid_mesh(4, perturb=0.9, seed=1, two_regions=True),  # interface 4-4 flips
        flat_protected_mesh,
        lambda: delaunay_mesh(150, seed=3, clustered=True),
        # bent boundary faces are flipped too: every step's topology keeps the angle
        lambda: ball_mesh(seed=2)._with_feature_angle(30.0),
        # vertex ids above 2**16: keys of two ids must not wrap in the int32 topology
        lambda: shifted(delaunay_mesh(100, seed=5, surface_points=60)),
        lambda: shifted(flat_protected_mesh()),
    ],
    ids=[
        "boundary",
        "interface",
        "protected",
        "clustered",
        "feature-angle",
        "boundary-shifted",
        "protected-shifted",
    ],
)
def test_real_passes(make):
    assert run_passes(make()) > 0


def test_protected_faces_swapped():
    mesh = flat_protected_mesh()
    before = {tuple(f) for f in mesh.protected_faces}
    run_passes(mesh, n_passes=1)
    out, _, keep = edge_removal_pass(mesh, max_ring=8)
    assert {tuple(f) for f in out.protected_faces} != before  # the case is exercised
    check_step(mesh, out, keep)


@pytest.mark.parametrize("moved", [1, 0])
def test_protected_face_labels_changed_in_place(moved):
    """The protected faces relabelled (two labels meeting on the plane), one face
    unprotected and one boundary face newly protected, in a step that moves one tet to
    the end, or changes no tet at all: the borders between labels become subsegments,
    as a full build finds them."""
    mesh = flat_protected_mesh()
    pf = mesh.protected_faces
    half = mesh.points[pf].mean(axis=1)[:, 1] < 0.5
    T = mesh.topology
    extra = np.sort(T.faces[T.boundary_face][:1], axis=1)
    for faces, labels in (
        (pf, np.where(half, 4, 9)),
        (np.concatenate([pf[1:], extra]), np.concatenate([np.where(half, 4, 9)[1:], [4]])),
    ):
        keep = np.ones(mesh.n_tets, bool)
        keep[:moved] = False
        new = mesh.replace(
            tets=np.concatenate([mesh.tets[moved:], mesh.tets[:moved]]),
            protected_faces=faces,
            protected_face_labels=labels,
        )
        check_step(mesh, new, keep)
        assert new.topology.subsegment.sum() > T.subsegment.sum()  # the label border


@pytest.mark.parametrize("make", [lambda: ball_mesh(3), flat_protected_mesh])
def test_step_that_changes_nothing(make):
    """A step that removes and adds no tet (once an IndexError in the ring ordering of
    the empty set of redone edges) gives the old topology's equal."""
    mesh = make()
    check_step(mesh, mesh.replace(), np.ones(mesh.n_tets, bool))


def test_protected_vertices_are_corners_after_an_update():
    """Protected interior vertices are corners (never moved) in the build and after
    incremental updates whose changed tets hold them; a step that changes the protected
    vertices takes the full build."""
    mesh = ball_mesh(5)
    T = mesh.topology
    pinned = np.flatnonzero(T.vertex_kind == 0)[::3]
    mesh = mesh.replace(protected_vertices=pinned)
    assert (mesh.topology.vertex_kind[pinned] == CORNER).all()
    assert (mesh.topology.surface_normal[pinned] == 0).all()
    steps = run_passes(mesh)  # every step is checked against a full build
    assert steps > 0
    keep = np.ones(mesh.n_tets, bool)
    fewer = mesh.replace(protected_vertices=pinned[1:])
    assert not U._compatible(mesh.topology, mesh, fewer, keep, False)
    topo = U.update_topology(mesh.topology, mesh, fewer, keep)
    assert_same(topo, Topology.build(fewer, fewer._feature_angle))


def test_inverted_input():
    # three tets around an edge, one inverted; the 3-2 flip replaces them all
    pts = np.array([[1.2, 0, 1.0], [0.9, 0, -1.0], [1, 0, 0], [-0.5, 0.8, 0], [-0.5, -0.8, 0.0]])
    bad = jtet.TetMesh(pts, np.array([[0, 1, 3, 2], [0, 1, 4, 3], [0, 1, 2, 4]]))
    out, _, keep = edge_removal_pass(bad)
    check_step(bad, out, keep)
    # a bigger mesh with a few inverted tets: pushed interior vertices
    mesh = delaunay_mesh(200, seed=7)
    T = mesh.topology
    rng = np.random.default_rng(0)
    free = np.flatnonzero(T.vertex_kind == 0)
    pts = mesh.points.copy()
    pts[rng.choice(free, 6, replace=False)] += rng.normal(0, 0.08, (6, 3))
    inv = jtet.TetMesh(pts, mesh.tets)
    assert (inv.volumes < 0).any()
    out, _, keep = edge_removal_pass(inv)
    check_step(inv, out, keep)


# ------------------------------------------------------------------ synthetic changes
def random_labels(mesh, rng):
    """The mesh with random regions (labels include -1) and random protected faces."""
    region = rng.choice([-1, 0, 3], mesh.n_tets, p=[0.1, 0.8, 0.1])
    faces = mesh.topology.faces
    pf = faces[rng.choice(len(faces), len(faces) // 50, replace=False)]
    return jtet.TetMesh(mesh.points, mesh.tets, region, pf, mesh.topology.edges[:3])


def replaced(mesh, remove, new_tets, new_region):
    """replace_tets, keeping user-protected faces that are still faces of the result."""
    out, _ = replace_tets(mesh, remove, new_tets, new_region)
    faces = {
        tuple(f)
        for f in np.sort(out.tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]], 2).reshape(
            -1, 3
        )
    }
    pf = np.array([f for f in out.protected_faces if tuple(f) in faces]).reshape(-1, 3)
    return out.replace(protected_faces=pf)


@pytest.mark.parametrize("seed", range(4))
def test_reinsert_shuffled(seed):
    """Removed tets come back in another order with rotated vertices: renumbered slots."""
    rng = np.random.default_rng(seed)
    mesh = random_labels(delaunay_mesh(200, seed=seed, surface_points=20), rng)
    remove = rng.random(mesh.n_tets) < 0.1
    back = rng.permutation(np.flatnonzero(remove))
    tets = mesh.tets[back][:, [2, 3, 0, 1]]  # an even permutation: same orientation
    out, _ = replace_tets(mesh, remove, tets, mesh.region[back])
    check_step(mesh, out, ~remove)


@pytest.mark.parametrize("seed", range(4))
def test_holes(seed):
    """Tets removed and nothing added: faces and edges disappear, boundary grows,
    edges may become non-manifold."""
    rng = np.random.default_rng(seed)
    mesh = random_labels(delaunay_mesh(200, seed=seed), rng)
    remove = rng.random(mesh.n_tets) < 0.08
    out = replaced(mesh, remove, np.zeros((0, 4), np.int64), np.zeros(0, np.int64))
    check_step(mesh, out, ~remove)


@pytest.mark.parametrize("seed", range(6))
def test_random_23_flips(seed):
    """2-3 flips of random independent interior faces (some inverted, some making a
    non-conforming mesh: then the update defers to the full build, which raises)."""
    rng = np.random.default_rng(seed)
    mesh = random_labels(delaunay_mesh(150, seed=seed, clustered=seed % 2 == 1), rng)
    T = mesh.topology
    inner = rng.permutation(np.flatnonzero(T.face_tets[:, 1] >= 0))
    ft = T.face_tets[inner]
    # independent faces: no tet used twice (first use wins)
    first = np.zeros(mesh.n_tets, bool)
    order = np.unique(ft.reshape(-1), return_index=True)[1]
    first[ft.reshape(-1)[order]] = True
    used = np.zeros(len(ft) * 2, bool)
    used[order] = True
    pick = used.reshape(-1, 2).all(axis=1)
    faces, ft, apex = T.faces[inner[pick]], ft[pick], T.face_apex[inner[pick]]
    if seed % 2 == 0:  # keep flips whose new edge de is not an edge yet: a conforming result
        de = np.sort(apex, axis=1)
        fresh = (
            U._lookup(
                T.edges[:, 0] * mesh.n_points + T.edges[:, 1], de[:, 0] * mesh.n_points + de[:, 1]
            )
            < 0
        )
        fresh &= np.isin(np.arange(len(de)), np.unique(de, axis=0, return_index=True)[1])
        faces, ft, apex = faces[fresh], ft[fresh], apex[fresh]
    faces, ft, apex = faces[:20], ft[:20], apex[:20]
    a, b, c = faces.T
    d, e = apex.T
    new = np.concatenate([np.stack(t, 1) for t in ([a, b, d, e], [b, c, d, e], [c, a, d, e])])
    vol = jtet.TetMesh(mesh.points, new).volumes
    new = np.where((vol < 0)[:, None], new[:, [1, 0, 2, 3]], new)
    remove = np.zeros(mesh.n_tets, bool)
    remove[ft.reshape(-1)] = True
    region = rng.choice([0, 3], len(new))
    out = replaced(mesh, remove, new, region)
    try:
        want = Topology.build(out)
    except MeshInputError:
        assert direct_updates(T, mesh, out, ~remove) == [None, None]
        assert U.update_topology(T, mesh, out, ~remove, fallback=False) is None
        assert seed % 2 == 1
        return
    for got in direct_updates(T, mesh, out, ~remove):
        assert_same(got, want)


def test_fallbacks():
    mesh = delaunay_mesh(150, seed=1)
    T = mesh.topology
    keep = np.ones(mesh.n_tets, bool)
    keep[:5] = False
    out, _ = replace_tets(mesh, ~keep, mesh.tets[:5], mesh.region[:5])
    # not "kept tets first": the update must not be used
    shuffled = jtet.TetMesh(out.points, out.tets[::-1])
    assert U.update_topology(T, mesh, shuffled, keep, fallback=False) is None
    assert_same(U.update_topology(T, mesh, shuffled, keep), Topology.build(shuffled))
    # a large change falls back
    big = np.zeros(mesh.n_tets, bool)
    out2, _ = replace_tets(mesh, ~big, mesh.tets, mesh.region)
    assert U.update_topology(T, mesh, out2, big, fallback=False) is None
    # half of the tets changed: built on a small mesh, updated on a large one (the
    # threshold lowered to this mesh's size)
    half = np.arange(mesh.n_tets) >= mesh.n_tets // 4
    out3, _ = replace_tets(mesh, ~half, mesh.tets[~half], mesh.region[~half])
    assert U.update_topology(T, mesh, out3, half, fallback=False) is None
    saved = U.LARGE_MESH_TETS
    U.LARGE_MESH_TETS = mesh.n_tets
    try:
        assert_same(U.update_topology(T, mesh, out3, half, fallback=False), Topology.build(out3))
    finally:
        U.LARGE_MESH_TETS = saved
    # a protected face that is no longer a face: the full build reports it
    t, i = np.argwhere(T.tet_neighbors < 0)[0]  # a tet with a boundary face: remove both
    gone = T.faces[T.tet_faces[t, i]][None]
    keep0 = np.arange(mesh.n_tets) != t
    holed = jtet.TetMesh(mesh.points, mesh.tets[keep0], None, gone)
    assert U.update_topology(T, mesh, holed, keep0, fallback=False) is None
    with pytest.raises(MeshInputError):
        U.update_topology(T, mesh, holed, keep0)


@pytest.mark.slow
def test_demo_mesh_passes():
    assert run_passes(jtet.demo_mesh(), n_passes=3) > 0


def test_replace_tets_checks_the_new_tets():
    """replace_tets trusts the kept tets (rows of a checked mesh) and checks the new
    ones with the constructor's errors; its mesh equals the constructor's."""
    mesh = random_labels(delaunay_mesh(100, seed=1), np.random.default_rng(1))
    remove = np.zeros(mesh.n_tets, bool)
    remove[:3] = True
    start = mesh.n_tets - 3
    bad = mesh.tets[:3].copy()
    bad[1, 2] = bad[1, 0]
    with pytest.raises(MeshInputError, match=f"tet {start + 1} repeats a vertex"):
        replace_tets(mesh, remove, bad, mesh.region[:3])
    bad[1, 2] = mesh.n_points
    with pytest.raises(MeshInputError, match=f"tet {start + 1} has vertex indices"):
        replace_tets(mesh, remove, bad, mesh.region[:3])
    out, k = replace_tets(mesh, remove, mesh.tets[:3], mesh.region[:3])
    assert k == start
    ref = jtet.TetMesh(out.points, out.tets, out.region, out.protected_faces, out.protected_edges)
    for f in dataclasses.fields(jtet.TetMesh):
        a, b = getattr(out, f.name), getattr(ref, f.name)
        # mappings and tuples
        if f.name in ("label_names", "periodic", "node_sets", "point_data", "cell_data"):
            assert a == b
            continue
        if f.name == "curved_edges":  # a pair of arrays
            assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
            continue
        assert a.dtype == b.dtype and np.array_equal(a, b) and not a.flags.writeable, f.name
    # replace(): the replaced fields are checked, and what depends on them
    pts = mesh.points.copy()
    pts[0, 1] = np.nan
    with pytest.raises(MeshInputError, match="NaN or infinite"):
        mesh.replace(points=pts)
    with pytest.raises(MeshInputError, match="out of range"):
        mesh.replace(points=mesh.points[:-1])
    with pytest.raises(MeshInputError, match="one label per tet"):
        mesh.replace(tets=mesh.tets[:-1])
    moved = mesh.replace(points=mesh.points + 1.0)
    assert moved.tets is mesh.tets and np.array_equal(moved.points, mesh.points + 1.0)


def test_derive_with_appended_points_checks_only_the_new_tets():
    """Appending points keeps the trusted rows valid (the splice of a perturbation round
    and a 1-4 split append vertices): the new rows are still checked with the
    constructor's errors, and fewer points check every row again."""
    mesh = delaunay_mesh(100, seed=2)
    n, m = mesh.n_points, mesh.n_tets
    points = np.vstack([mesh.points, mesh.points[mesh.tets[:2]].mean(axis=1)])
    new = np.array([[n, *mesh.tets[0, 1:]], [n + 1, n + 1, *mesh.tets[1, 2:]]])
    tets = np.vstack([mesh.tets, new])
    with pytest.raises(MeshInputError, match=f"tet {m + 1} repeats a vertex"):
        mesh._derive(points=points, tets=tets, tets_checked=m)
    new[1, 1] = n + 2
    with pytest.raises(MeshInputError, match=f"tet {m + 1} has vertex indices"):
        mesh._derive(points=points, tets=np.vstack([mesh.tets, new]), tets_checked=m)
    new[1, 1] = mesh.tets[1, 1]
    region = np.concatenate([mesh.region, mesh.region[:2]])
    out = mesh._derive(
        points=points, tets=np.vstack([mesh.tets, new]), region=region, tets_checked=m
    )
    assert out.n_points == n + 2 and np.array_equal(out.tets[m:], new)
    # more points, same tets: nothing to check, the tets are reused
    assert mesh.replace(points=points).tets is mesh.tets
    # fewer points: the trusted rows are checked again
    with pytest.raises(MeshInputError, match="out of range"):
        mesh._derive(points=mesh.points[:-1], tets=mesh.tets, tets_checked=m)


def test_ids_are_narrow_only_when_every_id_fits():
    """The renumbering maps and the topology's id fields are int32 (half the bytes)
    exactly when every id and -1 fit (the fields' types are checked field by field in
    the tests above and in test_topology)."""
    from jtet._topology import index_dtype

    top = np.iinfo(np.int32).max
    assert index_dtype(10) is np.int32
    assert index_dtype(top - 1) is np.int32
    assert index_dtype(top) is np.int64
    assert index_dtype(2**31) is np.int64
    ids = np.arange(top - 3, top, dtype=np.int64)
    assert np.array_equal(ids.astype(index_dtype(top - 1)), ids)  # no wrap-around below the cut
