"""Topology against brute-force per-element references on small seeded meshes."""

import numpy as np
import pytest
from helpers import delaunay_mesh, grid_mesh, shifted

import jtet
from jtet._topology import (
    CORNER,
    FREE,
    INDEX_FIELDS,
    SEGMENT,
    SURFACE,
    Topology,
    corner_counts,
    distinct_values,
    first_of_runs,
    local_index,
    match_rows,
)


def _volume6(p):
    return np.dot(p[1] - p[0], np.cross(p[2] - p[0], p[3] - p[0]))


@pytest.mark.parametrize(
    "values",
    [
        np.zeros(0, np.int64),
        np.array([7]),
        np.random.default_rng(0).integers(0, 5, 1000),  # few labels, many copies
        np.random.default_rng(1).integers(0, 2**62, (300, 4)),  # wide keys, 2-D
        np.random.default_rng(2).permutation(5000).astype(np.int32),  # all distinct
    ],
)
def test_distinct_values_and_first_of_runs_match_numpy(values):
    """``distinct_values`` against np.unique (flattened); ``first_of_runs`` against a
    Python scan of the sorted values."""
    np.testing.assert_array_equal(distinct_values(values), np.unique(values))
    s = np.sort(values, axis=None)
    expected = [i == 0 or s[i] != s[i - 1] for i in range(len(s))]
    np.testing.assert_array_equal(first_of_runs(s), np.array(expected, bool))


def _pytetwild_mesh():
    pv = pytest.importorskip("pyvista")
    pytest.importorskip("pytetwild")
    # through jtet.tetrahedralize: fTetWild runs in a child whose working directory is a
    # temporary one (called here, it wrote __tracked_surface.stl into the checkout)
    return jtet.tetrahedralize(
        pv.Sphere(theta_resolution=12, phi_resolution=12), edge_length_fac=0.2
    )


MESHES = {
    "delaunay": lambda: delaunay_mesh(150, seed=1),
    "clustered": lambda: delaunay_mesh(150, seed=2, clustered=True),
    "grid": lambda: grid_mesh(3, perturb=0.3, seed=3),
    "pytetwild": _pytetwild_mesh,
}


@pytest.fixture(params=sorted(MESHES))
def mesh(request):
    return MESHES[request.param]()


def test_faces_and_neighbors_match_brute_force(mesh):
    T = mesh.topology
    ref = {}
    for t, tet in enumerate(mesh.tets):
        for i in range(4):
            key = tuple(sorted(np.delete(tet, i)))
            ref.setdefault(key, []).append((t, tet[i]))
    assert len(ref) == len(T.faces)
    for f, face in enumerate(T.faces):
        entries = ref[tuple(face)]
        got = {(t, a) for t, a in zip(T.face_tets[f], T.face_apex[f]) if t >= 0}
        assert got == set(entries)
        assert T.boundary_face[f] == (len(entries) == 1)
    for t in range(mesh.n_tets):
        for i in range(4):
            f = T.tet_faces[t, i]
            assert set(T.faces[f]) == set(np.delete(mesh.tets[t], i))
            nb = T.tet_neighbors[t, i]
            assert nb == (T.face_tets[f, 1] if T.face_tets[f, 0] == t else T.face_tets[f, 0])


def test_edge_rings_are_ordered_and_oriented(mesh):
    T = mesh.topology
    P = mesh.points
    ref = {}
    for t, tet in enumerate(mesh.tets):
        for i in range(4):
            for j in range(i + 1, 4):
                ref.setdefault(tuple(sorted((tet[i], tet[j]))), set()).add(t)
    assert len(ref) == len(T.edges)
    for e, (a, b) in enumerate(T.edges):
        tets = T.edge_tets[T.edge_tets_ptr[e] : T.edge_tets_ptr[e + 1]]
        ring = T.edge_ring[T.edge_ring_ptr[e] : T.edge_ring_ptr[e + 1]]
        assert set(tets) == ref[(a, b)]
        assert T.edge_manifold[e]
        k = len(tets)
        assert len(ring) == k + (1 if T.edge_boundary[e] else 0)
        for i, t in enumerate(tets):
            c, d = ring[i], ring[(i + 1) % len(ring)]
            # consecutive ring vertices share the tet with ab
            assert set(mesh.tets[t]) == {a, b, c, d}
            # counterclockwise about ab seen from a: (a, b, v_{i+1}, v_i) positive
            assert _volume6(P[[a, b, d, c]]) > 0
        if T.edge_boundary[e]:
            # an open chain runs from boundary vertex to boundary vertex
            bfaces = {tuple(f) for f in T.faces[T.boundary_face]}
            assert tuple(sorted((a, b, ring[0]))) in bfaces
            assert tuple(sorted((a, b, ring[-1]))) in bfaces


