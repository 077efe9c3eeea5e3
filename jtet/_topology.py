"""Mesh adjacency, all vectorized NumPy: faces, edges, ordered edge rings, protection.

Nothing here loops in Python over tets, faces or edges. Rings around edges are ordered
in buckets of equal ring size, each bucket vectorized (``_order_rings``).

Conventions (see also ``jtet._quality``): tets are positively oriented in the VTK sense.
For an edge (a, b) with a < b, its ring v_1..v_m is ordered counterclockwise about ab as
seen from a, so that every tet around the edge is (a, b, v_{i+1}, v_i) up to an even
permutation. On the exterior boundary the ring is an open chain of m + 1 vertices.
"""

from __future__ import annotations

import functools
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


def index_dtype(largest: int) -> type:
    """The integer type of topology ids and CSR pointers whose values are at most
    ``largest``: int32 while they fit, int64 beyond. Half the bytes of every incidence
    array to copy, gather and fault in: the 983k-tet cube's topology is 430 MB in
    int64 and each flip step's update copies all of it. Keys that combine ids (a * n +
    b) are computed in int64 explicitly (under NumPy 2, int32 * Python int stays
    int32)."""
    return np.int32 if largest < np.iinfo(np.int32).max else np.int64


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
    if len(table) == 0:
        return np.full(len(queries), -1, np.int64)
    both = np.concatenate([np.sort(table, axis=1), np.sort(queries, axis=1)])
    keys = row_keys(both, n)
    tk, qk = keys[: len(table)], keys[len(table) :]
    order = np.argsort(tk, kind="stable")
    pos = np.searchsorted(tk[order], qk)
    pos = np.minimum(pos, len(tk) - 1)
    found = tk[order][pos] == qk
    return np.where(found, order[pos], -1)


