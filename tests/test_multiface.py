"""Multi-face removal: the tree DP against brute force, special cases, invariants per pass.

The objective we compare (and why it is TESTNEIGHBOR's): let G' be the tree of faces the
search visits (sandwiched between a and b, joined by open degree-four edges, passing the
reflex test) and S a subtree of G' containing the root. Removing S deletes the 2|S| tets of
its faces and creates one tet (a, b, v, u) per boundary edge u -> v of S. Define

    F(S) = min( quality of the created tets, quality of the tets of G' \\ S (kept) ),

the worst tet of the region G' after the removal (tets outside G' are untouched). For a
leaf g whose parent goes, TESTNEIGHBOR removes g iff q_new > q_old or q_new > q_uw, i.e.
iff q_new > min(q_old, q_uw) = the F-value of keeping g; by induction over the tree its
choice G'' maximizes F over all subtrees S (ties allowed: several S may reach the maximum).
Independently, the root's test q_new > q_old succeeds iff SOME subtree S has
q_new(S) > q_old(S). Both statements are checked here by enumerating every subtree, first on
random trees with random qualities (the DP alone), then on meshes (the whole search).
"""

import itertools
from collections import defaultdict

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import delaunay_mesh, grid_mesh

import jtet
from jtet._edge_removal import edge_removal_pass
from jtet._invariants import InvariantChecker
from jtet._kernels.multiface import tree_dp
from jtet._multiface import (
    build_forest,
    candidate_faces,
    find_roots,
    multiface_removal_pass,
    solve_forest,
)
from jtet._quality import tet_quality
from jtet._topology import Topology

# ---------------------------------------------------------------------------------------
# Brute force on abstract trees (random qualities): the DP alone


def _random_tree(rng, n):
    """Random tree of n faces in BFS order: parent, parent slot, children per slot."""
    parent, pslot = [-1], [0]
    child = [[-1, -1, -1]]
    free = [(0, 0), (0, 1), (0, 2)]
    for i in range(1, n):
        p, s = free.pop(int(rng.integers(len(free))))
        parent.append(p)
        pslot.append(s)
        child[p][s] = i
        child.append([-1, -1, -1])
        free += [(i, 0), (i, 1)]
    # BFS order: renumber by depth so parents precede children (they already do: a
    # parent is created before its children)
    return np.array(parent), np.array(pslot), np.array(child)


def _subtrees(parent):
    """Every subtree containing node 0, as sets of node ids."""
    n = len(parent)
    for bits in itertools.product([False, True], repeat=n - 1):
        s = {0} | {i + 1 for i, keep in enumerate(bits) if keep}
        if all(parent[i] in s for i in s if i):
            yield s


def _evaluate(s, child, qs, qt):
    """(q_new, q_old, F) of removing the subtree s (abstract tree)."""
    created = []
    for i in s:
        for slot in (0, 1, 2) if i == 0 else (0, 1):
            c = child[i][slot]
            if c < 0 or c not in s:
                created.append(qs[i][slot])
    removed = [qt[i] for i in s]
    kept = [qt[i] for i in range(len(qt)) if i not in s]
    q_new, q_old = min(created), min(removed)
    return q_new, q_old, min([q_new] + kept)


