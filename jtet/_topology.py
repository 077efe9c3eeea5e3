"""Mesh adjacency, all vectorized NumPy: faces, edges, ordered edge rings, protection.

Nothing here loops in Python over tets, faces or edges. Rings around edges are ordered
by list ranking (pointer doubling): O(log m) vectorized rounds for rings of m tets.

Conventions (see also ``jtet._quality``): tets are positively oriented in the VTK sense.
For an edge (a, b) with a < b, its ring v_1..v_m is ordered counterclockwise about ab as
seen from a, so that every tet around the edge is (a, b, v_{i+1}, v_i) up to an even
permutation. On the exterior boundary the ring is an open chain of m + 1 vertices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._errors import MeshInputError

# Local faces (opposite vertex i) and local edges of a tet.
TET_FACES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
# For local edge (i, j), the two other local vertices (k, l) such that the permutation
# (i, j, l, k) of (0, 1, 2, 3) is even: then (a, b, v_l, v_k) has the tet's orientation,
# i.e. the ring steps from v_k to v_l.
_EDGE_OTHERS = np.array([[3, 2], [1, 3], [2, 1], [3, 0], [0, 2], [1, 0]])
# Vertex kinds for smoothing / protection.
FREE, SURFACE, SEGMENT, CORNER = 0, 1, 2, 3


def _perm_parity(p: np.ndarray) -> np.ndarray:
    """Parity (0 even, 1 odd) of each row permutation of range(k), vectorized."""
    p = np.asarray(p)
    k = p.shape[-1]
    inv = np.zeros(p.shape[:-1], np.int64)
    for i in range(k):  # k <= 4: a loop over positions, not over elements
        for j in range(i + 1, k):
            inv += p[..., i] > p[..., j]
    return inv % 2


assert (_perm_parity(np.concatenate([TET_EDGES, _EDGE_OTHERS[:, ::-1]], axis=1)) == 0).all()


def row_keys(rows: np.ndarray, n: int) -> np.ndarray:
    """Injective int64 key of every sorted row of small non-negative ints (< n).

    Exact while n ** k < 2**63 (faces: n < 2.09M points). Larger meshes fall back to a
    lexicographic rank, which is exact for any size.
    """
    rows = np.asarray(rows, np.int64)
    k = rows.shape[1]
    if float(n) ** k < 2.0**62:
        key = np.zeros(len(rows), np.int64)
        for c in range(k):
            key = key * n + rows[:, c]
        return key
    # exact for any n: rank of each row among the unique rows
    _, inv = np.unique(rows, axis=0, return_inverse=True)
    return inv.reshape(-1).astype(np.int64)


def match_rows(table: np.ndarray, queries: np.ndarray, n: int) -> np.ndarray:
    """Index in ``table`` of each sorted query row, or -1 (rows compared as sets)."""
    if len(queries) == 0:
        return np.zeros(0, np.int64)
    both = np.concatenate([np.sort(table, axis=1), np.sort(queries, axis=1)])
    keys = row_keys(both, n)
    tk, qk = keys[: len(table)], keys[len(table) :]
    order = np.argsort(tk, kind="stable")
    pos = np.searchsorted(tk[order], qk)
    pos = np.minimum(pos, len(tk) - 1)
    found = tk[order][pos] == qk
    return np.where(found, order[pos], -1)


def _csr(groups: np.ndarray, n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """(ptr, order): entries sorted by group id, and CSR pointers per group."""
    order = np.argsort(groups, kind="stable")
    counts = np.bincount(groups, minlength=n_groups)
    ptr = np.zeros(n_groups + 1, np.int64)
    np.cumsum(counts, out=ptr[1:])
    return ptr, order


def _unit(v: np.ndarray) -> np.ndarray:
    nrm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, nrm, out=np.zeros_like(v), where=nrm > 0)


@dataclass(frozen=True, eq=False)
class Topology:
    """Adjacency of a TetMesh (see the module docstring for conventions).

    Shapes: m tets, n points, F faces, E edges.
    """

    faces: np.ndarray  # (F, 3) sorted vertex triples
    tet_faces: np.ndarray  # (m, 4) face opposite local vertex i
    face_tets: np.ndarray  # (F, 2) tets containing the face, -1 if none
    face_apex: np.ndarray  # (F, 2) vertex opposite the face in face_tets[:, s]
    tet_neighbors: np.ndarray  # (m, 4) neighbour across the face opposite vertex i
    boundary_face: np.ndarray  # (F,) bool, face of exactly one tet
    interface_face: np.ndarray  # (F,) bool, face between tets of different regions
    subfacet: np.ndarray  # (F,) bool, boundary | interface | user-protected
    surface_id: np.ndarray  # (F,) int64 id of the bounding surface of a subfacet, -1 else
    edges: np.ndarray  # (E, 2) sorted vertex pairs
    tet_edges: np.ndarray  # (m, 6) edge id of local edges 01 02 03 12 13 23
    edge_tets_ptr: np.ndarray  # (E+1,) CSR pointers into edge_tets
    edge_tets: np.ndarray  # tets around each edge, in ring order
    edge_ring_ptr: np.ndarray  # (E+1,) CSR pointers into edge_ring
    edge_ring: np.ndarray  # ordered ring (interior) or chain (boundary) vertices
    edge_boundary: np.ndarray  # (E,) bool, ring is an open chain
    edge_manifold: np.ndarray  # (E,) bool, ring is one cycle or one chain
    edge_n_subfacets: np.ndarray  # (E,) number of subfacets containing the edge
    subsegment: np.ndarray  # (E,) bool, edge that must never be removed
    vert_tets_ptr: np.ndarray  # (n+1,)
    vert_tets: np.ndarray  # tets around each vertex
    vertex_kind: np.ndarray  # (n,) int8: FREE, SURFACE, SEGMENT, CORNER
    surface_normal: np.ndarray  # (n, 3) unit normal of a SURFACE vertex's flat surface
    segment_direction: np.ndarray  # (n, 3) unit direction of a SEGMENT vertex's line

    @property
    def n_edges(self) -> int:
        return len(self.edges)

    def edge_ring_size(self) -> np.ndarray:
        """(E,) number of tets around each edge."""
        return np.diff(self.edge_tets_ptr)

    @classmethod
    def build(cls, mesh, feature_angle: float = 0.0) -> Topology:
        """Adjacency of ``mesh``.

        ``feature_angle`` (degrees): two subfacets of one surface meeting at an edge whose
        planes deviate by more than this make the edge a subsegment. The default 0 keeps
        only exactly coplanar pairs (decided with the robust orient3d), so every
        transformation that flips such an edge leaves the surface geometrically identical.
        """
        points, tets, region = mesh.points, mesh.tets, mesh.region
        n, m = len(points), len(tets)

        # ---------------------------------------------------------------- faces
        tf = np.sort(tets[:, TET_FACES], axis=2).reshape(-1, 3)  # (4m, 3)
        fkeys = row_keys(tf, n)
        ukeys, first, inv, counts = np.unique(
            fkeys, return_index=True, return_inverse=True, return_counts=True
        )
        if (counts > 2).any():
            f = int(np.flatnonzero(counts > 2)[0])
            bad = tf[first[f]].tolist()
            raise MeshInputError(
                f"non-conforming mesh: face {bad} is shared by {int(counts[f])} tets "
                f"({int((counts > 2).sum())} such faces)"
            )
        faces = tf[first]
        F = len(faces)
        tet_faces = inv.reshape(m, 4)
        slot_tet = np.repeat(np.arange(m), 4)
        slot_local = np.tile(np.arange(4), m)
        order = np.argsort(inv, kind="stable")
        ptr = np.zeros(F + 1, np.int64)
        np.cumsum(counts, out=ptr[1:])
        face_tets = np.full((F, 2), -1, np.int64)
        face_apex = np.full((F, 2), -1, np.int64)
        s0 = order[ptr[:-1]]
        face_tets[:, 0] = slot_tet[s0]
        face_apex[:, 0] = tets[slot_tet[s0], slot_local[s0]]
        two = counts == 2
        s1 = order[ptr[:-1][two] + 1]
        face_tets[two, 1] = slot_tet[s1]
        face_apex[two, 1] = tets[slot_tet[s1], slot_local[s1]]
        other = np.where(
            face_tets[tet_faces, 0] == np.arange(m)[:, None],
            face_tets[tet_faces, 1],
            face_tets[tet_faces, 0],
        )
        tet_neighbors = other
        boundary_face = counts == 1
        r0 = region[face_tets[:, 0]]
        r1 = np.where(two, region[np.maximum(face_tets[:, 1], 0)], r0)
        interface_face = two & (r0 != r1)
        protected = np.zeros(F, bool)
        if len(mesh.protected_faces):
            idx = match_rows(faces, mesh.protected_faces, n)
            if (idx < 0).any():
                bad = mesh.protected_faces[idx < 0][0].tolist()
                raise MeshInputError(f"protected face {bad} is not a face of the mesh")
            protected[idx] = True
        subfacet = boundary_face | interface_face | protected
        # Surface identity: the (region, region) pair it separates; user-protected faces
        # inside one region form surfaces of their own kind.
        rmin, rmax = np.minimum(r0, r1), np.maximum(r0, r1)
        _, surface_code = np.unique(
            np.stack(
                [
                    np.where(boundary_face, -1, rmin),
                    rmax,
                    protected & ~interface_face & ~boundary_face,
                ],
                1,
            ),
            axis=0,
            return_inverse=True,
        )
        surface_id = np.where(subfacet, surface_code.reshape(-1), -1)

        # ---------------------------------------------------------------- edges
        te = np.sort(tets[:, TET_EDGES], axis=2).reshape(-1, 2)  # (6m, 2)
        ekeys = te[:, 0] * np.int64(n) + te[:, 1]
        _, efirst, einv = np.unique(ekeys, return_index=True, return_inverse=True)
        edges = te[efirst]
        E = len(edges)
        tet_edges = einv.reshape(m, 6)

        # ring step c -> d of every (tet, local edge), oriented w.r.t. the sorted edge:
        # for local edge (i, j) the step is v_k -> v_l; if tets[i] > tets[j] the edge is
        # traversed reversed (a and b swapped), which reverses the step.
        lo = tets[:, TET_EDGES[:, 0]]
        hi = tets[:, TET_EDGES[:, 1]]
        ck = tets[:, _EDGE_OTHERS[:, 0]]
        cl = tets[:, _EDGE_OTHERS[:, 1]]
        swap = lo > hi
        c = np.where(swap, cl, ck).reshape(-1)
        d = np.where(swap, ck, cl).reshape(-1)
        entry_tet = np.repeat(np.arange(m), 6)
        edge_of = einv.reshape(-1)
        (edge_tets_ptr, edge_tets, edge_ring_ptr, edge_ring, edge_boundary, edge_manifold) = (
            _order_rings(edge_of, c, d, entry_tet, E, n)
        )

        # ---------------------------------------------------------------- protection
        # subfacets containing each edge: every face has 3 edges
        fe = np.stack([faces[:, [0, 1]], faces[:, [0, 2]], faces[:, [1, 2]]], 1).reshape(-1, 2)
        fe_keys = fe[:, 0] * np.int64(n) + fe[:, 1]
        ekeys_u = edges[:, 0] * np.int64(n) + edges[:, 1]
        fe_edge = np.searchsorted(ekeys_u, fe_keys)
        sf_slot = np.repeat(subfacet, 3)
        sf_edge = fe_edge[sf_slot]
        sf_face = np.repeat(np.arange(F), 3)[sf_slot]
        edge_n_subfacets = np.bincount(sf_edge, minlength=E)
        subsegment = (edge_n_subfacets != 0) & (edge_n_subfacets != 2)
        subsegment |= ~edge_manifold
        # edges with exactly two subfacets: same surface and coplanar?
        pair_edges = np.flatnonzero(edge_n_subfacets == 2)
        if len(pair_edges):
            optr, oorder = _csr(sf_edge, E)
            f1 = sf_face[oorder[optr[pair_edges]]]
            f2 = sf_face[oorder[optr[pair_edges] + 1]]
            diff_surface = surface_id[f1] != surface_id[f2]
            a, b = edges[pair_edges, 0], edges[pair_edges, 1]
            third1 = faces[f1].sum(1) - a - b
            third2 = faces[f2].sum(1) - a - b
            bent = _bent(points, a, b, third1, third2, feature_angle)
            subsegment[pair_edges] |= diff_surface | bent
        if len(mesh.protected_edges):
            idx = match_rows(edges, mesh.protected_edges, n)
            if (idx < 0).any():
                bad = mesh.protected_edges[idx < 0][0].tolist()
                raise MeshInputError(f"protected edge {bad} is not an edge of the mesh")
            subsegment[idx] = True

        # ---------------------------------------------------------------- vertices
        vert_tets_ptr, vorder = _csr(tets.reshape(-1), n)
        vert_tets = vorder // 4
        vertex_kind, surface_normal, segment_direction = _vertex_kinds(
            points, faces, subfacet, edges, subsegment, n
        )
        return cls(
            faces=faces,
            tet_faces=tet_faces,
            face_tets=face_tets,
            face_apex=face_apex,
            tet_neighbors=tet_neighbors,
            boundary_face=boundary_face,
            interface_face=interface_face,
            subfacet=subfacet,
            surface_id=surface_id,
            edges=edges,
            tet_edges=tet_edges,
            edge_tets_ptr=edge_tets_ptr,
            edge_tets=edge_tets,
            edge_ring_ptr=edge_ring_ptr,
            edge_ring=edge_ring,
            edge_boundary=edge_boundary,
            edge_manifold=edge_manifold,
            edge_n_subfacets=edge_n_subfacets,
            subsegment=subsegment,
            vert_tets_ptr=vert_tets_ptr,
            vert_tets=vert_tets,
            vertex_kind=vertex_kind,
            surface_normal=surface_normal,
            segment_direction=segment_direction,
        )


def _order_rings(edge_of, c, d, entry_tet, E, n):
    """Order the ring steps c -> d of every edge by list ranking.

    Each edge's steps form one cycle (interior edge) or one path (boundary edge) in a
    manifold mesh. Returns CSR tets in ring order, CSR ring vertices (a chain gets its
    final vertex appended), the boundary flag and a manifold flag per edge.
    """
    N = len(c)
    # index of the step leaving vertex x in edge e: key (e, x)
    from_key = edge_of * np.int64(n) + c
    to_key = edge_of * np.int64(n) + d
    korder = np.argsort(from_key, kind="stable")
    sk = from_key[korder]
    dup = np.zeros(N, bool)
    dup[korder[1:]] = sk[1:] == sk[:-1]  # two steps leave the same vertex: not a manifold ring
    pos = np.minimum(np.searchsorted(sk, to_key), N - 1)
    has_next = sk[pos] == to_key
    nxt = np.where(has_next, korder[pos], -1)
    has_pred = np.zeros(N, bool)
    has_pred[nxt[has_next]] = True
    is_start = ~has_pred
    edge_counts = np.bincount(edge_of, minlength=E)
    n_starts = np.bincount(edge_of[is_start], minlength=E)
    bad_edge = np.bincount(edge_of[dup], minlength=E) > 0
    edge_boundary = n_starts > 0
    # cycles: cut them at their lowest entry so every ring becomes one path
    ptr, eorder = _csr(edge_of, E)
    head = np.full(E, -1, np.int64)
    cyc = ~edge_boundary & (edge_counts > 0)
    head[cyc] = eorder[ptr[:-1][cyc]]  # lowest entry index of each cycle (stable sort)
    is_head = np.zeros(N, bool)
    is_head[head[cyc]] = True
    nxt = np.where(is_head[np.maximum(nxt, 0)] & (nxt >= 0), -1, nxt)
    # pointer doubling: distance to the end of the path
    dist = (nxt >= 0).astype(np.int64)
    jump = nxt.copy()
    while True:
        live = jump >= 0
        if not live.any():
            break
        dist[live] += dist[jump[live]]
        jump[live] = jump[jump[live]]
    # a manifold ring is one path covering all steps: its start has dist = count - 1
    start_dist = np.full(E, -1, np.int64)
    starts = np.flatnonzero(is_start | is_head)
    np.maximum.at(start_dist, edge_of[starts], dist[starts])
    edge_manifold = (
        (start_dist == edge_counts - 1) & (n_starts <= 1) & ~bad_edge & (edge_counts > 0)
    )
    rank = edge_counts[edge_of] - 1 - dist
    rank = np.where(edge_manifold[edge_of], rank, 0)
    order = np.lexsort((rank, np.arange(N) * ~edge_manifold[edge_of], edge_of))
    edge_tets = entry_tet[order]
    edge_tets_ptr = ptr
    # ring vertices: c of each step; chains also get d of their last step
    ring_len = edge_counts + edge_boundary.astype(np.int64)
    edge_ring_ptr = np.zeros(E + 1, np.int64)
    np.cumsum(ring_len, out=edge_ring_ptr[1:])
    edge_ring = np.empty(edge_ring_ptr[-1], np.int64)
    e_sorted = edge_of[order]
    slot = edge_ring_ptr[e_sorted] + (np.arange(N) - ptr[e_sorted])
    edge_ring[slot] = c[order]
    bnd = np.flatnonzero(edge_boundary)
    last = order[ptr[bnd + 1] - 1]
    edge_ring[edge_ring_ptr[bnd + 1] - 1] = d[last]
    return edge_tets_ptr, edge_tets, edge_ring_ptr, edge_ring, edge_boundary, edge_manifold


def _bent(points, a, b, c, d, feature_angle: float) -> np.ndarray:
    """True where triangles abc and abd are not coplanar (within ``feature_angle`` deg)."""
    if feature_angle <= 0.0:
        from ._predicates import orient3d

        return orient3d(points[a], points[b], points[c], points[d]) != 0
    pa, pb = points[a], points[b]
    n1 = _unit(np.cross(pb - pa, points[c] - pa))
    n2 = _unit(np.cross(points[d] - pa, pb - pa))  # flipped: coplanar & opposite -> n1 == n2
    cosang = np.clip(np.einsum("ij,ij->i", n1, n2), -1.0, 1.0)
    return np.degrees(np.arccos(cosang)) > feature_angle


def _vertex_kinds(points, faces, subfacet, edges, subsegment, n):
    """Classify vertices for smoothing: FREE, SURFACE (flat), SEGMENT (straight), CORNER."""
    kind = np.zeros(n, np.int8)
    normal = np.zeros((n, 3))
    direction = np.zeros((n, 3))
    sf = faces[subfacet]
    on_surface = np.zeros(n, bool)
    on_surface[sf.reshape(-1)] = True
    kind[on_surface] = SURFACE
    # surface normal: area-weighted sum of the (consistently unoriented) subfacet normals;
    # sign-align each normal to the first one seen at the vertex so they do not cancel.
    if len(sf):
        p = points[sf]
        fn = _unit(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
        verts = sf.reshape(-1)
        fnr = np.repeat(fn, 3, axis=0)
        vptr, vorder = _csr(verts, n)
        ref = np.zeros((n, 3))
        firsts = vorder[vptr[:-1][on_surface]]
        ref[on_surface] = fnr[firsts]
        sgn = np.sign(np.einsum("ij,ij->i", fnr, ref[verts]))
        sgn[sgn == 0] = 1.0
        np.add.at(normal, verts, fnr * sgn[:, None])
        normal = _unit(normal)
    seg = edges[subsegment]
    nseg = np.bincount(seg.reshape(-1), minlength=n)
    kind[nseg > 2] = CORNER
    kind[nseg == 1] = CORNER
    two = np.flatnonzero(nseg == 2)
    if len(two):
        sv = seg.reshape(-1)
        other = np.stack([seg[:, 1], seg[:, 0]], 1).reshape(-1)
        sptr, sorder = _csr(sv, n)
        o1 = other[sorder[sptr[two]]]
        o2 = other[sorder[sptr[two] + 1]]
        u1 = points[o1] - points[two]
        u2 = points[two] - points[o2]
        cr = np.linalg.norm(np.cross(u1, u2), axis=1)
        scale = np.linalg.norm(u1, axis=1) * np.linalg.norm(u2, axis=1)
        straight = (cr <= 1e-12 * scale) & (np.einsum("ij,ij->i", u1, u2) > 0)
        kind[two] = np.where(straight, SEGMENT, CORNER)
        direction[two[straight]] = _unit(u1[straight] + u2[straight])
    # a surface vertex whose subfacets are not all coplanar is held by subsegments
    # (flatness is decided edge by edge above); SURFACE keeps its normal only.
    normal[kind != SURFACE] = 0.0
    return kind, normal, direction