def local_index(rows: np.ndarray, ids: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(q,) position of ``values[i]`` in row ``rows[ids[i]]`` of a (m, 4) array whose rows
    hold distinct values (tets: no repeated vertex), 0 if absent. Arithmetic on the row's
    three last columns: ~4x faster than argmax over a (q, 4) comparison."""
    r = np.take(rows, ids, axis=0)
    return (r[:, 1] == values) * 1 + (r[:, 2] == values) * 2 + (r[:, 3] == values) * 3


def sorted_rows(tets: np.ndarray, local: np.ndarray) -> np.ndarray:
    """(m, r, k) ``np.sort(tets[:, local], axis=2)`` for k = 2 or 3 local vertices
    (``local`` (r, k)), by min / max networks: np.sort over a tiny last axis runs one
    small sort per row, several times slower."""
    cols = [tets[:, local[:, c]] for c in range(local.shape[1])]
    if len(cols) == 2:
        return np.stack([np.minimum(*cols), np.maximum(*cols)], axis=2)
    a, b, c = cols
    lo = np.minimum(np.minimum(a, b), c)
    hi = np.maximum(np.maximum(a, b), c)
    return np.stack([lo, a + b + c - lo - hi, hi], axis=2)  # exact: ints


def faces_at(tets: np.ndarray, on: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(faces (r, 3) sorted vertex triples, owner (r,) tet ids): the faces of ``tets``
    (m, 4) with at least ``k`` vertices where ``on`` (n,) bool, once per tet holding
    them. Only the tets with ``k`` or more corners there hold such a face, and only
    those are read: a few sweeps, not a whole-mesh topology."""
    near = np.flatnonzero(corner_counts(on, tets) >= k)
    faces = sorted_rows(tets[near], TET_FACES).reshape(-1, 3)
    owner = np.repeat(near, 4)
    held = on[faces].sum(axis=1) >= k
    return faces[held], owner[held]


# ``_order_rings`` pads all rings to the largest in one bucket when the padded steps are at
# most this many.
PADDED_RING_SLOTS = 4096

# Above this many queries a binary search sorts them first (see ``search_sorted``).
SORT_QUERIES_ABOVE = 2048


def csr_rows(ptr: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pos, starts): positions of the CSR entries of the groups ``ids`` (g,) one group
    after the other, and where each group's run begins in ``pos`` (g,). Costs in
    proportion to those groups' entries, not to the whole CSR."""
    lens = ptr[ids + 1] - ptr[ids]
    starts = np.cumsum(lens) - lens
    return np.arange(int(lens.sum())) + np.repeat(ptr[ids] - starts, lens), starts


def corner_counts(vertex_mask: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(m,) uint32: how many of the 4 corners of each tet of ``tets`` (m, 4) are in
    ``vertex_mask`` (n,) bool.

    The four gathered bytes of a tet are read as one 32-bit word, whose byte sum the
    multiply by 0x01010101 leaves in its top byte (at most 4: no carries): 10 ms for
    983k tets against 31 ms for ``vertex_mask[tets].sum(axis=1)`` (measured), which
    reduces along rows of 4."""
    corners = np.ascontiguousarray(vertex_mask, bool).view(np.uint8)[tets]
    words = np.ascontiguousarray(corners).view(np.uint32).reshape(-1)
    return (words * np.uint32(0x01010101)) >> np.uint32(24)


def search_sorted(sorted_keys: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """``np.searchsorted(sorted_keys, queries)``, with many queries searched in increasing
    order: consecutive searches then walk the keys in one direction and stay in cache
    (NumPy narrows each search by the previous one for sorted queries). Measured into 2M
    keys: 100k queries 99 -> 25 ms, 5k queries 4.0 -> 1.6 ms, including the sort.
    Queries already in increasing order are not sorted again (one comparison pass)."""
    queries = np.asarray(queries)
    if queries.ndim != 1 or len(queries) <= SORT_QUERIES_ABOVE:
        return np.searchsorted(sorted_keys, queries)
    if (queries[1:] >= queries[:-1]).all():
        return np.searchsorted(sorted_keys, queries)
    order = np.argsort(queries)
    pos = np.empty(len(queries), np.int64)
    pos[order] = np.searchsorted(sorted_keys, queries[order])
    return pos


def sorted_lookup(sorted_keys: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """(q,) index of every query in the increasing unique ``sorted_keys`` (G,), or -1."""
    if len(sorted_keys) == 0:
        return np.full(len(queries), -1, np.int64)
    pos = np.minimum(search_sorted(sorted_keys, queries), len(sorted_keys) - 1)
    return np.where(sorted_keys[pos] == queries, pos, -1)


def _stable_sort(keys: np.ndarray, key_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """(perm, keys[perm]) of a stable sort of non-negative int keys below 2**key_bits.

    Packs (key, index) into one int64 and sorts VALUES when they fit: a SIMD value sort is
    ~10x faster than argsort, and the index in the low bits makes it stable. Keys up to
    twice as wide are sorted in two such passes, low bits first (LSD radix): face keys
    of the 983k-tet mesh (53 bits, 4M keys) 0.66 -> 0.42 s.
    """
    N = len(keys)
    ibits = max(N - 1, 1).bit_length()
    index = (1 << ibits) - 1
    if key_bits + ibits <= 63:
        packed = np.sort((keys.astype(np.int64, copy=False) << ibits) | np.arange(N))
        return packed & index, packed >> ibits
    lo_bits = 63 - ibits
    if key_bits - lo_bits + ibits <= 63:
        k64 = keys.astype(np.int64, copy=False)
        by_lo = np.sort(((k64 & ((1 << lo_bits) - 1)) << ibits) | np.arange(N)) & index
        # stable on the high bits, ties in low-bits order: positions in by_lo break them
        by_hi = np.sort(((k64 >> lo_bits)[by_lo] << ibits) | np.arange(N)) & index
        perm = by_lo[by_hi]
        return perm, keys[perm]
    perm = np.argsort(keys, kind="stable")
    return perm, keys[perm]


def first_of_runs(grouped: np.ndarray) -> np.ndarray:
    """(k,) bool: the first entry of each run of equal values of ``grouped`` (k,)."""
    first = np.ones(len(grouped), bool)
    np.not_equal(grouped[1:], grouped[:-1], out=first[1:])
    return first


def distinct_values(values: np.ndarray) -> np.ndarray:
    """The distinct values of ``values`` (any shape, flattened), increasing: np.unique
    without its hash table, which NumPy 2.4 uses when no index is asked for and which
    took 60x a sort's time on a million distinct int64 values (40 ms against 3 ms on a
    million copies of one label)."""
    values = np.sort(values, axis=None)
    return values[first_of_runs(values)]


def _group(keys: np.ndarray, dtype=np.int64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group equal keys with ONE sort: (perm, ptr, inverse).

    ``perm`` lists entries grouped by key (groups in increasing key order, entries in
    their original order inside a group), ``ptr`` (G+1,) delimits the groups in ``perm``
    and ``inverse`` (N,) is each entry's group id; ``ptr`` and ``inverse`` are ``dtype``
    (the build's ``index_dtype``: no int64 copies to convert). np.unique with
    return_index and return_inverse would sort twice.
    """
    perm, sk = _stable_sort(keys, int(keys.max()).bit_length() if len(keys) else 0)
    new = first_of_runs(sk)
    gid_sorted = np.cumsum(new, dtype=dtype)
    gid_sorted -= 1
    inverse = np.empty(len(keys), dtype)
    inverse[perm] = gid_sorted
    ptr = np.append(np.flatnonzero(new), len(keys)).astype(dtype)
    return perm, ptr, inverse


def _csr(groups: np.ndarray, n_groups: int, dtype=np.int64) -> tuple[np.ndarray, np.ndarray]:
    """(ptr, order): entries sorted by group id, and CSR pointers (``dtype``) per group."""
    order, _ = _stable_sort(groups, max(n_groups - 1, 1).bit_length())
    counts = np.bincount(groups, minlength=n_groups)
    ptr = np.zeros(n_groups + 1, dtype)
    np.cumsum(counts, out=ptr[1:])
    return ptr, order


def _unit(v: np.ndarray) -> np.ndarray:
    nrm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, nrm, out=np.zeros_like(v), where=nrm > 0)


