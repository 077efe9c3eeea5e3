"""check_validity: valid meshes pass, every hand-made defect is found with the right count.

Counts on random meshes are also compared with a brute-force reference written with Python
loops and dictionaries (small meshes only).
"""

import itertools
from collections import Counter, defaultdict
from types import SimpleNamespace

import numpy as np
import pytest
from helpers import delaunay_mesh, grid_mesh, orient_positive

import jtet
from jtet._validity import ValidityReport, check_validity, raise_if_invalid


def face_tets(tets):
    """Brute force: sorted face triple -> list of tets containing it."""
    out = defaultdict(list)
    for t, tet in enumerate(tets.tolist()):
        for f in itertools.combinations(sorted(tet), 3):
            out[f].append(t)
    return out


def interior_tet(mesh):
    """A tet all four of whose faces are shared with another tet."""
    ft = face_tets(mesh.tets)
    for t, tet in enumerate(mesh.tets.tolist()):
        if all(len(ft[f]) == 2 for f in itertools.combinations(sorted(tet), 3)):
            return t
    raise AssertionError("no interior tet")


def merged(*parts):
    """Union of (points, tets) parts with coincident points merged."""
    pts = np.concatenate([p for p, _ in parts])
    offs = np.cumsum([0] + [len(p) for p, _ in parts[:-1]])
    tets = np.concatenate([t + o for (_, t), o in zip(parts, offs, strict=True)])
    uniq, inv = np.unique(np.round(pts, 12), axis=0, return_inverse=True)
    return uniq, inv.reshape(-1)[tets]


def assert_only(report, **counts):
    """The given counts, and zero for every other problem."""
    for count, _, _ in ValidityReport._PROBLEMS:
        assert getattr(report, count) == counts.get(count, 0), (count, str(report))


# ------------------------------------------------------------------ valid meshes


@pytest.mark.parametrize(
    "mesh",
    [
        pytest.param(lambda: delaunay_mesh(300, seed=1), id="delaunay"),
        pytest.param(lambda: delaunay_mesh(200, seed=2, surface_points=40), id="flat-boundary"),
        pytest.param(lambda: grid_mesh(3, perturb=0.3), id="grid"),
        pytest.param(lambda: jtet.demo_mesh("demo"), id="demo-with-hole"),
        pytest.param(lambda: jtet.demo_mesh("two_regions"), id="two-regions"),
    ],
)
def test_valid_meshes_are_ok(mesh):
    mesh = mesh()
    r = check_validity(mesh)
    assert r.ok and bool(r) and r.conforming and r.manifold and r.topologically_ok, str(r)
    assert_only(r)
    assert r.orientation_exact
    assert r.n_tets == mesh.n_tets and r.n_points == mesh.n_points
    assert mesh.is_valid().ok
    assert str(r).startswith("valid mesh")
    raise_if_invalid(r, "unused")  # does not raise


def test_boundary_and_interface_counts():
    mesh = grid_mesh(2)  # 2 x 2 x 2 cubes of 6 tets: 6 faces x 4 squares x 2 triangles
    r = check_validity(mesh)
    assert r.n_boundary_faces == 48 and r.n_interface_faces == 0
    x = mesh.points[mesh.tets].mean(axis=1)[:, 0]
    r = check_validity(mesh.replace(region=(x > 0.5).astype(int)))
    assert r.ok and r.n_interface_faces == 8  # the plane x = 0.5: 4 squares
    # checkerboard of cubes: interfaces meet 4 at a time along interior edges, still closed
    c = np.floor(mesh.points[mesh.tets].mean(axis=1) * 2).astype(int).sum(axis=1) % 2
    r = check_validity(mesh.replace(region=c))
    assert r.ok and r.n_interface_faces == 3 * 4 * 2
    assert check_validity(jtet.demo_mesh("two_regions")).n_interface_faces > 0


# ------------------------------------------------------------------ defects


@pytest.fixture(scope="module")
def base():
    return delaunay_mesh(150, seed=3)


def test_duplicate_tet(base):
    m = base.n_tets
    tets = np.concatenate([base.tets, base.tets[[5]][:, [1, 2, 0, 3]]])  # same set, reordered
    r = check_validity(jtet.TetMesh(base.points, tets))
    assert r.n_duplicate_tets == 1 and r.duplicate_tets == ((5, m),)
    assert not r.ok and not r.conforming


