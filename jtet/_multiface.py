"""One batched pass of optimal multi-face removal (Shewchuk, Section 3).

gather -> face trees (host BFS, vectorized across all trees) -> tree DP kernel (JAX, one
compiled kernel per tree capacity) -> select -> apply.

For a candidate face f with apexes a and b, MULTIFACEREMOVAL (Figure 13) roots the search at
the first face g crossed by segment ab (a face sandwiched between a and b, i.e. whose two tets
are ``(g, a)`` and ``(g, b)``), so the faces removed need not include f. From g the search
visits the sandwiched faces reachable through edges of degree four (Figure 11, line 15: an
interior edge in exactly four tets, on no bounding curve or surface), rejecting faces whose
removal would create an inverted tet (lines 18-21: fewer than two of the three tets
``(a, b, edge)`` positive, Figure 10). The visited faces form the tree ``G'``; the kernel
(``jtet._kernels.multiface``) picks the optimal subtree ``G''``. Removing the k faces of
``G''`` replaces its ``2k`` tets by the ``k + 2`` tets ``(a, b, v_{i+1}, v_i)`` around the
new edge ab, for the ring ``v_1 .. v_{k+2}`` bounding ``G''`` (counterclockwise seen from a).

Orientation: jtet's ``orient3d(a, b, c, d)`` is positive for a correctly oriented (VTK) tet
and is the NEGATIVE of the paper's ORIENT3D. The paper's test ``j_uv = ORIENT3D(a, b, u, v)
> 0`` (u, v counterclockwise seen from a) therefore reads ``orient3d(a, b, v, u) > 0`` here:
exactly "the new tet (a, b, v, u) is positive".
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from . import _config
from ._aot import cached_call, prefetch
from ._apply import FlipPlan, apply_plans, nonconforming_owners, recreating_owners
from ._curved_guard import worse_owners
from ._edge_removal import PassStats, _segments
from ._kernels.multiface import solve_trees
from ._mesh import TetMesh
from ._predicates import (
    CROSS_INTERIOR,
    CROSS_NONE,
    orient3d_stacked,
    orient3d_tets,
    segment_crosses_triangle,
)
from ._select import select_conflict_free
from ._topology import _perm_parity, local_index

__all__ = [
    "Forest",
    "build_forest",
    "find_roots",
    "multiface_removal_pass",
    "plan_multiface_removal",
    "solve_forest",
]

# Face opposite local vertex i of a positive tet, ordered (u, v, w) so that (u, v, w, p_i)
# is an even permutation of (p0, p1, p2, p3): then u, v, w are counterclockwise seen from p_i.
FACE_CCW = np.array([[1, 3, 2], [0, 2, 3], [0, 3, 1], [0, 1, 2]])
assert (_perm_parity(np.concatenate([FACE_CCW, np.arange(4)[:, None]], axis=1)) == 0).all()
# Local edge index (order 01 02 03 12 13 23 of Topology.tet_edges) of local vertices i, j.
_LOCAL_EDGE = np.full((4, 4), -1)
for _e, (_i, _j) in enumerate([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]):
    _LOCAL_EDGE[_i, _j] = _LOCAL_EDGE[_j, _i] = _e

# Tree capacities the kernel is compiled for (plus max_faces itself). Most trees hold 1-3
# faces: measured, a batch of such trees costs 7-10x less at capacity 4 than at 16 (the
# slot qualities and the padded arrays scale with the capacity), worth one more compile.
_TREE_CAPS = (4, 16, 64, 256)
# Trees per kernel call: every call has this many (the last one of a group padded), so one
# batch shape per tree capacity compiles (it was one per power of two, 256..1024: three
# shapes and ~2.5 s more compile in a fresh process). A 1024-tree call takes ~1 ms at
# capacity 4, so a padded small group costs little; large groups run as before.
_CHUNK = 1024


def _local(tets: np.ndarray, t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Local index (0..3) of vertex v[i] in tet t[i] (v must be a vertex of t)."""
    return local_index(tets, t, v)