# Below this many tets, the three groupings of a build run one after the other: they
# are then many small NumPy calls that hold the GIL, and two threads trading it cost
# more than they share (builds break even at ~5000 tets: 2000 tets 12.4 ms one after the
# other, 12.7 ms on two threads; 33k tets 88.7 and 80.4 ms).
THREADED_MIN_TETS = 5000


def run_parts(parts: list, n_tets: int, threshold: int | None = None) -> list:
    """``[part() for part in parts]``, on the worker threads for a mesh of ``n_tets``
    tets of at least ``threshold`` (default ``THREADED_MIN_TETS``)."""
    if n_tets < (THREADED_MIN_TETS if threshold is None else threshold):
        return [part() for part in parts]
    from ._config import parallel_map

    return parallel_map(lambda part: part(), parts)


# The fields of ``Topology`` that hold ids or CSR pointers (``index_dtype``).
INDEX_FIELDS = (
    "faces", "tet_faces", "face_tets", "face_apex", "tet_neighbors", "surface_id",
    "edges", "tet_edges", "edge_tets_ptr", "edge_tets", "edge_ring_ptr", "edge_ring",
    "edge_n_subfacets", "vert_tets_ptr", "vert_tets",
)  # fmt: skip


def index_bound(m: int, n: int) -> int:
    """The largest id or pointer value of the topology of m tets and n points: ring
    entries (at most 6m tets plus one chain end per edge) bound every other field."""
    return max(12 * m, n) + 1


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
    surface_id: np.ndarray  # (F,) id of the bounding surface of a subfacet, -1 else
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

    def __post_init__(self):
        # every id / pointer field in one integer type (``index_dtype``): the build and
        # the update make them so directly; this only converts what comes otherwise
        it = self.index_dtype
        for name in INDEX_FIELDS:
            a = getattr(self, name)
            if a.dtype != it:
                object.__setattr__(self, name, a.astype(it))

    @property
    def index_dtype(self) -> type:
        """The integer type of the id and pointer fields (``INDEX_FIELDS``)."""
        return index_dtype(index_bound(len(self.tet_faces), len(self.vert_tets_ptr) - 1))

    @property
    def n_edges(self) -> int:
        return len(self.edges)

    def edge_ring_size(self) -> np.ndarray:
        """(E,) number of tets around each edge."""
        return np.diff(self.edge_tets_ptr)

    @property
    def n_points(self) -> int:
        return len(self.vert_tets_ptr) - 1

    @functools.cached_property
    def face_keys(self) -> np.ndarray | None:
        """(F,) ``row_keys`` of ``faces``, increasing (faces are numbered in key order);
        None when the mesh has too many points for keys that compare across calls."""
        n = self.n_points
        return row_keys(self.faces, n) if float(n) ** 3 < 2.0**62 else None

    @functools.cached_property
    def edge_keys(self) -> np.ndarray:
        """(E,) keys a * n + b of ``edges`` (a < b), increasing (edge numbering order)."""
        return self.edges[:, 0] * np.int64(self.n_points) + self.edges[:, 1]

    def face_ids(self, rows: np.ndarray) -> np.ndarray:
        """(q,) index in ``faces`` of every vertex triple ``rows`` (q, 3), any vertex
        order, or -1. A binary search of the sorted face keys (``match_rows`` would sort
        the whole face table on every call)."""
        rows = np.sort(np.asarray(rows, np.int64).reshape(-1, 3), axis=1)
        if self.face_keys is None:
            return match_rows(self.faces, rows, self.n_points)
        return sorted_lookup(self.face_keys, row_keys(rows, self.n_points))

    def edge_ids(self, pairs: np.ndarray) -> np.ndarray:
        """(q,) index in ``edges`` of every vertex pair ``pairs`` (q, 2), or -1."""
        pairs = np.sort(np.asarray(pairs, np.int64).reshape(-1, 2), axis=1)
        return sorted_lookup(self.edge_keys, pairs[:, 0] * np.int64(self.n_points) + pairs[:, 1])

    @classmethod
    def build(cls, mesh, feature_angle: float = 0.0) -> Topology:
        """Adjacency of ``mesh``.

        ``feature_angle`` (degrees): two subfacets of one surface meeting at an edge whose
        planes deviate by more than this make the edge a subsegment. The default 0 keeps
        only exactly coplanar pairs (decided with the robust orient3d), so every
        transformation that flips such an edge leaves the surface geometrically identical.
        """
        points, tets, region = mesh.points, mesh.tets, mesh.region
        n = len(points)
        it = index_dtype(index_bound(len(tets), n))  # the id and pointer fields' type
        # the three groupings are independent and NumPy's sorts and gathers release the
        # GIL: side by side on the worker threads they take ~0.7x the time of one after
        # the other (182k tets: 0.65 -> 0.46 s). Faces first: a non-conforming mesh
        # reports its face error, as when they ran first.
        face_part, edge_part, vertex_part = run_parts(
            [
                lambda: _face_groups(
                    tets, n, region, mesh.protected_faces, it, mesh.protected_face_labels
                ),
                lambda: _edge_groups(tets, n, it),
                lambda: _vertex_groups(tets, n, it),
            ],
            len(tets),
        )
        faces, subfacet, surface_id = (face_part[k] for k in ("faces", "subfacet", "surface_id"))
        edges, edge_manifold = edge_part["edges"], edge_part["edge_manifold"]

        # ---------------------------------------------------------------- protection
        edge_n_subfacets, subsegment = _subsegments(
            points, faces, subfacet, surface_id, edges, edge_manifold, feature_angle
        )
        if len(mesh.protected_edges):
            idx = match_rows(edges, mesh.protected_edges, n)
            if (idx < 0).any():
                bad = mesh.protected_edges[idx < 0][0].tolist()
                raise MeshInputError(f"protected edge {bad} is not an edge of the mesh")
            subsegment[idx] = True
        vertex_kind, surface_normal, segment_direction = _vertex_kinds(
            points, faces, subfacet, edges, subsegment, n
        )
        pin_vertices(mesh.protected_vertices, vertex_kind, surface_normal, segment_direction)
        return cls(
            **face_part,
            **edge_part,
            **vertex_part,
            edge_n_subfacets=edge_n_subfacets,
            subsegment=subsegment,
            vertex_kind=vertex_kind,
            surface_normal=surface_normal,
            segment_direction=segment_direction,
        )