def test_three_copies_and_a_tet_sharing_three_vertices(base):
    # copies in any vertex order and orientation are one group; a tet that shares the
    # face opposite the largest vertex but not that vertex is not a copy
    m, n = base.n_tets, base.n_points
    i = int(np.flatnonzero(base.tets.max(axis=1) < n - 2)[0])
    t = base.tets[i]
    # the same three smallest vertices and a larger fourth: the face opposite the
    # largest vertex is the same, the tet is not
    twin_face = np.sort(t)[:3].tolist() + [n - 1]
    extra = np.array([t[[3, 2, 1, 0]], t[[2, 0, 1, 3]], twin_face])
    r = check_validity(jtet.TetMesh(base.points, np.concatenate([base.tets, extra])))
    assert r.n_duplicate_tets == 2 and r.duplicate_tets == ((i, m), (i, m + 1))


def test_face_shared_by_three_tets(base):
    ft = face_tets(base.tets)
    face = next(f for f, ts in ft.items() if len(ts) == 2)
    pts = np.vstack([base.points, [[3.0, 3.0, 3.0]]])
    new = orient_positive(pts, np.array([[*face, len(pts) - 1]]))
    r = check_validity(jtet.TetMesh(pts, np.concatenate([base.tets, new])))
    assert r.n_overshared_faces == 1 and r.overshared_faces == (face,)
    assert not r.conforming and not r.ok
    assert r.n_inverted == 0


def test_flipped_tet(base):
    t = interior_tet(base)
    tets = base.tets.copy()
    tets[t] = tets[t][[1, 0, 2, 3]]
    r = check_validity(jtet.TetMesh(base.points, tets))
    assert_only(r, n_inverted=1, n_misoriented_faces=4)
    assert r.inverted_tets == (t,)
    assert all(t in pair for pair in r.misoriented_faces)
    assert not r.ok and not r.conforming


def test_overlapping_tets_same_side_of_a_face():
    # both tets positively oriented, both apexes above the face abc: they overlap
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 1], [0.3, 0.1, 0.5]])
    r = check_validity(jtet.TetMesh(pts, [[0, 1, 2, 3], [0, 1, 2, 4]]))
    assert r.n_inverted == 0 and r.n_degenerate == 0
    assert r.n_misoriented_faces == 1 and r.misoriented_faces == ((0, 1),)
    assert not r.ok
    # the apex on the other side: a valid bipyramid
    pts[4, 2] = -0.5
    r = check_validity(jtet.TetMesh(pts, [[0, 1, 2, 3], [1, 0, 2, 4]]))
    assert r.ok, str(r)


def test_degenerate_tet():
    # a tet (0,1,2,3) cut from face 012's centroid 4, plus the flat tet (0,1,2,4) on the face
    pts = np.array([[0.0, 0, 0], [3, 0, 0], [0, 3, 0], [0, 0, 3], [1, 1, 0]])
    side = orient_positive(pts, np.array([[0, 1, 4, 3], [1, 2, 4, 3], [2, 0, 4, 3]]))
    reports = [
        check_validity(jtet.TetMesh(pts, np.vstack([side, flat])))
        for flat in ([0, 1, 2, 4], [1, 0, 2, 4])
    ]
    good = [r for r in reports if r.conforming]
    assert len(good) == 1  # exactly one orientation of the flat tet fits its neighbours
    (r,) = good
    assert_only(r, n_degenerate=1)
    assert r.degenerate_tets == (3,) and r.topologically_ok and not r.ok
    assert r.n_boundary_faces == 4


def test_repeated_vertex():
    # TetMesh refuses such tets; check_validity also takes plain arrays
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    r = check_validity(SimpleNamespace(points=pts, tets=np.array([[0, 1, 2, 3], [0, 1, 1, 2]])))
    assert r.n_repeated_vertex_tets == 1 and r.repeated_vertex_tets == (1,)
    assert not r.ok


def test_unreferenced_point_is_only_reported(base):
    pts = np.vstack([base.points, [[0.5, 0.5, 2.0]]])
    r = check_validity(jtet.TetMesh(pts, base.tets))
    assert r.ok and r.n_unreferenced_points == 1
    assert r.unreferenced_points == (len(pts) - 1,)
    assert "unreferenced" in str(r)


def _coincident_brute_force(points, tets):
    """(first, other) for every used point whose coordinates an earlier used one has."""
    first, pairs = {}, []
    for i in sorted(set(tets.reshape(-1).tolist())):
        key = tuple(float(x) + 0.0 for x in points[i])  # -0.0 and 0.0: one key
        if key in first:
            pairs.append((first[key], i))
        else:
            first[key] = i
    return np.array(pairs, np.int64).reshape(-1, 2)