def test_tree_dp_maximizes_the_region_minimum_on_random_trees():
    rng = np.random.default_rng(0)
    N, B = 8, 400
    batch = {k: [] for k in ("qs", "qt", "parent", "pslot", "child", "valid")}
    trees = []
    for _ in range(B):
        n = int(rng.integers(1, N + 1))
        parent, pslot, child = _random_tree(rng, n)
        # rounded qualities: many ties, the hard case for "optimal up to ties"
        qs = rng.random((n, 3)).round(1)
        qt = rng.random(n).round(1)
        trees.append((n, parent, child, qs, qt))
        pad = N - n
        batch["qs"].append(np.pad(qs, ((0, pad), (0, 0))))
        batch["qt"].append(np.pad(qt, (0, pad)))
        batch["parent"].append(np.pad(np.maximum(parent, 0), (0, pad)))
        batch["pslot"].append(np.pad(pslot, (0, pad)))
        batch["child"].append(np.pad(child, ((0, pad), (0, 0)), constant_values=-1))
        batch["valid"].append(np.arange(N) < n)
    args = [jnp.asarray(np.stack(batch[k])) for k in batch]
    q_old, q_new, chosen = jax.jit(jax.vmap(tree_dp))(*args)
    q_old, q_new, chosen = np.asarray(q_old), np.asarray(q_new), np.asarray(chosen)
    n_success = 0
    for t, (_n, parent, child, qs, qt) in enumerate(trees):
        got = set(np.flatnonzero(chosen[t]).tolist())
        assert got in list(_subtrees(parent))  # a subtree containing the root
        qn, qo, f = _evaluate(got, child, qs, qt)
        assert (qn, qo) == (q_new[t], q_old[t])  # the reported values are the set's
        options = [_evaluate(s, child, qs, qt) for s in _subtrees(parent)]
        assert f == max(o[2] for o in options)
        exists = any(o[0] > o[1] for o in options)
        assert (q_new[t] > q_old[t]) == exists
        n_success += exists
    assert 0 < n_success < B


# ---------------------------------------------------------------------------------------
# Brute force on meshes: the whole search (sandwiched faces, degree-four edges, reflex test)


def _sign(p0, p1, p2, p3):
    return np.sign(np.linalg.det(np.array([p1 - p0, p2 - p0, p3 - p0])))


class _MeshFacts:
    """Plain-Python adjacency of a small mesh, independent of jtet's topology code."""

    def __init__(self, mesh):
        self.mesh = mesh
        self.P = mesh.points
        self.tet_of = {frozenset(t): i for i, t in enumerate(mesh.tets.tolist())}
        self.face_count = defaultdict(int)
        self.edge_tets = defaultdict(list)
        for i, t in enumerate(mesh.tets.tolist()):
            for f in itertools.combinations(t, 3):
                self.face_count[frozenset(f)] += 1
            for e in itertools.combinations(t, 2):
                self.edge_tets[frozenset(e)].append(i)

    def ccw_from(self, face, a):
        u, v, w = sorted(face)
        P = self.P
        return (u, v, w) if _sign(P[u], P[v], P[w], P[a]) > 0 else (u, w, v)

    def search(self, a, b, root):
        """G' from root: (faces in BFS order, parent index per face)."""
        P = self.P

        def sandwiched(f):
            return (f | {a}) in self.tet_of and (f | {b}) in self.tet_of

        def open_edge(e):
            ts = self.edge_tets[e]
            others = {x for t in ts for x in self.mesh.tets[t]} - e
            return len(ts) == 4 and all(self.face_count[e | {x}] == 2 for x in others)

        def admissible(f):
            y = self.ccw_from(f, a)
            return sum(_sign(P[a], P[b], P[y[(k + 1) % 3]], P[y[k]]) > 0 for k in range(3)) >= 2

        faces, parent = [root], [-1]
        seen = {root}
        head = 0
        while head < len(faces):
            f = faces[head]
            for e in map(frozenset, itertools.combinations(f, 2)):
                if not open_edge(e):
                    continue
                around = {x for t in self.edge_tets[e] for x in self.mesh.tets[t].tolist()}
                for x in around - e - f - {a, b}:
                    g = e | {x}
                    if not sandwiched(g) or not admissible(g):
                        continue
                    assert g not in seen or g == faces[parent[head]], "G' has a cycle"
                    if g not in seen:
                        seen.add(g)
                        faces.append(g)
                        parent.append(head)
            head += 1
        return faces, parent

    def best(self, a, b, faces, parent, measure):
        """Max F and whether some subtree improves, plus F of any given subtree."""
        q = self.mesh.quality(measure)
        qt = [min(q[self.tet_of[f | {a}]], q[self.tet_of[f | {b}]]) for f in faces]
        orient = [self.ccw_from(f, a) for f in faces]
        # every directed edge of every face may bound a subtree: evaluate them at once
        slots = [(i, k) for i in range(len(faces)) for k in range(3)]
        new = np.array([[a, b, orient[i][(k + 1) % 3], orient[i][k]] for i, k in slots])
        qn = dict(zip(slots, tet_quality(self.P, new, measure), strict=True))
        edge_owner = {(orient[i][k], orient[i][(k + 1) % 3]): i for i, k in slots}

        def evaluate(s):
            created = [
                qn[(i, k)]
                for i in s
                for k in range(3)
                if edge_owner.get((orient[i][(k + 1) % 3], orient[i][k])) not in s
            ]
            kept = [qt[i] for i in range(len(faces)) if i not in s]
            q_new, q_old = min(created), min(qt[i] for i in s)
            assert len(created) == len(s) + 2  # the ring of an m-face removal: m + 2
            return q_new, q_old, min([q_new] + kept)

        options = [evaluate(s) for s in _subtrees(parent)]
        return max(o[2] for o in options), any(o[0] > o[1] for o in options), evaluate