def test_grid_protection_classes():
    mesh = grid_mesh(3)
    T = mesh.topology
    on = lambda v: np.isclose(mesh.points[v], 0) | np.isclose(mesh.points[v], 1)  # noqa: E731
    n_on = on(np.arange(mesh.n_points)).sum(axis=1)
    expect = np.select([n_on == 0, n_on == 1, n_on == 2], [FREE, SURFACE, SEGMENT], CORNER)
    np.testing.assert_array_equal(T.vertex_kind, expect)
    # subsegments are exactly the edges lying on the cube's 12 edges
    e_on = on(T.edges[:, 0]) & on(T.edges[:, 1])
    np.testing.assert_array_equal(T.subsegment, e_on.sum(axis=1) >= 2)
    surf = np.flatnonzero(T.vertex_kind == SURFACE)
    n = T.surface_normal[surf]
    assert np.allclose(np.abs(n).max(axis=1), 1.0)


def test_region_interface_and_protected_entities():
    mesh = grid_mesh(2)
    c = mesh.points[mesh.tets].mean(axis=1)
    region = (c[:, 0] > 0.5).astype(int)
    T = Topology.build(mesh.replace(region=region))
    f = T.faces[T.interface_face]
    assert len(f) == 8 and np.allclose(mesh.points[f][..., 0], 0.5)
    assert T.subfacet[T.interface_face].all()
    # interface edges on the plane x = 0.5 which are not on the outer boundary are
    # removable (flat), edges where the interface meets the boundary are subsegments
    ex = np.isclose(mesh.points[T.edges][..., 0], 0.5).all(axis=1)
    inner = ex & (T.edge_n_subfacets == 2)
    assert inner.any() and not T.subsegment[inner].any()
    assert T.subsegment[ex & (T.edge_n_subfacets > 2)].all()
    # user protection
    e0 = np.flatnonzero(~T.subsegment)[0]
    prot = mesh.replace(protected_edges=T.edges[[e0]], protected_faces=T.faces[[0]])
    P = prot.topology
    assert P.subsegment[e0] and P.subfacet[0]
    with pytest.raises(jtet.MeshInputError, match="not an edge"):
        Topology.build(mesh.replace(protected_edges=[[0, mesh.n_points - 1]]))


def test_feature_angle_controls_curved_boundary():
    from jtet._predicates import orient3d

    mesh = _pytetwild_mesh()
    exact = Topology.build(mesh)
    loose = Topology.build(mesh, feature_angle=60.0)
    bnd = np.flatnonzero(exact.edge_n_subfacets == 2)
    # at feature angle 0 an edge between two boundary faces is removable only when the
    # two faces are exactly coplanar (pv.Sphere is a polyhedron: its facets are flat)
    a, b = exact.edges[bnd, 0], exact.edges[bnd, 1]
    bf = exact.faces[exact.boundary_face]
    third = {}
    for f in bf:
        for i in range(3):
            key = tuple(np.delete(f, i))
            third.setdefault(key, []).append(f[i])
    c = np.array([third[(x, y)][0] for x, y in zip(a, b)])
    d = np.array([third[(x, y)][1] for x, y in zip(a, b)])
    P = mesh.points
    coplanar = orient3d(P[a], P[b], P[c], P[d]) == 0
    np.testing.assert_array_equal(exact.subsegment[bnd], ~coplanar)
    assert (~coplanar).any()
    assert loose.subsegment[bnd].sum() < exact.subsegment[bnd].sum()


def test_nonconforming_mesh_is_rejected():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [1, 1, 1.0]])
    tets = np.array([[0, 1, 2, 3], [0, 2, 1, 4], [0, 1, 2, 5]])
    with pytest.raises(jtet.MeshInputError, match="shared by 3 tets"):
        Topology.build(jtet.TetMesh(pts, tets))