def _face_groups(
    tets, n: int, region, protected_faces, it, protected_labels
) -> dict[str, np.ndarray]:
    """The face fields of ``Topology`` (faces .. surface_id) of the tets (m, 4) of a mesh
    with n points, ids of type ``it``, protected faces (k, 3) with labels (k,); raises
    ``MeshInputError`` for a face in more than two tets or a protected face that is not
    a face."""
    m = len(tets)
    tf = sorted_rows(tets, TET_FACES).reshape(-1, 3)  # (4m, 3)
    fperm, fptr, inv = _group(row_keys(tf, n), it)
    counts = np.diff(fptr)
    if (counts > 2).any():
        f = int(np.flatnonzero(counts > 2)[0])
        bad = tf[fperm[fptr[f]]].tolist()
        raise MeshInputError(
            f"non-conforming mesh: face {bad} is shared by {int(counts[f])} tets "
            f"({int((counts > 2).sum())} such faces)"
        )
    s0 = fperm[fptr[:-1]]  # first slot (tet * 4 + local vertex) of every face
    faces = np.take(tf, s0, axis=0).astype(it, copy=False)
    F = len(faces)
    tet_faces = inv.reshape(m, 4)
    face_tets = np.full((F, 2), -1, it)
    face_apex = np.full((F, 2), -1, it)
    flat = tets.reshape(-1)
    face_tets[:, 0] = s0 // 4
    face_apex[:, 0] = flat[s0]
    two = counts == 2
    s1 = fperm[fptr[:-1][two] + 1]
    face_tets[two, 1] = s1 // 4
    face_apex[two, 1] = flat[s1]
    side0, side1 = np.take(face_tets[:, 0], tet_faces), np.take(face_tets[:, 1], tet_faces)
    other = np.where(side0 == np.arange(m, dtype=it)[:, None], side1, side0)
    protected = np.zeros(F, bool)
    label = np.zeros(F, np.int64)
    if len(protected_faces):
        idx = match_rows(faces, protected_faces, n)
        if (idx < 0).any():
            bad = protected_faces[idx < 0][0].tolist()
            raise MeshInputError(f"protected face {bad} is not a face of the mesh")
        protected[idx] = True
        label[idx] = protected_labels
    boundary_face, interface_face, subfacet, surface_id = _face_flags(
        face_tets, region, protected, label
    )
    return dict(
        faces=faces,
        tet_faces=tet_faces,
        face_tets=face_tets,
        face_apex=face_apex,
        tet_neighbors=other,
        boundary_face=boundary_face,
        interface_face=interface_face,
        subfacet=subfacet,
        surface_id=surface_id,
    )