def _check_against_brute_force(mesh, measure="min_sine", max_nodes=9):
    T = mesh.topology
    q = mesh.quality(measure)
    faces = candidate_faces(mesh, q, None)
    a, b, root = find_roots(mesh, faces)
    has = root >= 0
    a, b, root = a[has], b[has], root[has]
    forest = build_forest(mesh, a, b, root, q, 16)
    q_old, q_new, chosen = solve_forest(mesh, forest, q, measure)
    facts = _MeshFacts(mesh)
    checked = successes = 0
    for t in np.flatnonzero(~forest.bad & (forest.count <= max_nodes)):
        A, B = int(a[t]), int(b[t])
        g_faces, g_parent = facts.search(A, B, frozenset(T.faces[root[t]].tolist()))
        ours = [frozenset(f) for f in T.faces[forest.face[t, : forest.count[t]]].tolist()]
        assert set(ours) == set(g_faces)  # the same tree G'
        best_f, exists, evaluate = facts.best(A, B, g_faces, g_parent, measure)
        pick = {g_faces.index(ours[i]) for i in np.flatnonzero(chosen[t])}
        qn, qo, f = evaluate(pick)
        assert np.isclose(qn, q_new[t], rtol=0, atol=1e-12)
        assert np.isclose(qo, q_old[t], rtol=0, atol=1e-12)
        assert f >= best_f - 1e-12  # optimal (ties allowed)
        assert (q_new[t] > q_old[t]) == exists
        checked += 1
        successes += exists
    return checked, successes


def _bipyramid(rng, m, jitter=0.2):
    """A random triangulated polygon v_1..v_m around segment ab, coned to a and to b.

    2(m - 2) tets; the m - 2 triangles are the faces sandwiched between a and b. The
    polygon is convex in projection; a and b are shifted sideways so that ab crosses a
    random triangle (or misses the polygon) and the reflex test prunes some faces.
    """
    for _ in range(1000):
        gaps = rng.uniform(0.5, 1.5, m)
        ang = np.cumsum(gaps) / gaps.sum() * 2 * np.pi
        r = rng.uniform(1 - jitter, 1 + jitter, m)
        ring = np.column_stack(
            [r * np.cos(ang), r * np.sin(ang), rng.uniform(-jitter, jitter, m) / 2]
        )
        xy = ring[:, :2]
        d1 = np.roll(xy, -1, 0) - xy
        d2 = np.roll(xy, -2, 0) - np.roll(xy, -1, 0)
        if (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] <= 0).any():
            continue  # not convex
        a = np.r_[rng.uniform(-0.6, 0.6, 2), rng.uniform(0.3, 1.2)]
        b = np.r_[rng.uniform(-0.6, 0.6, 2), -rng.uniform(0.3, 1.2)]
        tris, stack = [], [(0, m - 1)]
        while stack:  # a random triangulation: split (i, j) at a random k
            i, j = stack.pop()
            if j - i >= 2:
                k = int(rng.integers(i + 1, j))
                tris.append((i, k, j))
                stack += [(i, k), (k, j)]
        pts = np.vstack([a, b, ring])
        tets = []
        for i, k, j in tris:  # ring indices + 2; jtet's ring convention
            tets += [[i + 2, k + 2, j + 2, 0], [i + 2, j + 2, k + 2, 1]]
        mesh = jtet.TetMesh(pts, np.array(tets))
        if (mesh.volumes > 1e-3 / m**3).all() and mesh.is_valid().conforming:
            return mesh
    raise AssertionError("no valid bipyramid found")