def test_face_and_edge_ids_match_match_rows(mesh):
    """Lookups by the topology's sorted keys agree with match_rows (any vertex order,
    rows that are not faces / edges give -1)."""
    T = mesh.topology
    n = mesh.n_points
    rng = np.random.default_rng(0)
    faces = rng.permuted(T.faces[rng.choice(len(T.faces), 40)], axis=1)
    rows = np.concatenate([faces, rng.integers(0, n, (40, 3))])
    assert np.array_equal(T.face_ids(rows), match_rows(T.faces, rows, n))
    assert (T.face_ids(faces) >= 0).all()
    edges = T.edges[rng.choice(len(T.edges), 40)][:, ::-1]
    pairs = np.concatenate([edges, rng.integers(0, n, (40, 2))])
    assert np.array_equal(T.edge_ids(pairs), match_rows(T.edges, pairs, n))
    assert len(T.face_ids(np.zeros((0, 3), np.int64))) == 0


def test_topology_face_conflicts_equal_face_conflicts():
    """Misoriented and duplicate pairs read from the topology equal face_conflicts'."""
    from jtet._mesh import face_conflicts, topology_face_conflicts

    mesh = delaunay_mesh(150, seed=4)
    rng = np.random.default_rng(0)
    tets = mesh.tets.copy()
    flip = rng.choice(len(tets), 12, replace=False)
    tets[flip] = tets[flip][:, [1, 0, 2, 3]]  # listed inside out: misoriented pairs
    for t in (mesh.tets, tets, np.array([[0, 1, 2, 3], [0, 1, 2, 3]])):
        m = jtet.TetMesh(mesh.points, t)
        T = Topology.build(m)
        _, mis, dup = face_conflicts(m.tets, m.n_points)
        got_mis, got_dup = topology_face_conflicts(m.tets, T)
        assert np.array_equal(got_mis, mis) and np.array_equal(got_dup, dup)
        assert len(mis) > 0 or t is not tets
    assert len(mis) == 0 and np.array_equal(dup, [[0, 1]])


def test_local_index_equals_argmax(mesh):
    rng = np.random.default_rng(0)
    t = rng.integers(0, mesh.n_tets, 500)
    v = mesh.tets[t, rng.integers(0, 4, 500)]
    want = np.argmax(mesh.tets[t] == v[:, None], axis=1)
    assert np.array_equal(local_index(mesh.tets, t, v), want)


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_build_is_the_same_on_any_number_of_threads(mesh, monkeypatch, workers):
    """The face, edge and vertex groupings run side by side on the worker threads; the
    topology must not depend on how many there are (1: one after the other; the test
    mesh is below the size where real builds use the threads)."""
    from jtet import _config, _topology

    ref = Topology.build(mesh)
    monkeypatch.setattr(_topology, "THREADED_MIN_TETS", 0)
    monkeypatch.setattr(_config, "WORKERS", workers)
    monkeypatch.setattr(_config, "_pool", None)  # a pool of the patched size
    got = Topology.build(mesh)
    for name in Topology.__dataclass_fields__:
        assert np.array_equal(getattr(got, name), getattr(ref, name)), name