@pytest.mark.parametrize("seed", range(4))
def test_coincident_points_against_brute_force(seed):
    from jtet._validity import coincident_points

    rng = np.random.default_rng(seed)
    # coordinates on a coarse lattice: many equal x, y or z, some equal rows
    points = rng.integers(0, 4, (300, 3)).astype(float) / 3
    points[rng.random(300) < 0.1, 1] *= -1.0  # -0.0 where y is 0
    tets = rng.integers(0, 300, (40, 4))  # a fifth or so of the points unused
    expected = _coincident_brute_force(points, tets)
    assert len(expected) > 10
    np.testing.assert_array_equal(coincident_points(points, tets), expected)
    # distinct points: none, whatever their hash mixes do
    cloud = rng.random((500, 3))
    assert coincident_points(cloud, np.arange(500).reshape(-1, 4)).shape == (0, 2)


def test_coincident_points_are_only_reported():
    # two unit cubes side by side, not merged: the 4 points of the face between them
    # are there twice, and each cube is a valid mesh of its own
    (pa, ta), (pb, tb) = _cube([0.0, 0, 0]), _cube([1.0, 0, 0])
    r = check_validity(jtet.TetMesh(np.vstack([pa, pb]), np.vstack([ta, tb + len(pa)])))
    assert r.ok and r.n_coincident_points == 4
    x1 = np.flatnonzero(pa[:, 0] == 1.0)
    assert sorted(r.coincident_points) == [(int(i), int(i) - 4 + len(pa)) for i in x1]
    assert "(note: 4 point(s) at the same coordinates as another point of the tets" in str(r)


def _cube(shift):
    g = grid_mesh(1)
    return g.points + shift, g.tets


def test_two_cubes_sharing_an_edge():
    pts, tets = merged(_cube([0, 0, 0]), _cube([1, 1, 0]))
    r = check_validity(jtet.TetMesh(pts, tets))
    (edge,) = r.nonmanifold_edges
    assert r.n_nonmanifold_edges == 1 and r.n_nonmanifold_vertices == 0
    assert np.allclose(pts[list(edge)][:, :2], 1.0)  # the edge x = y = 1
    assert r.conforming and not r.manifold and not r.ok


def test_two_cubes_sharing_a_vertex():
    pts, tets = merged(_cube([0, 0, 0]), _cube([1, 1, 1]))
    r = check_validity(jtet.TetMesh(pts, tets))
    assert r.n_nonmanifold_edges == 0 and r.n_nonmanifold_vertices == 1
    (v,) = r.nonmanifold_vertices
    assert np.allclose(pts[v], 1.0)
    assert r.conforming and not r.manifold and not r.ok
    assert "more than one fan" in str(r)


def test_missing_protected_entities(base):
    ft = face_tets(base.tets)
    face = next(iter(ft))
    # a triangle of three mesh vertices that is not a face (nor are some of its edges)
    nonface = next(f for f in itertools.combinations(range(base.n_points), 3) if f not in ft)
    r = check_validity(base.replace(protected_faces=[face, nonface]))
    assert r.n_missing_protected_faces == 1 and r.missing_protected_faces == (nonface,)
    edges = {e for f in ft for e in itertools.combinations(f, 2)}
    nonedge = next(e for e in itertools.combinations(range(base.n_points), 2) if e not in edges)
    r = check_validity(base.replace(protected_edges=[face[:2], nonedge]))
    assert r.n_missing_protected_edges == 1 and r.missing_protected_edges == (nonedge,)
    assert r.topologically_ok is False


def test_raise_if_invalid_and_baseline(base):
    tets = base.tets.copy()
    # move a vertex through its opposite face: inverted but combinatorially consistent
    t = interior_tet(base)
    pts = base.points.copy()
    a, b, c, d = tets[t]
    n = np.cross(pts[b] - pts[a], pts[c] - pts[a])
    pts[d] -= 1.05 * np.dot(pts[d] - pts[a], n) / (n @ n) * n  # 5 % beyond the plane abc
    bad = jtet.TetMesh(pts, tets)
    r = check_validity(bad)
    assert r.n_inverted >= 1 and r.topologically_ok and not r.ok
    with pytest.raises(jtet.InvariantError, match="after pass 3"):
        raise_if_invalid(r, "after pass 3")
    raise_if_invalid(r, "same as input", baseline=r)  # no NEW inverted tets: fine
    fewer = check_validity(base)
    with pytest.raises(jtet.InvariantError, match="inverted"):
        raise_if_invalid(r, "pass", baseline=fewer)


def test_report_as_dict_is_json_friendly(base):
    import json

    d = check_validity(base).as_dict()
    assert d["ok"] is True and json.loads(json.dumps(d))["n_tets"] == base.n_tets