def test_bipyramids_against_brute_force():
    rng = np.random.default_rng(4)
    checked = successes = 0
    for trial in range(24):
        mesh = _bipyramid(rng, int(rng.integers(4, 10)))
        c, s = _check_against_brute_force(mesh, "min_sine" if trial % 2 else "radius_ratio")
        checked += c
        successes += s
    assert checked > 50 and successes > 5


@pytest.mark.parametrize("seed", [0, 1])
def test_delaunay_trees_against_brute_force(seed):
    mesh = delaunay_mesh(70, seed=seed)
    checked, successes = _check_against_brute_force(mesh)
    assert checked > 100 and successes > 10


def test_walk_finds_the_same_roots_as_the_full_star_search():
    for mesh in (delaunay_mesh(150, seed=9, clustered=True), grid_mesh(4, perturb=0.8)):
        faces = candidate_faces(mesh, mesh.quality(), None)
        walked = find_roots(mesh, faces, walk=True)[2]
        searched = find_roots(mesh, faces, walk=False)[2]
        np.testing.assert_array_equal(walked, searched)
        assert (walked >= 0).sum() > 0.3 * len(faces)


# ---------------------------------------------------------------------------------------
# Special cases


def _oriented_set(tets):
    """Tets as a set of (sorted vertices, orientation parity) for comparing meshes."""
    from jtet._topology import _perm_parity

    order = np.argsort(tets, axis=1)
    return {(tuple(np.sort(t)), int(p)) for t, p in zip(tets, _perm_parity(order), strict=True)}


def test_two_three_flip_is_one_face_removal():
    u, v, w = [1.0, 0, 0], [-0.5, 0.866, 0], [-0.5, -0.866, 0]
    a, b = [0.05, 0.02, 0.3], [-0.03, 0.04, -0.3]
    mesh = jtet.TetMesh(np.array([a, b, u, v, w]), np.array([[2, 3, 4, 0], [2, 4, 3, 1]]))
    new, stats, keep = multiface_removal_pass(mesh)
    assert stats.by_size == {1: 1} and not keep.any()
    # u, v, w counterclockwise seen from a: the new tets are (a, b, v, u), (a, b, w, v), ...
    assert _oriented_set(new.tets) == _oriented_set(
        np.array([[0, 1, 3, 2], [0, 1, 4, 3], [0, 1, 2, 4]])
    )
    assert (new.volumes > 0).all()
    assert np.isclose(new.volumes.sum(), mesh.volumes.sum(), rtol=1e-13)
    assert new.quality().min() > mesh.quality().max()


def test_four_four_flip_is_both_edge_and_two_face_removal():
    # octahedron around a long edge uw with ring (a, x, b, v): diagonal ab is the best
    pts = np.array(
        [[-1, 0.02, 0], [1, 0, 0.01], [0.03, 0.05, 0.5], [0, 0.8, 0.03], [0.02, 0, -0.5],
         [0.01, -0.8, 0]]
    )  # fmt: skip
    ring = [2, 3, 4, 5]
    tets = np.array([[0, 1, ring[(i + 1) % 4], ring[i]] for i in range(4)])
    mesh = jtet.TetMesh(pts, tets)
    if (mesh.volumes < 0).any():
        mesh = jtet.TetMesh(pts, tets[:, [1, 0, 2, 3]])
    assert (mesh.volumes > 0).all()
    by_edge, s_edge, _ = edge_removal_pass(mesh)
    by_face, s_face, _ = multiface_removal_pass(mesh)
    assert s_edge.by_size == {4: 1} and s_face.by_size == {2: 1}
    assert _oriented_set(by_edge.tets) == _oriented_set(by_face.tets)
    assert {tuple(e) for e in by_face.topology.edges} >= {(2, 4)}  # the new edge ab