@pytest.mark.parametrize("q", [10, 5000])
def test_search_sorted_and_lookup_match_numpy(q):
    """search_sorted (sorts many unsorted queries first) equals np.searchsorted, and sorted_lookup
    finds exactly the present keys, for queries with repeats, misses and both ends."""
    from jtet._topology import search_sorted, sorted_lookup

    rng = np.random.default_rng(q)
    keys = np.unique(rng.integers(0, 10**6, 20000))
    queries = np.concatenate([rng.choice(keys, q // 2), rng.integers(-5, 10**6 + 5, q - q // 2)])
    rng.shuffle(queries)
    assert np.array_equal(search_sorted(keys, queries), np.searchsorted(keys, queries))
    increasing = np.sort(queries)  # searched as they are (no second sort)
    assert np.array_equal(search_sorted(keys, increasing), np.searchsorted(keys, increasing))
    got = sorted_lookup(keys, queries)
    present = np.isin(queries, keys)
    assert np.array_equal(got >= 0, present)
    assert np.array_equal(keys[got[present]], queries[present])


@pytest.mark.parametrize("key_bits", [1, 20, 40, 45, 53, 62])
def test_stable_sort_matches_numpy_stable_argsort(key_bits):
    """Every path of ``_stable_sort`` (one packed value sort, two packed passes for keys
    up to twice as wide, argsort beyond) against NumPy's stable argsort, with many ties."""
    from jtet._topology import _stable_sort

    rng = np.random.default_rng(key_bits)
    for n in (1, 2, 1000, 70_000):
        distinct = rng.integers(0, 2**key_bits, max(n // 7, 1), dtype=np.int64)
        keys = rng.choice(distinct, n)  # ~7 entries per key: ties must keep their order
        perm, sorted_keys = _stable_sort(keys, key_bits)
        ref = np.argsort(keys, kind="stable")
        np.testing.assert_array_equal(perm, ref)
        np.testing.assert_array_equal(sorted_keys, keys[ref])


def _rings_reference(ptr, c, d, entry_tet):
    """``_order_rings`` edge by edge in plain Python: a chain starts at its only step
    without a predecessor, a cycle at its first step; anything else is non-manifold and
    keeps its order."""
    tets, rings, boundary, manifold = [], [], [], []
    for e in range(len(ptr) - 1):
        idx = list(range(ptr[e], ptr[e + 1]))
        succ = {i: [j for j in idx if c[j] == d[i]] for i in idx}
        pred = {i: [j for j in idx if d[j] == c[i]] for i in idx}
        starts = [i for i in idx if not pred[i]]
        ok = all(len(succ[i]) <= 1 and len(pred[i]) <= 1 for i in idx) and len(starts) <= 1
        order = [starts[0] if starts else idx[0]]
        while ok and len(order) < len(idx):
            nxt = succ[order[-1]]
            ok = len(nxt) == 1 and nxt[0] not in order
            order.append(nxt[0] if ok else -1)
        order = order if ok else idx
        tets += [entry_tet[i] for i in order]
        rings += [c[i] for i in order]
        if starts:  # a chain (or a broken ring with a start) gets its last vertex
            rings.append(d[order[-1]] if ok and len(starts) == 1 else -1)
        boundary.append(bool(starts))
        manifold.append(ok)
    return np.array(tets), np.array(rings), np.array(boundary), np.array(manifold)


@pytest.mark.parametrize("padded", [False, True])
@pytest.mark.parametrize("dtype", [np.int64, np.int32])
def test_order_rings_matches_a_plain_python_walk(dtype, padded, monkeypatch):
    """Random rings: cycles and chains in shuffled order, some with a corrupted step
    (non-manifold), sizes 1-13 and 255-257 (wider counters), int32 or int64 steps; one
    bucket per ring size, or all rings padded into one (few edges)."""
    from jtet import _topology
    from jtet._topology import _order_rings

    monkeypatch.setattr(_topology, "PADDED_RING_SLOTS", 10**6 if padded else 0)

    rng = np.random.default_rng(7)
    counts = np.concatenate([rng.integers(1, 14, 300), [255, 256, 257]])
    ptr = np.concatenate([[0], np.cumsum(counts)])
    c, d = np.empty(ptr[-1], np.int64), np.empty(ptr[-1], np.int64)
    for e, k in enumerate(counts):
        v = rng.permutation(k + 40)[: k + 1]
        cycle = rng.random() < 0.5
        cs, ds = v[:k], (np.roll(v[:k], -1) if cycle else v[1:])
        p = rng.permutation(k)
        c[ptr[e] : ptr[e + 1]], d[ptr[e] : ptr[e + 1]] = cs[p], ds[p]
        if rng.random() < 0.2:
            c[ptr[e] + rng.integers(k)] = rng.integers(k + 40)
    entry_tet = rng.integers(0, 10**6, ptr[-1])
    tets, ring_ptr, ring, boundary, manifold = _order_rings(
        ptr, c.astype(dtype), d.astype(dtype), entry_tet
    )
    ref_tets, ref_ring, ref_boundary, ref_manifold = _rings_reference(ptr, c, d, entry_tet)
    assert 0.5 < ref_manifold.mean() < 1 and 0 < ref_boundary.mean() < 1
    np.testing.assert_array_equal(tets, ref_tets)
    np.testing.assert_array_equal(ring, ref_ring)
    np.testing.assert_array_equal(boundary, ref_boundary)
    np.testing.assert_array_equal(manifold, ref_manifold)
    np.testing.assert_array_equal(np.diff(ring_ptr), counts + boundary)
    assert ring.dtype == np.int64


def test_match_rows_with_an_empty_table_finds_nothing():
    queries = np.array([[0, 1, 2], [2, 3, 1]])
    np.testing.assert_array_equal(match_rows(np.zeros((0, 3), np.int64), queries, 4), [-1, -1])
    assert match_rows(queries, np.zeros((0, 3), np.int64), 4).shape == (0,)


def test_corner_counts_match_a_row_sum():
    """Marked corners per tet, read as 32-bit words, against NumPy's row sum of the
    gathered mask: every count 0..4 occurs, int32 / int64 ids, non-contiguous tets, and
    no tets at all."""
    rng = np.random.default_rng(7)
    for n, p in ((1, 1.0), (6, 0.5), (1000, 0.3)):
        mask = rng.random(n) < p
        tets = rng.integers(0, n, (4000, 4))
        ref = mask[tets].sum(axis=1)
        for t in (tets, tets.astype(np.int32), np.repeat(tets, 2, axis=1)[:, ::2]):
            assert np.array_equal(corner_counts(mask, t), ref)
    assert set(np.unique(ref)) == {0, 1, 2, 3, 4}
    assert corner_counts(np.ones(5, bool), np.zeros((0, 4), np.int64)).shape == (0,)


def test_ids_are_int32_and_exact_for_vertex_ids_above_2_to_16():
    """The id and pointer fields are int32 (half the bytes of int64), and every key that
    combines vertex ids is still exact: with 70k unreferenced points first, a key a * n
    + b computed in int32 would wrap. Reference: the same mesh without those points."""
    mesh = grid_mesh(4, perturb=0.3, seed=5, two_regions=True)
    T0 = mesh.topology
    mesh = mesh.replace(protected_faces=T0.faces[[3]], protected_edges=T0.edges[[7]])
    T, off = mesh.topology, 70_000
    B = shifted(mesh, off).topology
    for name in INDEX_FIELDS:
        assert getattr(T, name).dtype == np.int32 and getattr(B, name).dtype == np.int32, name
    for name in ("faces", "edges", "edge_ring"):  # vertex ids
        np.testing.assert_array_equal(getattr(B, name), getattr(T, name) + off, name)
    np.testing.assert_array_equal(B.face_apex, np.where(T.face_apex >= 0, T.face_apex + off, -1))
    np.testing.assert_array_equal(B.vert_tets_ptr[off:], T.vert_tets_ptr)
    assert not B.vert_tets_ptr[:off].any()
    same = ("tet_faces", "face_tets", "tet_neighbors", "surface_id", "tet_edges",
            "edge_tets_ptr", "edge_tets", "edge_ring_ptr", "edge_n_subfacets", "vert_tets",
            "boundary_face", "interface_face", "subfacet", "edge_boundary", "edge_manifold",
            "subsegment")  # fmt: skip
    for name in same:
        np.testing.assert_array_equal(getattr(B, name), getattr(T, name), name)
    np.testing.assert_array_equal(B.vertex_kind[off:], T.vertex_kind)
    np.testing.assert_array_equal(B.face_ids(T.faces[::-1] + off), np.arange(len(T.faces))[::-1])
    np.testing.assert_array_equal(B.edge_ids(T.edges[::-1] + off), np.arange(len(T.edges))[::-1])


def _protected_delaunay():
    m = delaunay_mesh(120, seed=5, surface_points=20)
    T = m.topology
    interior = np.flatnonzero(~T.subsegment)[:5]
    return jtet.TetMesh(
        m.points, m.tets, protected_faces=T.faces[[2, 9, 40]], protected_edges=T.edges[interior]
    )


# Meshes whose vertices take every kind: flat facets with points on them, region
# interfaces, user protection, a curved boundary at two feature angles, points in no tet
VERTEX_KIND_MESHES = [
    lambda: delaunay_mesh(150, seed=3, surface_points=40),
    lambda: grid_mesh(4, perturb=0.3, seed=1, two_regions=True),
    _protected_delaunay,
    _pytetwild_mesh,
    lambda: _pytetwild_mesh()._with_feature_angle(60.0),
    lambda: shifted(grid_mesh(3, perturb=0.2), offset=40),  # 40 points in no tet (FREE)
]


@pytest.mark.parametrize("case", range(len(VERTEX_KIND_MESHES)))
def test_vertex_kinds_from_stars_match_the_whole_build(case):
    """``TetMesh.vertex_kinds`` without a cached topology (the stars' own topology)
    against the whole mesh's build, for random vertex sets and every vertex."""
    mesh = VERTEX_KIND_MESHES[case]()
    full = Topology.build(mesh, mesh._feature_angle).vertex_kind
    assert len(set(full.tolist())) >= 2  # free and boundary vertices at least
    rng = np.random.default_rng(case)
    some = rng.choice(mesh.n_points, 7, replace=False)
    for vids in [some, np.arange(mesh.n_points), np.zeros(0, np.int64), some[[0, 0, 1]]]:
        fresh = mesh._derive()  # same arrays and feature angle, no cached topology
        np.testing.assert_array_equal(fresh.vertex_kinds(vids), full[vids])
        assert "topology" not in fresh.__dict__  # the whole mesh was not built