def _edge_groups(tets, n: int, it) -> dict[str, np.ndarray]:
    """The edge fields of ``Topology`` (edges .. edge_manifold, rings ordered) of the
    tets (m, 4) of a mesh with n points, ids of type ``it``."""
    m = len(tets)
    te = sorted_rows(tets, TET_EDGES).reshape(-1, 2)  # (6m, 2)
    eperm, eptr, einv = _group(te[:, 0] * np.int64(n) + te[:, 1], it)
    edges = np.take(te, eperm[eptr[:-1]], axis=0).astype(it, copy=False)
    tet_edges = einv.reshape(m, 6)

    c, d = _sorted_steps(tets, n, eperm)
    edge_tets, edge_ring_ptr, edge_ring, edge_boundary, edge_manifold = _order_rings(
        eptr, c, d, (eperm // 6).astype(it, copy=False)
    )
    return dict(
        edges=edges,
        tet_edges=tet_edges,
        edge_tets_ptr=eptr,
        edge_tets=edge_tets,
        edge_ring_ptr=edge_ring_ptr,
        edge_ring=edge_ring,
        edge_boundary=edge_boundary,
        edge_manifold=edge_manifold,
    )


def _sorted_steps(tets, n: int, eperm) -> tuple[np.ndarray, np.ndarray]:
    """(c, d), each (6m,): the ring step c -> d of every (tet, local edge) slot of the
    tets (m, 4), in the order ``eperm`` (6m,) of the slots; int32 when the n point ids
    fit."""
    # the step is oriented w.r.t. the sorted edge: for local edge (i, j) it is
    # v_k -> v_l; if tets[i] > tets[j] the edge is traversed reversed (a and b swapped),
    # which reverses the step.
    if n > np.iinfo(np.int32).max:
        c, d = _slot_steps(tets)
        return c.reshape(-1)[eperm], d.reshape(-1)[eperm]
    # eperm reads the slots at random: one gather of (c, d) int32 pairs as int64 words
    # touches half the cache lines of two int64 gathers (983k tets: 0.36 -> 0.21 s with
    # the steps computed in int32)
    cd = np.empty((len(tets), 6, 2), np.int32)
    cd[:, :, 0], cd[:, :, 1] = _slot_steps(tets.astype(np.int32))
    cd = cd.reshape(-1).view(np.int64)[eperm].view(np.int32).reshape(-1, 2)
    return cd[:, 0], cd[:, 1]


def _slot_steps(tets) -> tuple[np.ndarray, np.ndarray]:
    """(c, d), each (m, 6): the ring step of every local edge of the tets (m, 4)."""
    lo = tets[:, TET_EDGES[:, 0]]
    hi = tets[:, TET_EDGES[:, 1]]
    ck = tets[:, _EDGE_OTHERS[:, 0]]
    cl = tets[:, _EDGE_OTHERS[:, 1]]
    swap = lo > hi
    return np.where(swap, cl, ck), np.where(swap, ck, cl)


def _vertex_groups(tets, n: int, it) -> dict[str, np.ndarray]:
    """vert_tets_ptr (n+1,) and vert_tets (type ``it``) of ``Topology``: the tets around
    each vertex, increasing."""
    vert_tets_ptr, vorder = _csr(tets.reshape(-1), n, it)
    return dict(vert_tets_ptr=vert_tets_ptr, vert_tets=(vorder // 4).astype(it))


def _face_flags(face_tets, region, protected, label):
    """Boundary, interface, subfacet flags (F,) and surface ids (F,) of every face.

    ``face_tets`` (F, 2) with -1 in slot 1 for a boundary face, ``region`` (m,) tet labels,
    ``protected`` (F,) bool user-protected faces, ``label`` (F,) their labels. Shared by
    ``Topology.build`` and the incremental update so both give identical arrays.
    """
    boundary_face, interface_face, subfacet = _face_kinds(face_tets, region, protected)
    surface_id = _surface_ids(face_tets, region, boundary_face, interface_face, protected, label)
    return boundary_face, interface_face, subfacet, surface_id


def _face_kinds(face_tets, region, protected):
    """(boundary, interface, subfacet) flags, each (F,), of faces ``face_tets`` (F, 2)."""
    two = face_tets[:, 1] >= 0
    boundary_face = ~two
    r0 = region[face_tets[:, 0]]
    r1 = np.where(two, region[np.maximum(face_tets[:, 1], 0)], r0)
    interface_face = two & (r0 != r1)
    return boundary_face, interface_face, boundary_face | interface_face | protected


def _surface_ids(face_tets, region, boundary_face, interface_face, protected, label):
    """(F,) id of the bounding surface of every subfacet (-1 elsewhere): the rank of its
    surface kind among the kinds present, so it depends on the subfacets only."""
    # Surface identity: the (region, region) pair it separates, whether the user
    # protected it and with which label: protected faces inside one region form surfaces
    # of their own, and a protected patch of the boundary or of an interface (each label
    # its own) is a surface apart from the rest of it, so the edges around the patch are
    # subsegments and no flip moves its border.
    sub = np.flatnonzero(boundary_face | interface_face | protected)
    ft = face_tets[sub]
    two = ft[:, 1] >= 0
    r0 = region[ft[:, 0]]
    r1 = np.where(two, region[np.maximum(ft[:, 1], 0)], r0)
    rmin, rmax = np.minimum(r0, r1), np.maximum(r0, r1)
    c0 = np.where(boundary_face[sub], -1, rmin)
    # 0: not protected; 1 + the rank of the label among the protected faces' labels
    prot = protected[sub]
    labels, lrank = np.unique(label[sub][prot], return_inverse=True)
    c2 = np.zeros(len(sub), np.int64)
    c2[prot] = 1 + lrank.reshape(-1)
    # rank of the row (c0, rmax, c2) among the distinct rows, as np.unique(axis=0) would
    # give, from one 1-D key: values replaced by their rank keep the lexicographic order
    vals, vrank = np.unique(np.concatenate([c0, rmax]), return_inverse=True)
    vrank = vrank.reshape(-1)
    code = (vrank[: len(sub)] * np.int64(len(vals)) + vrank[len(sub) :]) * (1 + len(labels)) + c2
    _, surface_code = np.unique(code, return_inverse=True)
    surface_id = np.full(len(face_tets), -1, face_tets.dtype)
    surface_id[sub] = surface_code.reshape(-1)
    return surface_id


def _subsegments(points, faces, subfacet, surface_id, edges, edge_manifold, feature_angle):
    """(E,) number of subfacets on each edge and (E,) subsegment flags.

    ``edges`` (E, 2) must be sorted by key a * n + b (as built). User-protected edges are
    added by the caller.
    """
    n, E = len(points), len(edges)
    sub = np.flatnonzero(subfacet)
    # subfacets containing each edge: every face has 3 edges
    sfaces = faces[sub]
    fe = np.stack([sfaces[:, [0, 1]], sfaces[:, [0, 2]], sfaces[:, [1, 2]]], 1).reshape(-1, 2)
    ekeys_u = edges[:, 0] * np.int64(n) + edges[:, 1]  # sorted: edges come from a sort
    sf_edge = search_sorted(ekeys_u, fe[:, 0] * np.int64(n) + fe[:, 1])
    sf_face = np.repeat(sub, 3)
    edge_n_subfacets = np.bincount(sf_edge, minlength=E).astype(edges.dtype, copy=False)
    subsegment = (edge_n_subfacets != 0) & (edge_n_subfacets != 2)
    subsegment |= ~edge_manifold
    # edges with exactly two subfacets: same surface and coplanar?
    pair_edges = np.flatnonzero(edge_n_subfacets == 2)
    if len(pair_edges):
        optr, oorder = _csr(sf_edge, E)
        f1 = sf_face[oorder[optr[pair_edges]]]
        f2 = sf_face[oorder[optr[pair_edges] + 1]]
        subsegment[pair_edges] |= _pair_bent(
            points, faces, surface_id, edges[pair_edges], f1, f2, feature_angle
        )
    return edge_n_subfacets, subsegment


def _pair_bent(points, faces, surface_id, ab, f1, f2, feature_angle):
    """(k,) bool: edges ``ab`` (k, 2) whose two subfacets ``f1`` < ``f2`` (face ids) lie
    on different surfaces or are not coplanar (within ``feature_angle``)."""
    diff_surface = surface_id[f1] != surface_id[f2]
    a, b = ab[:, 0], ab[:, 1]
    third1 = faces[f1].sum(1) - a - b
    third2 = faces[f2].sum(1) - a - b
    return diff_surface | _bent(points, a, b, third1, third2, feature_angle)


def _order_rings(ptr, c, d, entry_tet):
    """Order the ring steps c -> d of every edge into its ring.

    Entries come grouped by edge (CSR ``ptr``). Each edge's steps form one cycle (interior
    edge) or one path (boundary edge) in a manifold mesh. Edges are processed in buckets of
    equal ring size k: within a bucket the successor of every step is found by comparing
    the k steps with each other (``_ring_links``), then the ring is walked in k vectorized
    steps (``_ring_walk``). Cache-friendly and O(sum E_k k^2) with k ~ 5 on average.
    ``c`` and ``d`` may be int32 (half the bytes to gather and compare).

    Returns the tets in ring order (CSR as ``ptr``), CSR ring vertices (``ptr``'s type;
    a chain gets its final vertex appended), the boundary flag and a manifold flag per
    edge.
    """
    E = len(ptr) - 1
    counts = np.diff(ptr)
    src = np.empty(len(c), np.int64)  # entry at each ring position
    edge_boundary = np.zeros(E, bool)
    edge_manifold = np.zeros(E, bool)
    chain_end = np.full(E, -1, np.int64)
    kmax = int(counts.max(initial=0))
    if E == 0:  # no edge to order (an incremental update of a step that changed no tet)
        buckets = []
    elif 0 < E * kmax <= PADDED_RING_SLOTS:
        # few edges (the step updates of small meshes): one bucket padded to the largest
        # ring, ~8 ring sizes' worth of fixed NumPy calls saved
        buckets = [(np.arange(E), kmax, counts)]
    else:  # one bucket per ring size (length None: no padding); edges by ring size (ids
        # increasing within a size): one value sort, not a scan of the (E,) counts per size
        by_size, sizes = _stable_sort(counts, max(kmax, 1).bit_length())
        cut = np.flatnonzero(np.r_[True, sizes[1:] != sizes[:-1], True])
        buckets = [(by_size[b0:b1], int(sizes[b0]), None) for b0, b1 in zip(cut[:-1], cut[1:])]
    for es, k, length in buckets:  # a loop over ring sizes, each bucket vectorized
        base = ptr[es]
        slots = base[:, None] + np.arange(k)  # (E_k, k)
        if length is None:
            cc, dd = c[slots], d[slots]
        else:  # padded steps never link: sentinels that match no vertex nor each other
            real = np.arange(k) < length[:, None]
            slots = np.where(real, slots, 0)
            cc, dd = np.where(real, c[slots], -1), np.where(real, d[slots], -2)
        order, ok, n_starts = _ring_walk(*_ring_links(cc, dd), length)
        if length is None:
            src[slots] = base[:, None] + order
            last = order[:, -1]
        else:
            src[slots[real]] = (base[:, None] + order)[real]
            last = order[np.arange(len(es)), np.maximum(length - 1, 0)]
        edge_boundary[es] = n_starts >= 1
        edge_manifold[es] = ok
        bnd = ok & (n_starts == 1)
        chain_end[es[bnd]] = d[base[bnd] + last[bnd]]
    # ring vertices: c of each step; chains also get d of their last step, inserted after
    # their run (a mask, not a scatter of every entry through the ring CSR)
    edge_ring_ptr = np.zeros(E + 1, ptr.dtype)
    np.cumsum(counts + edge_boundary, out=edge_ring_ptr[1:])
    bnd = np.flatnonzero(edge_boundary)
    ends = edge_ring_ptr[bnd + 1] - 1
    steps = np.ones(edge_ring_ptr[-1], bool)
    steps[ends] = False
    edge_ring = np.empty(edge_ring_ptr[-1], ptr.dtype)
    edge_ring[steps] = c[src]
    edge_ring[ends] = chain_end[bnd]
    return entry_tet[src], edge_ring_ptr, edge_ring, edge_boundary, edge_manifold


def _ring_links(cc, dd):
    """(succ, n_next, n_prev), each (E_k, k), of the ring steps cc -> dd (E_k, k) of E_k
    edges: how many steps follow / precede each step, and the position of its successor
    where it has exactly one (any value below k elsewhere).

    A loop over the k positions of (E_k, k) compares: measured 2-2.5x faster than one
    (E_k, k, k) comparison reduced over its small axes (argmax, sums), k = 4..7.
    """
    E_k, k = cc.shape
    dt = np.uint8 if k < 256 else np.int64  # counts <= k
    n_next, n_prev, succ = (np.zeros((E_k, k), dt) for _ in range(3))
    for j in range(k):
        m = (dd == cc[:, j : j + 1]).astype(dt, copy=False)  # step j follows step i
        n_next += m
        succ += m * dt(j)  # wraps only where n_next > 1, where it is not used
        n_prev += (cc == dd[:, j : j + 1]).astype(dt, copy=False)
    return succ, n_next, n_prev


def _ring_walk(succ, n_next, n_prev, length=None):
    """(order (E_k, k), ok (E_k,), n_starts (E_k,)) of ``_ring_links``' output: the step
    positions in ring order, from the only step without a predecessor (chain) or from
    step 0 (cycle); ok where the steps form one chain or one cycle (else the order is
    0..k-1); the number of steps without a predecessor. ``length`` (E_k,): rows whose
    steps are only their first ``length`` columns (the rest padding that links to
    nothing); only those columns of ``order`` are meaningful."""
    E_k, k = succ.shape
    # row reductions as loops over the k columns: ~6x faster than .all / .sum / .argmax
    # along rows of ~5
    n_starts = np.zeros(E_k, np.int64)
    start = np.zeros(E_k, np.int64)
    bad = np.zeros(E_k, bool)
    for j in reversed(range(k)):
        s = n_prev[:, j] == 0
        if length is not None:
            s &= j < length
        n_starts += s
        np.copyto(start, j, where=s)  # the first start (only one where ok)
        bad |= (n_prev[:, j] > 1) | (n_next[:, j] > 1)
    ok = ~bad & (n_starts <= 1)
    # a step with no successor leads back to the start: a walk that ends early then
    # revisits the start, like one around a cycle shorter than k
    flat = np.where(n_next == 1, succ, start[:, None]).reshape(-1)
    rk = np.arange(E_k) * k
    order = np.empty((E_k, k), np.int64)
    order[:, 0] = pos = start
    for step in range(1, k):
        pos = flat[rk + pos]
        order[:, step] = pos
        ok &= (pos != start) if length is None else (pos != start) | (step >= length)
    order[~ok] = np.arange(k)
    return order, ok, n_starts


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
    """Classify vertices for smoothing: FREE, SURFACE (flat), SEGMENT (straight), CORNER.

    ``_vertex_kinds_at`` of every vertex, from its subfacet and subsegment incidences.
    """
    return _vertex_kinds_at(
        points,
        np.arange(n),
        _incidences(faces, subfacet, n),
        faces,
        _incidences(edges, subsegment, n),
        edges,
    )


def _incidences(rows: np.ndarray, selected: np.ndarray, n: int) -> np.ndarray:
    """(k, 2) pairs (vertex, row id) of the ``selected`` (bool) rows of ``rows`` (r, c),
    sorted by vertex then row id."""
    ids = np.flatnonzero(selected)
    verts = rows[ids].reshape(-1)
    order, _ = _stable_sort(verts, max(n - 1, 1).bit_length())  # row ids stay ascending
    return np.column_stack([verts[order], np.repeat(ids, rows.shape[1])[order]])


def pin_vertices(protected, kind, normal, direction) -> None:
    """Make the ``protected`` (k,) vertices corners, in place in ``kind`` (n,), ``normal``
    and ``direction`` (n, 3): smoothing and kicks never move a corner."""
    kind[protected] = CORNER
    normal[protected] = 0.0
    direction[protected] = 0.0


def _vertex_kinds_at(points, vids, vf, faces, ve, edges):
    """Kinds (FREE, SURFACE, SEGMENT, CORNER), surface normals and segment directions of
    the vertices ``vids`` (V,), from their incidences.

    ``vf`` (k, 2): pairs (index into ``vids``, id of a subfacet at that vertex) and ``ve``
    (l, 2): pairs (index into ``vids``, id of a subsegment at that vertex), each sorted
    by vertex then id, so a vertex's normals are summed in one fixed order whether all
    vertices are classified (``_vertex_kinds``) or a few (the incremental update): the
    results are bit-identical. Returns (kind, normal, direction).
    """
    V = len(vids)
    kind = np.zeros(V, np.int8)
    normal = np.zeros((V, 3))
    direction = np.zeros((V, 3))
    on_surface = np.zeros(V, bool)
    on_surface[vf[:, 0]] = True
    kind[on_surface] = SURFACE
    # surface normal: area-weighted sum of the (consistently unoriented) subfacet normals;
    # sign-align each normal to the first one seen at the vertex so they do not cancel.
    if len(vf):
        p = points[faces[vf[:, 1]]]
        fn = _unit(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
        first = np.flatnonzero(np.r_[True, vf[1:, 0] != vf[:-1, 0]])
        ref = np.zeros((V, 3))
        ref[vf[first, 0]] = fn[first]
        sgn = np.sign(np.einsum("ij,ij->i", fn, ref[vf[:, 0]]))
        sgn[sgn == 0] = 1.0
        np.add.at(normal, vf[:, 0], fn * sgn[:, None])
        normal = _unit(normal)
    nseg = np.bincount(ve[:, 0], minlength=V)
    kind[nseg > 2] = CORNER
    kind[nseg == 1] = CORNER
    two = np.flatnonzero(nseg == 2)
    if len(two):
        at = np.searchsorted(ve[:, 0], two)
        v = vids[two]
        o1 = edges[ve[at, 1]].sum(1) - v
        o2 = edges[ve[at + 1, 1]].sum(1) - v
        u1 = points[o1] - points[v]
        u2 = points[v] - points[o2]
        cr = np.linalg.norm(np.cross(u1, u2), axis=1)
        scale = np.linalg.norm(u1, axis=1) * np.linalg.norm(u2, axis=1)
        straight = (cr <= 1e-12 * scale) & (np.einsum("ij,ij->i", u1, u2) > 0)
        kind[two] = np.where(straight, SEGMENT, CORNER)
        direction[two[straight]] = _unit(u1[straight] + u2[straight])
    # a surface vertex whose subfacets are not all coplanar is held by subsegments
    # (flatness is decided edge by edge above); SURFACE keeps its normal only.
    normal[kind != SURFACE] = 0.0
    return kind, normal, direction