def test_overflow_truncates_and_stays_valid():
    # a polygon of 22 vertices: up to 20 sandwiched faces, more than the capacity 16
    rng = np.random.default_rng(1)
    for _ in range(20):
        mesh = _bipyramid(rng, 22, jitter=0.0)
        new, stats, keep = multiface_removal_pass(mesh, max_faces=16)
        if stats.overflow:
            break
    assert stats.overflow >= 1
    if keep is not None:
        InvariantChecker(mesh).check(new, 0, "face")


def test_protected_edges_stop_the_search():
    # a protected edge (subsegment) is never removed: with every edge protected, only
    # single faces (2-3 flips, which remove no edge) may go
    mesh = delaunay_mesh(120, seed=7)
    _, stats, _ = multiface_removal_pass(mesh)
    assert max(stats.by_size) > 1
    locked = mesh.replace(protected_edges=mesh.topology.edges)
    new, stats2, keep = multiface_removal_pass(locked)
    assert stats2.successes > 0 and set(stats2.by_size) == {1}
    edges = {tuple(e) for e in new.topology.edges}
    assert {tuple(e) for e in mesh.topology.edges} <= edges


def test_dirty_restricts_candidates_and_inverted_tets_are_skipped():
    mesh = delaunay_mesh(80, seed=3)
    none = np.zeros(mesh.n_tets, bool)
    new, stats, keep = multiface_removal_pass(mesh, dirty=none)
    assert keep is None and stats.attempts == 0
    # claim every tet is inverted: multi-face removal assumes none and tries nothing
    q = -np.ones(mesh.n_tets)
    _, stats2, keep2 = multiface_removal_pass(mesh, quality=q)
    assert keep2 is None and stats2.attempts == 0


# ---------------------------------------------------------------------------------------
# Invariants after every pass


def _run_passes(mesh, measure, n_passes=4):
    checker = InvariantChecker(mesh)
    total = 0
    for p in range(n_passes):
        q = mesh.quality(measure)
        new, stats, keep = multiface_removal_pass(mesh, measure=measure)
        if keep is None:
            break
        checker.check(new, p, "face")
        q_new = new.quality(measure)
        assert q_new.min() >= q.min()  # never worse
        created = q_new[keep.sum() :]
        assert (created > 0).all()  # nothing inverted
        # k faces removed: 2k tets out, k + 2 in
        k = np.array([s for s, c in stats.by_size.items() for _ in range(c)])
        assert (~keep).sum() == 2 * k.sum() and len(created) == (k + 2).sum()
        total += stats.successes
        mesh = new
    return mesh, total


@pytest.mark.parametrize(
    "make, measure",
    [
        (lambda: delaunay_mesh(150, seed=7), "min_sine"),
        (lambda: delaunay_mesh(120, seed=8, clustered=True), "radius_ratio"),
        (lambda: grid_mesh(4, perturb=0.7, seed=2), "mean_ratio"),
        (lambda: grid_mesh(4, perturb=0.9, seed=1, two_regions=True), "min_sine"),
        (lambda: delaunay_mesh(100, seed=5, surface_points=40), "min_sine"),
    ],
)
def test_invariants_after_every_pass(make, measure):
    mesh = make()
    _, total = _run_passes(mesh, measure)
    assert total > 0


@pytest.mark.parametrize("ops", [("face",), ("edge", "face")])
def test_improve_with_face_removal(ops):
    mesh = delaunay_mesh(120, seed=2)
    result = jtet.improve(mesh, ops=ops, check=True, max_passes=6)
    assert result.stats_after.quality_min["min_sine"] >= result.stats_before.quality_min["min_sine"]
    face = [h for h in result.history if h["op"] == "face"]
    assert face and sum(h["successes"] for h in face) > 0