# ------------------------------------------------------------------ brute-force reference


def brute_force(points, tets):
    """Counts by Python loops: overshared / misoriented faces, boundary edges and fans."""
    ft = defaultdict(list)
    for t, tet in enumerate(tets.tolist()):
        for f in ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)):
            tri = tuple(tet[i] for i in f)
            # orientation parity of the triple relative to its sorted order
            inv = sum(tri[i] > tri[j] for i, j in ((0, 1), (0, 2), (1, 2))) % 2
            ft[tuple(sorted(tri))].append((t, inv, tri))
    over = sum(len(v) > 2 for v in ft.values())
    mis = sum(len(v) == 2 and v[0][1] == v[1][1] for v in ft.values())
    bfaces = [v[0][2] for v in ft.values() if len(v) == 1]
    ecount = Counter(tuple(sorted(e)) for f in bfaces for e in itertools.combinations(f, 2))
    bad_edges = {e for e, c in ecount.items() if c != 2}
    # fans: union-find over the boundary faces at each vertex, joined across manifold edges
    pinched = 0
    at = defaultdict(list)
    for i, f in enumerate(bfaces):
        for v in f:
            at[v].append(i)
    for v, fs in at.items():
        if any(v in e for e in bad_edges):
            continue
        parent = {i: i for i in fs}

        def find(i, parent=parent):
            while parent[i] != i:
                i = parent[i]
            return i

        for i, j in itertools.combinations(fs, 2):
            shared = set(bfaces[i]) & set(bfaces[j])
            if len(shared) == 2 and tuple(sorted(shared)) not in bad_edges:
                parent[find(i)] = find(j)
        pinched += len({find(i) for i in fs}) > 1
    return dict(
        n_overshared_faces=over,
        n_misoriented_faces=mis,
        n_boundary_faces=len(bfaces),
        n_nonmanifold_edges=len(bad_edges),
        n_nonmanifold_vertices=pinched,
    )


@pytest.mark.parametrize("seed", range(4))
def test_counts_match_brute_force_on_damaged_meshes(seed):
    """Delete, duplicate and flip random tets; compare every topological count."""
    rng = np.random.default_rng(seed)
    mesh = delaunay_mesh(60, seed=seed)
    tets = mesh.tets[rng.random(mesh.n_tets) > 0.15]  # holes: pinched vertices, bad edges
    extra = tets[rng.choice(len(tets), 3)][:, [1, 0, 2, 3]]  # flipped copies: overshared
    flip = rng.choice(len(tets), 2)
    tets = tets.copy()
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    tets = np.concatenate([tets, extra])
    r = check_validity(jtet.TetMesh(mesh.points, tets))
    ref = brute_force(mesh.points, tets)
    got = {k: getattr(r, k) for k in ref}
    assert got == ref
    assert r.n_duplicate_tets == 3 - (len({tuple(sorted(t)) for t in extra}) < 3)


@pytest.mark.parametrize("seed", range(6))
def test_component_roots_match_scipy(seed):
    # against scipy's connected components: the same partition, labelled by the
    # smallest node of each component; paths and cycles (as the fans of a boundary
    # vertex), random graphs, self loops, repeated edges, isolated nodes, no edge at all
    import scipy.sparse
    import scipy.sparse.csgraph

    from jtet._validity import component_roots

    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400))
    perm = rng.permutation(n)  # paths and cycles over shuffled ids
    cuts = np.sort(rng.choice(np.arange(1, n), size=min(n - 1, 10), replace=False)) if n > 1 else []
    src, dst = [], []
    for part in np.split(perm, cuts):
        src.append(part[:-1])
        dst.append(part[1:])
        if len(part) > 2 and rng.random() < 0.5:  # close it into a cycle
            src.append(part[-1:])
            dst.append(part[:1])
    k = int(rng.integers(0, n // 4 + 1)) if seed % 2 else 0  # random extra edges
    src.append(rng.integers(0, n, k))
    dst.append(rng.integers(0, n, k))
    src, dst = np.concatenate(src).astype(np.int64), np.concatenate(dst).astype(np.int64)
    if seed == 0:
        src, dst = src[:0], dst[:0]
    roots = component_roots(n, src, dst)
    graph = scipy.sparse.coo_matrix((np.ones(len(src)), (src, dst)), shape=(n, n))
    _, labels = scipy.sparse.csgraph.connected_components(graph, directed=False)
    smallest = np.full(labels.max() + 1, n)
    np.minimum.at(smallest, labels, np.arange(n))
    assert np.array_equal(roots, smallest[labels])