def _at(table: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``table[rows, cols]`` for a C-ordered (m, w) table, by ``np.take`` of flat indices
    (2-3x faster than NumPy's two-array fancy indexing on whole-mesh tables)."""
    return np.take(table.reshape(-1), rows * table.shape[1] + cols)


def candidate_faces(mesh: TetMesh, quality: np.ndarray, dirty: np.ndarray | None) -> np.ndarray:
    """Interior non-subfacet faces worth trying, worst tets first, one per apex pair.

    A face touching a dirty tet (if ``dirty`` (m,) is given) is a candidate. Faces whose
    apexes are the same pair {a, b} lead to the same search, so only the first (the one
    next to the worst tet) is kept. Returns face ids (c,).
    """
    T = mesh.topology
    ft = T.face_tets
    ok = (ft[:, 1] >= 0) & ~T.subfacet
    if dirty is not None:
        # the faces of the dirty tets (rows of tet_faces), not a gather of every face's
        # two tets: late in a run a few hundred tets of a large mesh
        near = np.zeros(len(ok), bool)
        near[T.tet_faces[np.asarray(dirty, bool)].reshape(-1)] = True
        ok &= near
    f = np.flatnonzero(ok)
    if len(f) == 0:
        return f
    qf = np.minimum(quality[ft[f, 0]], quality[ft[f, 1]])
    f = f[np.argsort(qf, kind="stable")]
    a, b = T.face_apex[f, 0], T.face_apex[f, 1]
    key = np.minimum(a, b) * np.int64(mesh.n_points) + np.maximum(a, b)
    _, first = np.unique(key, return_index=True)
    return f[np.sort(first)]


def _sandwich_ok(mesh: TetMesh, g: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """g >= 0 is an interior non-subfacet face whose apexes are exactly {a, b}."""
    T = mesh.topology
    fg = np.maximum(g, 0)
    ga = T.face_apex[fg]
    lo, hi = np.minimum(ga[:, 0], ga[:, 1]), np.maximum(ga[:, 0], ga[:, 1])
    return (g >= 0) & (lo == a) & (hi == b) & ~T.subfacet[fg] & (T.face_tets[fg, 1] >= 0)


def _search_star(mesh: TetMesh, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Face opposite a, among ALL tets around a, crossed by ab in its interior (or -1).

    Exact (``segment_crosses_triangle`` on every tet of the star); -1 also when the
    crossed face is not unique (only possible in an invalid mesh).
    """
    T = mesh.topology
    P = mesh.points
    vp = T.vert_tets_ptr
    own, off = _segments(vp, a)
    t = T.vert_tets[vp[a][own] + off]
    g = T.tet_faces[t, _local(mesh.tets, t, a[own])]
    gv = T.faces[g]
    c = segment_crosses_triangle(P[a[own]], P[b[own]], P[gv[:, 0]], P[gv[:, 1]], P[gv[:, 2]])
    hit = c == CROSS_INTERIOR
    found = np.full(len(a), -1, np.int64)
    found[own[hit]] = g[hit]
    found[np.bincount(own[hit], minlength=len(a)) != 1] = -1
    return found


def _walk_star(
    mesh: TetMesh, a: np.ndarray, b: np.ndarray, start: np.ndarray, max_steps: int = 12
) -> tuple[np.ndarray, np.ndarray]:
    """Walk from tet ``start`` (around a) to the tet whose cone at a holds the ray a -> b.

    All walks advance together, one round per step. In tet t with face (y0, y1, y2)
    opposite a (counterclockwise seen from a) the exact signs ``orient3d(a, b, y_{k+1},
    y_k)`` say on which side of each plane (a, y_k, y_{k+1}) the ray lies: all positive,
    the ray is inside t's cone (found); one negative, step to the tet across that face
    (a, y_k, y_{k+1}), which holds a too, so the walk stays in the star of a. The edge
    tried first rotates with the step and the row, so that a walk cannot cycle forever
    (a walk in a non-Delaunay star can). Returns ``(status, tet)``: status 1 found,
    0 the ray runs along a face of the star (no face is crossed in its interior: no
    root), -1 unresolved (the star's boundary was hit, or ``max_steps`` ran out).
    """
    T = mesh.topology
    tets, P = mesh.tets, mesh.points
    n = len(a)
    status = np.full(n, -1, np.int8)
    where = np.full(n, -1, np.int64)
    act = np.arange(n)
    cur = start.copy()
    for step in range(max_steps):
        if len(act) == 0:
            break
        t, A, B = cur[act], a[act], b[act]
        y = np.take_along_axis(tets[t], FACE_CCW[_local(tets, t, A)], axis=1)
        pa, pb = P[A], P[B]
        y0, y1, y2 = P[y[:, 0]], P[y[:, 1]], P[y[:, 2]]
        s = orient3d_stacked([(pa, pb, y1, y0), (pa, pb, y2, y1), (pa, pb, y0, y2)]).T
        neg = s < 0
        inside = (s > 0).all(axis=1)
        status[act[inside]] = 1
        where[act[inside]] = t[inside]
        status[act[~inside & ~neg.any(axis=1)]] = 0
        go = np.flatnonzero(neg.any(axis=1))
        r = np.arange(len(go))
        order = ((r + step + act[go])[:, None] + np.arange(3)) % 3
        k = order[r, np.argmax(np.take_along_axis(neg[go], order, axis=1), axis=1)]
        opp = y[go, (k + 2) % 3]
        nb = T.tet_neighbors[t[go], _local(tets, t[go], opp)]
        cont = nb >= 0
        cur[act[go[cont]]] = nb[cont]
        act = act[go[cont]]
    return status, where


def find_roots(
    mesh: TetMesh, faces: np.ndarray, walk: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MULTIFACEREMOVAL's root (Figure 13, lines 33-36) for every candidate face.

    The root is the face opposite a of the tet around a that segment ab enters, where a, b
    are the candidate's apexes (a the smaller id): the first face ab crosses. It must be
    crossed in its relative interior (ab through a vertex or an edge: no root), sandwiched
    between a and b, and not a subfacet. Decided with the exact predicates.

    When ab misses the candidate face itself, ``walk=True`` walks through the star of a
    (``_walk_star``, ~3 orient3d per step, a few steps) and confirms the face found with
    ``segment_crosses_triangle``; walks that do not resolve, and ``walk=False``, test every
    tet around a (``_search_star``, 5 orient3d per tet of the star: ~10x more work).

    Returns ``(a, b, root)``, each (c,): root = -1 where there is none.
    """
    T = mesh.topology
    P = mesh.points
    fa = T.face_apex[faces]
    a, b = fa.min(axis=1), fa.max(axis=1)
    root = np.full(len(faces), -1, np.int64)
    if len(faces) == 0:
        return a, b, root
    fv = T.faces[faces]
    cross = segment_crosses_triangle(P[a], P[b], P[fv[:, 0]], P[fv[:, 1]], P[fv[:, 2]])
    root[cross == CROSS_INTERIOR] = faces[cross == CROSS_INTERIOR]
    # ab misses its own face: find the face ab leaves the star of a through
    s = np.flatnonzero(cross == CROSS_NONE)
    if len(s) == 0:
        return a, b, root
    found = np.full(len(s), -1, np.int64)
    todo = np.arange(len(s))
    if walk:
        f = faces[s]
        start = T.face_tets[f, (T.face_apex[f, 0] != a[s]).astype(np.int64)]
        status, tet = _walk_star(mesh, a[s], b[s], start)
        hit = np.flatnonzero(status == 1)
        g = T.tet_faces[tet[hit], _local(mesh.tets, tet[hit], a[s][hit])]
        gv = T.faces[g]
        c = segment_crosses_triangle(
            P[a[s][hit]], P[b[s][hit]], P[gv[:, 0]], P[gv[:, 1]], P[gv[:, 2]]
        )
        found[hit] = np.where(c == CROSS_INTERIOR, g, -1)
        todo = np.flatnonzero(status == -1)
    if len(todo):
        found[todo] = _search_star(mesh, a[s][todo], b[s][todo])
    ok = _sandwich_ok(mesh, found, a[s], b[s])
    root[s[ok]] = found[ok]
    return a, b, root


@dataclass
class Forest:
    """Padded face trees, one per candidate, in BFS order (node 0 = root).

    Shapes: P trees, capacity N = max_faces. Node corners are counterclockwise seen from
    a; slot s is the edge ``verts[s] -> verts[s+1 mod 3]``; slot 2 of a non-root node is
    the edge shared with its parent.
    """

    a: np.ndarray  # (P,) apex a (the new edge is ab)
    b: np.ndarray  # (P,)
    face: np.ndarray  # (P, N) face id, -1 for padding
    verts: np.ndarray  # (P, N, 3) corners
    ta: np.ndarray  # (P, N) tet (face, a)
    tb: np.ndarray  # (P, N) tet (face, b)
    parent: np.ndarray  # (P, N) parent node, -1 for the root and padding
    pslot: np.ndarray  # (P, N) slot of the parent holding this node
    child: np.ndarray  # (P, N, 3) child node per slot, -1 if none
    count: np.ndarray  # (P,) number of nodes
    overflow: np.ndarray  # (P,) the search was cut at capacity N (a truncated tree)
    bad: np.ndarray  # (P,) skip: an inverted / degenerate tet, or a cycle was met


def build_forest(
    mesh: TetMesh,
    a: np.ndarray,
    b: np.ndarray,
    root: np.ndarray,
    quality: np.ndarray,
    max_faces: int,
) -> Forest:
    """The trees ``G'`` of faces sandwiched between a[i] and b[i], searched from root[i].

    Breadth-first, one round per depth for ALL trees at once (NumPy over the frontier of
    every tree; no loop over trees or faces). A neighbour across a slot edge uw is taken
    when uw is in exactly four tets, none of its four faces is a subfacet, it is not a
    subsegment, and at least two of the three tets ``(a, b, edge)`` of the neighbour are
    positive (exact orient3d). A tree that would exceed ``max_faces`` nodes keeps the first
    nodes found, stops growing and is flagged ``overflow``: it is still a valid (smaller)
    candidate set, but its optimum is over the truncated tree only, not over all of ``G'``.
    A tree reaching a tet of quality <= 0 (multi-face removal assumes none) or meeting a
    face twice (a cycle; impossible in a valid mesh) is flagged ``bad``.
    """
    T = mesh.topology
    tets, P = mesh.tets, mesh.points
    nt, N, F = len(a), int(max_faces), len(T.faces)
    face = np.full((nt, N), -1, np.int64)
    verts = np.zeros((nt, N, 3), np.int64)
    ta = np.zeros((nt, N), np.int64)
    tb = np.zeros((nt, N), np.int64)
    parent = np.full((nt, N), -1, np.int64)
    pslot = np.zeros((nt, N), np.int64)
    child = np.full((nt, N, 3), -1, np.int64)
    count = np.ones(nt, np.int64)
    overflow = np.zeros(nt, bool)
    bad = np.zeros(nt, bool)
    if nt == 0:
        return Forest(a, b, face, verts, ta, tb, parent, pslot, child, count, overflow, bad)

    # roots: orient the face counterclockwise seen from a, using the tet (face, a)
    side = (T.face_apex[root, 0] != a).astype(np.int64)
    t_a = T.face_tets[root, side]
    t_b = T.face_tets[root, 1 - side]
    la = _local(tets, t_a, a)
    face[:, 0] = root
    verts[:, 0] = np.take_along_axis(tets[t_a], FACE_CCW[la], axis=1)
    ta[:, 0], tb[:, 0] = t_a, t_b
    bad |= (quality[t_a] <= 0) | (quality[t_b] <= 0)

    # the sum of a tet's vertex ids: a neighbour's vertex opposite a known face in one gather
    vertex_sum = tets[:, 0] + tets[:, 1] + tets[:, 2] + tets[:, 3]
    # frontier rows: (tree, node, slot); the root expands all three slots
    ft = np.repeat(np.arange(nt), 3)
    fn = np.zeros(3 * nt, np.int64)
    fs = np.tile(np.arange(3), nt)
    keep = ~bad[ft]
    ft, fn, fs = ft[keep], fn[keep], fs[keep]
    while len(ft):
        x = verts[ft, fn]  # (R, 3)
        r = np.arange(len(ft))
        p, q, o = x[r, fs], x[r, (fs + 1) % 3], x[r, (fs + 2) % 3]
        A, B = a[ft], b[ft]
        t_a, t_b = ta[ft, fn], tb[ft, fn]
        lo_a, lo_b = _local(tets, t_a, o), _local(tets, t_b, o)
        na = _at(T.tet_neighbors, t_a, lo_a)
        nb = _at(T.tet_neighbors, t_b, lo_b)
        ok = (na >= 0) & (nb >= 0)
        na0, nb0 = np.maximum(na, 0), np.maximum(nb, 0)
        va = np.take(vertex_sum, na0) - A - p - q
        vb = np.take(vertex_sum, nb0) - B - p - q
        ok &= va == vb  # the edge pq is in exactly four tets: (f,a) (f,b) (g,a) (g,b)
        edge = _at(T.tet_edges, t_a, _LOCAL_EDGE[_local(tets, t_a, p), _local(tets, t_a, q)])
        g = _at(T.tet_faces, na0, _local(tets, na0, A))
        ok &= ~T.subfacet[_at(T.tet_faces, t_a, lo_a)] & ~T.subfacet[_at(T.tet_faces, t_b, lo_b)]
        ok &= ~T.subsegment[edge] & ~T.subfacet[g]
        # the child (p, v, q), counterclockwise seen from a; reflex test (lines 18-21)
        sel = np.flatnonzero(ok)
        v = va[sel]
        Ps, Qs, As, Bs, Vs = (np.take(P, i, axis=0) for i in (p[sel], q[sel], A[sel], B[sel], v))
        signs = orient3d_stacked([(As, Bs, Vs, Ps), (As, Bs, Qs, Vs), (As, Bs, Ps, Qs)])
        npos = (signs > 0).sum(axis=0)
        sel = sel[npos >= 2]
        ct, cn, cs, cg = ft[sel], fn[sel], fs[sel], g[sel]
        # a face met twice (already in its tree, or twice this round): a cycle. A tree
        # holds at most N faces, so its row of ``face`` is searched directly (an isin
        # against every node of every tree hashed them all each round)
        ck = ct * np.int64(F) + cg
        _, uinv, ucnt = np.unique(ck, return_inverse=True, return_counts=True)
        dup = (face[ct] == cg[:, None]).any(axis=1) | (ucnt[uinv.reshape(-1)] > 1)
        bad[ct[dup]] = True
        inverted = (quality[na[sel]] <= 0) | (quality[nb[sel]] <= 0)
        bad[ct[inverted]] = True
        live = ~bad[ct]
        sel, ct, cn, cs, cg = sel[live], ct[live], cn[live], cs[live], cg[live]
        # capacity: rank of each new node within its tree (rows are grouped by tree)
        order = np.argsort(ct, kind="stable")
        sel, ct, cn, cs, cg = sel[order], ct[order], cn[order], cs[order], cg[order]
        first = np.searchsorted(ct, ct, side="left")
        idx = count[ct] + np.arange(len(ct)) - first
        fits = idx < N
        overflow[ct[~fits]] = True
        sel, ct, cn, cs, cg, idx = sel[fits], ct[fits], cn[fits], cs[fits], cg[fits], idx[fits]
        face[ct, idx] = cg
        verts[ct, idx] = np.column_stack([p[sel], va[sel], q[sel]])
        ta[ct, idx], tb[ct, idx] = na[sel], nb[sel]
        parent[ct, idx], pslot[ct, idx] = cn, cs
        child[ct, cn, cs] = idx
        np.add.at(count, ct, 1)
        # next round: the new nodes' slots 0 and 1, for trees still growing
        grow = ~overflow[ct] & ~bad[ct]
        ct, idx = ct[grow], idx[grow]
        ft = np.repeat(ct, 2)
        fn = np.repeat(idx, 2)
        fs = np.tile(np.arange(2), len(ct))
    return Forest(a, b, face, verts, ta, tb, parent, pslot, child, count, overflow, bad)


def _tree_caps(max_faces: int) -> list[int]:
    return sorted({c for c in _TREE_CAPS if c < max_faces} | {int(max_faces)})


def tree_kernel_specs(measure: str, max_faces: int) -> list[tuple]:
    """``_aot.prefetch`` spec of the tree DP kernel at the smallest tree capacity, the one
    every ``multiface_removal_pass(max_faces=max_faces)`` calls (its trees of up to 4
    faces; larger capacities only where larger trees occur)."""
    import jax

    cap = _tree_caps(max_faces)[0]
    f64, i64 = np.dtype(np.float64), np.dtype(np.int64)

    def struct(shape, dtype):
        return jax.ShapeDtypeStruct(shape, dtype)

    args = (
        *[struct((_CHUNK,), f64)] * 6,
        *[struct((_CHUNK, cap, 3), f64)] * 3,
        struct((_CHUNK, cap), i64), struct((_CHUNK, cap), i64), struct((_CHUNK, cap, 3), i64),
        struct((_CHUNK, cap), f64), struct((_CHUNK, cap), np.dtype(bool)),
        struct((), np.dtype(np.int32)),
    )  # fmt: skip
    return [("solve_trees", (measure,), functools.partial(solve_trees, measure=measure), args)]


def solve_forest(
    mesh: TetMesh, forest: Forest, quality: np.ndarray, measure: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run the tree DP on every tree: ``(q_old (P,), q_new (P,), chosen (P, N))``.

    Trees are grouped by size into the capacities ``_tree_caps(N)``, cut into chunks of
    ``_CHUNK`` trees (the last one padded), so the kernel compiles once per (capacity,
    measure). Bad trees get ``q_new = -inf``.
    """
    nt, N = forest.face.shape
    q_old = np.full(nt, np.inf)
    q_new = np.full(nt, -np.inf)
    chosen = np.zeros((nt, N), bool)
    P = mesh.points
    live = ~forest.bad
    tasks = []
    lo = 0
    for cap in _tree_caps(N):
        group = np.flatnonzero(live & (forest.count > lo) & (forest.count <= cap))
        lo = cap
        tasks += [(cap, group[s : s + _CHUNK]) for s in range(0, len(group), _CHUNK)]

    def arguments(task):
        cap, sel = task
        f = forest.face[sel, :cap]
        valid = f >= 0
        xyz = P[forest.verts[sel, :cap]]  # (k, cap, 3 corners, 3 coords)
        pa, pb = P[forest.a[sel]], P[forest.b[sel]]
        qt = np.minimum(quality[forest.ta[sel, :cap]], quality[forest.tb[sel, :cap]])
        child = np.where(valid[:, :, None], forest.child[sel, :cap], -1)
        # padded to _CHUNK trees, copies of the first one with no valid node: only the
        # real trees are gathered (a late pass solves a handful of trees per call)
        return (
            *(_padded(x) for x in (pa[:, 0], pa[:, 1], pa[:, 2], pb[:, 0], pb[:, 1], pb[:, 2])),
            *(_padded(xyz[..., c]) for c in range(3)),
            # ids in the kernel's int64, whatever the topology's index type
            _padded(np.maximum(forest.parent[sel, :cap], 0).astype(np.int64)),
            _padded(forest.pslot[sel, :cap].astype(np.int64)),
            _padded(child.astype(np.int64), -1),
            _padded(qt),
            _padded(valid, False),
            np.asarray(forest.count[sel].max(), np.int32),
        )

    kernel = functools.partial(solve_trees, measure=measure)
    # every tree capacity's kernel compiled (or loaded) at once on the worker threads;
    # the first task of each capacity keeps the arguments built for that (a late pass
    # has one or two tasks: building them twice was a third of its host work)
    firsts = {cap: i for i, (cap, _) in reversed(list(enumerate(tasks)))}
    built = {i: arguments(tasks[i]) for i in firsts.values()}
    prefetch([("solve_trees", (measure,), kernel, args) for args in built.values()])

    def solve(i):
        args = built.pop(i, None)
        out = cached_call("solve_trees", (measure,), kernel, *(args or arguments(tasks[i])))
        return [np.asarray(x)[: len(tasks[i][1])] for x in out]

    # the trees' chunks are independent: solved on the worker threads, in order
    results = _config.parallel_map(solve, list(range(len(tasks))))
    for (cap, sel), (qo, qn, ch) in zip(tasks, results, strict=True):
        q_old[sel] = qo
        q_new[sel] = qn
        chosen[sel, :cap] = ch
    return q_old, q_new, chosen


def _padded(rows: np.ndarray, fill=None) -> np.ndarray:
    """``rows`` (k, ...) padded to ``_CHUNK`` rows with copies of its first row (or with
    ``fill``), contiguous."""
    out = np.empty((_CHUNK, *rows.shape[1:]), rows.dtype)
    out[: len(rows)] = rows
    out[len(rows) :] = rows[0] if fill is None else fill
    return out


def new_tets_of(forest: Forest, chosen: np.ndarray, trees: np.ndarray):
    """The tets created by removing ``chosen`` faces of the given trees.

    Returns ``(owner, tets)``: (W,) tree of each new tet and (W, 4) tets ``(a, b, x_{s+1},
    x_s)`` for every slot edge ``x_s -> x_{s+1}`` on the boundary of the chosen set.
    """
    N = forest.face.shape[1]
    ch = chosen[trees]  # (k, N)
    c = forest.child[trees]  # (k, N, 3)
    c_in = np.take_along_axis(ch, np.maximum(c, 0).reshape(len(trees), -1), axis=1)
    c_in = c_in.reshape(c.shape) & (c >= 0)
    is_root = (np.arange(N) == 0)[None, :, None]
    slot_ok = (np.arange(3) < 2)[None, None, :] | is_root
    boundary = ch[:, :, None] & slot_ok & ~c_in
    w, i, s = np.nonzero(boundary)
    x = forest.verts[trees[w], i]
    r = np.arange(len(w))
    out = np.column_stack([forest.a[trees[w]], forest.b[trees[w]], x[r, (s + 1) % 3], x[r, s]])
    return trees[w], out


def _claims(forest: Forest, chosen: np.ndarray, cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(claims, k): the two tets of every face the candidates ``cand`` (c,) remove, one
    candidate after the other, and how many faces each removes (c,)."""
    ci, ni = np.nonzero(chosen[cand])
    claims = np.stack([forest.ta[cand[ci], ni], forest.tb[cand[ci], ni]], axis=1).reshape(-1)
    return claims, chosen[cand].sum(axis=1)


def multiface_removal_pass(
    mesh: TetMesh, **options
) -> tuple[TetMesh, PassStats, np.ndarray | None]:
    """One pass: try every candidate face at once, apply a conflict-free set of winners
    (``plan_multiface_removal``'s, with the same options).

    Returns:
        (new mesh, stats, keep): ``keep`` (m,) marks the old tets that survive, in order,
        at the front of the new mesh; the new tets follow. ``keep`` is None (and the
        mesh returned unchanged) when nothing improved. ``stats.by_size`` counts
        successes by the number of faces removed.
    """
    plan, stats = plan_multiface_removal(mesh, **options)
    out, keep = apply_plans(mesh, [plan])
    return out, stats, keep


def plan_multiface_removal(
    mesh: TetMesh,
    *,
    measure: str = "min_sine",
    max_faces: int = 16,
    quality: np.ndarray | None = None,
    dirty: np.ndarray | None = None,
    min_improvement: float = 1e-9,
    sites: np.ndarray | None = None,
    forbidden: np.ndarray | None = None,
    min_scaled_jacobian: float | None = None,
    prior: FlipPlan | None = None,
) -> tuple[FlipPlan | None, PassStats]:
    """Try every candidate face at once and choose a conflict-free set of winners.

    Args:
        mesh: input mesh (multi-face removal assumes no inverted tets; candidates whose
            trees reach a tet of quality <= 0 are skipped).
        measure: quality measure name.
        max_faces: tree capacity: the search stops growing a tree at this many faces
            (counted in ``stats.overflow``); the truncated tree is still evaluated, and its
            result is optimal over the truncated tree only.
        quality: (m,) quality of ``mesh``'s tets under ``measure`` if already known.
        dirty: (m,) bool; only faces touching a dirty tet are tried (None: all faces).
        min_improvement: a winner must raise its worst tet by more than this.
        sites: (k,) face ids from ``candidate_faces`` to try instead (``dirty`` unused).
        forbidden: (f, 4) tets no winner may create again (see ``plan_edge_removal``).
        min_scaled_jacobian: floor of the guard on curved tets (``_curved_guard``).
        prior: another plan of this mesh (edge removal's) to be applied together with
            this one (``apply_plans``): no winner removes one of its tets, and the new
            tets of both must conform together.

    Returns:
        (plan, stats): the winners' ``FlipPlan`` (None when nothing improved), not
        applied. ``stats.by_size`` counts successes by the number of faces removed.
    """
    stats = PassStats("face")
    q = mesh.quality(measure) if quality is None else np.asarray(quality)
    faces = candidate_faces(mesh, q, dirty) if sites is None else np.asarray(sites, np.int64)
    a, b, root = find_roots(mesh, faces)
    has = root >= 0
    a, b, root = a[has], b[has], root[has]
    if len(root) == 0:
        return None, stats
    forest = build_forest(mesh, a, b, root, q, max_faces)
    stats.attempts = int((~forest.bad).sum())
    stats.overflow = int((forest.overflow & ~forest.bad).sum())
    q_old, q_new, chosen = solve_forest(mesh, forest, q, measure)
    cand = np.flatnonzero(~forest.bad & (q_new > q_old + min_improvement))
    if len(cand) == 0:
        return None, stats
    # new tets, checked with the exact predicate (float quality > 0 is not a proof)
    owner, new = new_tets_of(forest, chosen, cand)
    flat = orient3d_tets(mesh.points, new) <= 0
    dead = np.zeros(len(forest.a), bool)
    dead[owner[flat]] = True
    # before the conflict-free selection: a candidate that would undo a kick leaves its
    # tets to the others
    dead |= recreating_owners(new, owner, forbidden, len(forest.a))
    if min_scaled_jacobian is not None and mesh.has_curved_edges:
        claims, k = _claims(forest, chosen, cand)
        dead |= worse_owners(
            mesh,
            min_scaled_jacobian,
            (mesh.points, mesh.tets[claims], np.repeat(cand, 2 * k)),
            (mesh.points, new, owner),
            len(forest.a),
        )
    if prior is not None:  # its tets are taken
        claims, k = _claims(forest, chosen, cand)
        dead[np.repeat(cand, 2 * k)[prior.remove[claims]]] = True
    cand = cand[~dead[cand]]
    claims, k = _claims(forest, chosen, cand)
    claim_ptr = np.concatenate([[0], np.cumsum(2 * k)])
    # worst removed tet first (as edge removal); among equals, the best created worst tet
    rank = np.empty(len(cand), np.int64)
    rank[np.lexsort((-q_new[cand], q_old[cand]))] = np.arange(len(cand))
    win = select_conflict_free(claim_ptr, claims, rank, mesh.n_tets)
    if not win.any():
        return None, stats
    winners = cand[win]
    remove = np.zeros(mesh.n_tets, bool)
    remove[claims[np.repeat(win, 2 * k)]] = True
    is_w = np.zeros(len(forest.a), bool)
    is_w[winners] = True
    keep_new = is_w[owner]
    new, owner = new[keep_new], owner[keep_new]
    # Guard (as edge removal's): a new face may coincide with an existing one when the
    # neighbourhood holds inverted or degenerate tets; reject those winners and retry.
    claim_owner = np.repeat(cand, 2 * k)
    while True:
        # the prior plan's tets are checked with these (owner len(forest.a): its own
        # tets conform, it chose them on this mesh, and no winner here touches them)
        reject = nonconforming_owners(
            mesh,
            remove if prior is None else remove | prior.remove,
            new if prior is None else np.concatenate([new, prior.new_tets]),
            owner
            if prior is None
            else np.concatenate([owner, np.full(len(prior.new_tets), len(forest.a))]),
            len(forest.a) + 1,
        )[: len(forest.a)]
        if not reject.any():
            break
        remove[claims[reject[claim_owner] & is_w[claim_owner]]] = False
        is_w &= ~reject
        ok = ~reject[owner]
        new, owner = new[ok], owner[ok]
        if not is_w.any():
            return None, stats
    winners = np.flatnonzero(is_w)
    region = mesh.region[forest.ta[owner, 0]]
    sizes = k[win & is_w[cand]]
    stats.successes = int(len(winners))
    stats.by_size = {int(s): int(c) for s, c in zip(*np.unique(sizes, return_counts=True))}
    return FlipPlan(remove, new, region), stats