@pytest.mark.parametrize("fraction", [0.02, 0.5])
def test_candidate_faces_dirty_filter_matches_a_scan_of_every_face(fraction):
    """candidate_faces with a dirty mask: the candidates without one, restricted to the
    faces one of whose two tets is dirty (the old whole-mesh formulation)."""
    mesh = delaunay_mesh(300, seed=8)
    rng = np.random.default_rng(8)
    q = mesh.quality()
    dirty = rng.random(mesh.n_tets) < fraction
    ft = mesh.topology.face_tets
    touches = dirty[ft[:, 0]] | ((ft[:, 1] >= 0) & dirty[np.maximum(ft[:, 1], 0)])
    T = mesh.topology
    ok = (ft[:, 1] >= 0) & ~T.subfacet & touches
    f = np.flatnonzero(ok)
    f = f[np.argsort(np.minimum(q[ft[f, 0]], q[ft[f, 1]]), kind="stable")]
    a, b = T.face_apex[f, 0], T.face_apex[f, 1]
    _, first = np.unique(np.minimum(a, b) * mesh.n_points + np.maximum(a, b), return_index=True)
    assert np.array_equal(candidate_faces(mesh, q, dirty), f[np.sort(first)])


# ---------------------------------------------------------------------------------------
# A face plan made beside an edge plan of the same mesh (``prior``), applied together


def test_face_plans_beside_edge_plans():
    """Seeded random meshes: the face plan leaves the edge plan's tets alone, and both
    applied at once make a valid mesh whose carried topology is a full build's."""
    from jtet._apply import apply_plans
    from jtet._edge_removal import plan_edge_removal
    from jtet._multiface import plan_multiface_removal

    overlapped = face_wins = 0
    for seed in range(8):
        mesh = delaunay_mesh(150, seed=seed, surface_points=20)
        q = mesh.quality()
        edge_plan, _ = plan_edge_removal(mesh, quality=q)
        alone, _ = plan_multiface_removal(mesh, quality=q)
        face_plan, stats = plan_multiface_removal(mesh, quality=q, prior=edge_plan)
        assert edge_plan is not None and alone is not None
        overlapped += bool((alone.remove & edge_plan.remove).any())
        face_wins += stats.successes
        plans = [edge_plan] if face_plan is None else [edge_plan, face_plan]
        assert face_plan is None or not (face_plan.remove & edge_plan.remove).any()
        out, keep = apply_plans(mesh, [edge_plan, face_plan])
        remove = np.logical_or.reduce([p.remove for p in plans])
        assert np.array_equal(keep, ~remove)
        expected = np.concatenate([mesh.tets[keep], *(p.new_tets for p in plans)])
        assert np.array_equal(out.tets, expected)
        # conforming, volumes and boundary kept (the checker builds the topology anew)
        InvariantChecker(mesh).check(out, 0, "edge+face")
        # neither plan lowers the worst tet it touches, so the whole mesh's worst stays
        assert out.quality().min() >= q.min()
        # the topology carried through the update is the one a full build gives
        assert "topology" in out.__dict__  # derived from the plans' mesh, not built
        fresh = Topology.build(out)
        for name in ("faces", "tet_neighbors", "edges", "edge_ring", "vert_tets"):
            assert np.array_equal(getattr(out.topology, name), getattr(fresh, name))
    # the plans chosen apart claim common tets on these meshes: ``prior`` had work to
    # do, and the face plans still found winners beside the edge plans
    assert overlapped >= 4 and face_wins > 0


def test_face_plan_conforms_with_the_prior_plans_new_tets():
    # a prior plan that creates a tet some face winner would create too: together they
    # would put that tet's faces in two tets on one side, so that winner must go
    from jtet._apply import FlipPlan
    from jtet._multiface import plan_multiface_removal

    mesh = delaunay_mesh(150, seed=2)
    alone, _ = plan_multiface_removal(mesh)
    twin = alone.new_tets[:1]
    prior = FlipPlan(np.zeros(mesh.n_tets, bool), twin, mesh.region[:1])
    plan, _ = plan_multiface_removal(mesh, prior=prior)
    as_sets = {tuple(t) for t in np.sort(plan.new_tets, axis=1)}
    assert tuple(np.sort(twin[0])) not in as_sets
    assert len(plan.new_tets) > 0  # the other winners stay
