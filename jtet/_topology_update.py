"""Incremental topology: the adjacency of a mesh after a flip step, from the one before.

A flip step (``jtet._apply.replace_tets``) keeps most tets in their order and appends a
few new ones. Rebuilding the topology from scratch sorts every face and edge and orders
every ring again; here only the faces, edges and vertices of removed and new tets are
regrouped and reordered, and the rest is carried over with renumbered tets. The cheap
global per-face / per-edge / per-vertex passes (surface flags and ids, subsegments,
vertex kinds) reuse ``Topology.build``'s own helpers on the new arrays, so every field
is identical to ``Topology.build(new_mesh)`` by construction.

Whenever a precondition fails (large change, a mesh that is not the old one minus some
tets plus appended ones, an error the full build would report) the full build runs.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._topology import (
    _EDGE_OTHERS,
    TET_EDGES,
    TET_FACES,
    Topology,
    _face_kinds,
    _group,
    _order_rings,
    _pair_bent,
    _subsegments,
    _surface_ids,
    _vertex_kinds,
    _vertex_kinds_at,
    csr_rows,
    index_bound,
    index_dtype,
    local_index,
    pin_vertices,
    row_keys,
    run_parts,
    sorted_lookup,
)

# Above this fraction of the edges (vertices) to redo, the edge protection flags (vertex
# kinds) are recomputed for all edges (vertices): the same arrays, found faster by the
# global pass (measured crossover on a 182k-tet cube: ~5-10 %).
LOCAL_FRACTION = 0.05
# Below this many tets the update's three parts run one after the other (see
# ``_topology.run_parts``). Its parts are lighter than a build's, so the threads pay off
# later; small steps of the holeplate and Gmsh cubes, one after the other / on two
# threads: 1092 tets 5.5 / 7.8 ms, 5338 tets 6.4 / 9.4 ms, 31.6k tets 22.9 / 27.6 ms, 53k
# tets 27.6 / 23.5 ms, 169k tets 74.8 / 53.2 ms.
UPDATE_THREADED_MIN_TETS = 40_000
# Above this fraction of changed tets (removed + added, relative to the old count) the
# full build runs. Measured on a 182k-tet cube (same process, loaded machine): the
# update takes 1.1x the build's time at 47 % changed (the first flip step of an
# unoptimized mesh), 0.74x at 25 %, 0.2-0.25x below 2 %.
MAX_CHANGE = 0.4
# From LARGE_MESH_TETS tets, MAX_CHANGE_LARGE instead: the build's sorts then cost more
# per tet, and the first edge step of an unoptimized mesh (47 % changed) is updated
# faster than built. Four alternating pairs each, the first edge step: 182k-tet cube
# update 0.19-0.25 s, build 0.19-0.25 s; 583k two-region ball in a box 0.67-0.83 /
# 0.74-0.91 s; 983k cube 1.10-1.51 / 1.30-1.61 s, and the whole 983k run (--perturb 0,
# three alternating pairs) 0.25-0.74 s faster, peak RSS 2.02 -> 2.18 GB (session 54).
LARGE_MESH_TETS = 500_000
MAX_CHANGE_LARGE = 0.55


def max_change(n_tets: int) -> float:
    """The largest fraction of changed tets that an update handles for a mesh of
    ``n_tets`` tets (``MAX_CHANGE``, ``MAX_CHANGE_LARGE``); above it the full build runs."""
    return MAX_CHANGE_LARGE if n_tets >= LARGE_MESH_TETS else MAX_CHANGE


def update_topology(
    old: Topology,
    old_mesh,
    new_mesh,
    keep: np.ndarray,
    feature_angle: float | None = None,
    fallback: bool = True,
    kept_first: bool = False,
) -> Topology | None:
    """``Topology.build(new_mesh, feature_angle)``, derived from ``old`` (of ``old_mesh``).

    ``new_mesh.tets`` must be ``old_mesh.tets[keep]`` followed by new tets (``keep`` (m,)
    bool), with the same points and protected edges; ``old`` must have been built with
    the same ``feature_angle`` (None: the new mesh's own, which its ``topology`` uses).
    Otherwise, or for a large change, or when the full build would raise (non-conforming
    faces, missing protected entities), it runs the full build (``fallback``) or returns
    None. ``kept_first=True``: the caller built ``new_mesh``'s tets and regions as
    ``old_mesh``'s kept ones followed by the new ones (``_apply.replace_tets``), so that
    is not compared again (two gathers and compares of every tet: ~24 ms per step at
    983k tets).
    """
    if feature_angle is None:
        feature_angle = new_mesh._feature_angle
    keep = np.asarray(keep, bool)
    if _compatible(old, old_mesh, new_mesh, keep, kept_first):
        topo = _update(old, old_mesh, new_mesh, keep, feature_angle)
        if topo is not None:
            return topo
    return Topology.build(new_mesh, feature_angle) if fallback else None


def _compatible(old: Topology, old_mesh, new_mesh, keep: np.ndarray, kept_first: bool) -> bool:
    """Whether ``new_mesh`` is ``old_mesh`` with the tets where ~keep replaced by appended
    ones (taken as given with ``kept_first``), small enough a change, and face keys that
    compare across meshes."""
    m0, n = old_mesh.n_tets, old_mesh.n_points
    if keep.shape != (m0,) or len(old.tet_faces) != m0 or new_mesh.n_points != n:
        return False
    K = int(keep.sum())
    m1 = new_mesh.n_tets
    if m1 < K or (m0 - K) + (m1 - K) > max_change(m0) * m0:
        return False
    if index_dtype(index_bound(m1, n)) != old.index_dtype:  # ids outgrew int32
        return False
    # row_keys switches to per-call ranks for huge n: keys would not compare across meshes
    if float(n) ** 3 >= 2.0**62:
        return False
    if new_mesh.points is not old_mesh.points and not np.array_equal(
        new_mesh.points, old_mesh.points
    ):
        return False
    if not np.array_equal(new_mesh.protected_edges, old_mesh.protected_edges):
        return False
    if not np.array_equal(new_mesh.protected_vertices, old_mesh.protected_vertices):
        return False
    return kept_first or (
        np.array_equal(new_mesh.tets[:K], old_mesh.tets[keep])
        and np.array_equal(new_mesh.region[:K], old_mesh.region[keep])
    )


def _update(old: Topology, old_mesh, new_mesh, keep, feature_angle) -> Topology | None:
    """The incremental update proper; None when the full build must decide (errors)."""
    points, tets, region = new_mesh.points, new_mesh.tets, new_mesh.region
    n, m0 = len(points), len(keep)
    K = int(keep.sum())
    removed = np.flatnonzero(~keep)
    keep_idx = np.flatnonzero(keep)
    # old tet id -> new id, -1 for removed tets; renum[-1] == -1 maps "no tet" to itself.
    # Id maps are int32 while the ids fit: whole-mesh renumbering gathers read their map
    # at random, and an int32 map (half the bytes) stays in cache where an int64 one does
    # not (2-4x faster for 4-6M ids through the 1M-entry tet map or the 2M-entry face map
    # of a 983k-tet mesh; 6M ids through a 6M-entry map 1.3x)
    renum = np.full(m0 + 1, -1, index_dtype(m0 + 1))
    renum[keep_idx] = np.arange(K)

    def faces_and_flags():
        fu = _update_faces(old, tets, keep, keep_idx, removed, renum, n)
        return fu, None if fu is None else _update_face_flags(old, old_mesh, new_mesh, fu, region)

    # faces, edges and vertices are regrouped independently: side by side on the worker
    # threads (NumPy's sorts and gathers release the GIL), as in ``Topology.build``
    (fu, flags), eu, (vert_tets_ptr, vert_tets) = run_parts(
        [
            faces_and_flags,
            lambda: _update_edges(old, tets, keep, keep_idx, removed, renum, n),
            lambda: _update_vertices(old, old_mesh.tets, tets, keep, removed, renum),
        ],
        len(tets),
        UPDATE_THREADED_MIN_TETS,
    )
    if fu is None or flags is None:
        return None  # the full build reports the non-conforming or missing face
    boundary_face, interface_face, subfacet, surface_id, prot_changed = flags

    pe = new_mesh.protected_edges
    pe_ids = _lookup(eu.keys, pe[:, 0] * np.int64(n) + pe[:, 1])
    if (pe_ids < 0).any():
        return None
    # edges whose subfacets may have changed: the regrouped ones (every edge of a
    # regrouped face is one) and those of faces whose user protection changed
    fe = fu.faces[prot_changed][:, [[0, 1], [0, 2], [1, 2]]].reshape(-1, 2)
    affected = _ids(len(eu.edges), eu.redo, _lookup(eu.keys, fe[:, 0] * np.int64(n) + fe[:, 1]))
    if len(affected) > LOCAL_FRACTION * len(eu.edges):  # the global pass is cheaper
        edge_n_subfacets, subsegment = _subsegments(
            points, fu.faces, subfacet, surface_id, eu.edges, eu.manifold, feature_angle
        )
    else:
        # (added edges read the last old edge's flags, then are overwritten: all affected)
        edge_n_subfacets = np.take(old.edge_n_subfacets, eu.src, mode="clip")
        subsegment = np.take(old.subsegment, eu.src, mode="clip")
        cnt, seg = _edge_subsegments(
            points, tets, fu, subfacet, surface_id, eu, affected, feature_angle, n
        )
        edge_n_subfacets[affected] = cnt
        subsegment[affected] = seg
    subsegment[pe_ids] = True

    # vertices whose subfacets or subsegments may have changed
    vf = np.concatenate(
        [
            fu.faces[fu.redo[subfacet[fu.redo]]].reshape(-1),
            old.faces[fu.touched[old.subfacet[fu.touched]]].reshape(-1),
            fu.faces[prot_changed].reshape(-1),
        ]
    )
    vs = np.concatenate(
        [
            eu.edges[affected[subsegment[affected]]].reshape(-1),
            old.edges[eu.touched[old.subsegment[eu.touched]]].reshape(-1),
            eu.edges[affected].reshape(-1) if len(prot_changed) else np.zeros(0, np.int64),
        ]
    )
    vids = _ids(n, vf, vs)
    if len(vids) > LOCAL_FRACTION * n:
        vertex_kind, surface_normal, segment_direction = _vertex_kinds(
            points, fu.faces, subfacet, eu.edges, subsegment, n
        )
    else:
        vertex_kind, surface_normal, segment_direction = _update_vertex_kinds(
            old, points, tets, fu, subfacet, eu, subsegment, vert_tets_ptr, vert_tets, vids
        )
    pin_vertices(new_mesh.protected_vertices, vertex_kind, surface_normal, segment_direction)
    topo = Topology(
        faces=fu.faces,
        tet_faces=fu.tet_faces,
        face_tets=fu.face_tets,
        face_apex=fu.face_apex,
        tet_neighbors=fu.tet_neighbors,
        boundary_face=boundary_face,
        interface_face=interface_face,
        subfacet=subfacet,
        surface_id=surface_id,
        edges=eu.edges,
        tet_edges=eu.tet_edges,
        edge_tets_ptr=eu.edge_tets_ptr,
        edge_tets=eu.edge_tets,
        edge_ring_ptr=eu.ring_ptr,
        edge_ring=eu.ring,
        edge_boundary=eu.boundary,
        edge_manifold=eu.manifold,
        edge_n_subfacets=edge_n_subfacets,
        subsegment=subsegment,
        vert_tets_ptr=vert_tets_ptr,
        vert_tets=vert_tets,
        vertex_kind=vertex_kind,
        surface_normal=surface_normal,
        segment_direction=segment_direction,
    )
    # the sorted keys are known: the next step's lookups need not recompute them
    topo.__dict__["face_keys"] = fu.keys
    topo.__dict__["edge_keys"] = eu.keys
    return topo


def _update_face_flags(old: Topology, old_mesh, new_mesh, fu, region):
    """(boundary, interface, subfacet, surface_id) of the new faces, and the (new) ids of
    the faces whose user protection or its label changed; None if a protected face is
    missing.

    Carried faces keep their tets and regions, hence their flags; regrouped faces and
    those whose protection changed are recomputed. Surface ids rank the surface kinds
    present, so they are recomputed over all subfacets (a few percent of the faces).
    """
    n = new_mesh.n_points
    F1 = len(fu.faces)
    p_new = _lookup(fu.keys, row_keys(new_mesh.protected_faces, n))
    if (p_new < 0).any():
        return None
    p_old = fu.fmap[_lookup(old.face_keys, row_keys(old_mesh.protected_faces, n))]
    was = p_old >= 0
    # the faces whose protection or label changed (a label change moves surface borders),
    # from the protected faces alone: no whole-mesh arrays per step
    both, i_new, i_old = np.intersect1d(p_new, p_old[was], return_indices=True)
    relabelled = both[
        new_mesh.protected_face_labels[i_new] != old_mesh.protected_face_labels[was][i_old]
    ]
    prot_changed = np.union1d(np.setxor1d(p_new, p_old[was]), relabelled)
    protected = np.zeros(F1, bool)
    protected[p_new] = True
    label = np.zeros(F1, np.int64)
    label[p_new] = new_mesh.protected_face_labels
    src = fu.src  # added faces (src >= F0, clipped) are all regrouped
    boundary_face = np.take(old.boundary_face, src, mode="clip")
    interface_face = np.take(old.interface_face, src, mode="clip")
    subfacet = np.take(old.subfacet, src, mode="clip")
    redo = _ids(F1, fu.redo, prot_changed)
    b, i, sf = _face_kinds(fu.face_tets[redo], region, protected[redo])
    boundary_face[redo], interface_face[redo], subfacet[redo] = b, i, sf
    surface_id = _surface_ids(fu.face_tets, region, boundary_face, interface_face, protected, label)
    return boundary_face, interface_face, subfacet, surface_id, prot_changed


def _edge_subsegments(points, tets, fu, subfacet, surface_id, eu, eids, feature_angle, n):
    """(number of subfacets, subsegment flag) of the edges ``eids`` (k,), as
    ``_subsegments`` computes them (user-protected edges are added by the caller).

    The faces around an edge are (a, b, o) for the two other vertices o of each of its
    tets; their subfacets, in face id order, are the ones ``_subsegments`` pairs up.
    """
    pos, owner = _csr_take(eu.edge_tets_ptr, eids)
    t = tets[eu.edge_tets[pos]]  # (q, 4)
    ab = eu.edges[eids][owner]
    other = (t != ab[:, :1]) & (t != ab[:, 1:])
    o = t[other].reshape(-1, 2)
    own2 = np.repeat(owner, 2)
    rows = np.sort(np.column_stack([np.repeat(ab, 2, axis=0), o.reshape(-1)]), axis=1)
    fid = _lookup(fu.keys, row_keys(rows, n))
    on = subfacet[np.maximum(fid, 0)] & (fid >= 0)
    key = np.unique(own2[on] * np.int64(len(fu.faces)) + fid[on])  # (edge, face) sorted
    e_loc, f = key // len(fu.faces), key % len(fu.faces)
    cnt = np.bincount(e_loc, minlength=len(eids))
    seg = ((cnt != 0) & (cnt != 2)) | ~eu.manifold[eids]
    pair = np.flatnonzero(cnt == 2)
    if len(pair):
        at = np.searchsorted(e_loc, pair)
        seg[pair] |= _pair_bent(
            points, fu.faces, surface_id, eu.edges[eids[pair]], f[at], f[at + 1], feature_angle
        )
    return cnt, seg


def _update_vertex_kinds(old, points, tets, fu, subfacet, eu, subsegment, vptr, vtets, vids):
    """(vertex_kind, surface_normal, segment_direction): the old ones, with the vertices
    ``vids`` recomputed from their subfacets and subsegments (found through their tets).

    A vertex's kind, normal and direction depend only on the subfacets and subsegments
    at it, met in face / edge id order, i.e. in key order, which renumbering keeps.
    """
    kind = old.vertex_kind.copy()
    normal = old.surface_normal.copy()
    direction = old.segment_direction.copy()
    if len(vids) == 0:
        return kind, normal, direction
    pos, owner = _csr_take(vptr, vids)
    t = vtets[pos]
    v = vids[owner]
    lv = tets[t] == v[:, None]  # (q, 4)
    # faces of t that contain v (those opposite the other three vertices), edges of t
    # that contain v
    vf = _incident_pairs(owner, fu.tet_faces[t], ~lv, subfacet)
    ve = _incident_pairs(
        owner, eu.tet_edges[t], lv[:, TET_EDGES[:, 0]] | lv[:, TET_EDGES[:, 1]], subsegment
    )
    k, nrm, d = _vertex_kinds_at(points, vids, vf, fu.faces, ve, eu.edges)
    kind[vids], normal[vids], direction[vids] = k, nrm, d
    return kind, normal, direction


# -------------------------------------------------------------------------- helpers


def _incident_pairs(owner, ids, has, selected) -> np.ndarray:
    """(k, 2) distinct pairs (owner, id), sorted by owner then id, of the entries of
    ``ids`` (q, c) where ``has`` (q, c) and ``selected[id]``; ``owner`` (q,) per row."""
    own = np.broadcast_to(owner[:, None], ids.shape)[has]
    idv = ids[has]
    on = selected[idv]
    count = np.int64(len(selected))
    key = np.unique(own[on] * count + idv[on])
    return np.column_stack([key // count, key % count])


_lookup = sorted_lookup


def _ids(size: int, *parts: np.ndarray) -> np.ndarray:
    """Sorted distinct ids (< ``size``) of all ``parts``: a mask, not np.unique (which
    hashes or sorts; a mask of a few hundred thousand bools costs well under a ms)."""
    mask = np.zeros(size, bool)
    for p in parts:
        mask[p.reshape(-1)] = True
    return np.flatnonzero(mask)


class _NewKeys(NamedTuple):
    """The keys of the new tets' faces (edges), deduplicated once: sorted queries make
    the binary searches into the large old key arrays cache-friendly."""

    ukeys: np.ndarray  # (U,) sorted unique keys
    first: np.ndarray  # (U,) index of each one's first occurrence
    inverse: np.ndarray  # (q,) index into ukeys of every key
    hit: np.ndarray  # (U,) old id with that key, or -1


def _new_keys(old_keys: np.ndarray, keys: np.ndarray) -> _NewKeys:
    # np.unique(keys, return_index=True, return_inverse=True), by build's one packed value
    # sort (664k edge keys of a 983k-tet step: 48 -> 20 ms)
    perm, ptr, inverse = _group(keys)
    first = perm[ptr[:-1]]
    ukeys = keys[first]
    return _NewKeys(ukeys, first, inverse, _lookup(old_keys, ukeys))


def _merge(old_keys, dead, nk: _NewKeys):
    """Sorted keys of the new entity set: surviving old keys plus new candidate keys.

    ``old_keys`` (G0,) sorted unique, ``dead`` (D,) sorted ids of the old entities that
    do not survive, ``nk`` the candidate keys (duplicates and already-present ones
    allowed). Returns ``keys`` (G1,) sorted, ``gmap`` (G0,) new id of each old entity (-1
    if gone; int32 when the ids fit, ``index_dtype``), ``src`` (G1,) where each new
    entity comes from (an old id, or G0 + j for the j-th added key), ``add_src`` (A,) the
    index among the candidates of each added key and ``add_pos`` (A,) its new id. Only
    the few added and dead entities are searched; ``gmap`` and ``src`` are piecewise
    shifted ranges, made by one cumulative sum each (no whole-set sort or mask).
    """
    G0 = len(old_keys)
    is_dead = np.zeros(G0 + 1, bool)  # a mask, not a search of the hits in dead
    is_dead[dead] = True
    fresh = (nk.hit < 0) | is_dead[nk.hit]
    add, add_src = nk.ukeys[fresh], nk.first[fresh]
    A, D = len(add), len(dead)
    G1 = G0 - D + A
    ins = np.searchsorted(old_keys, add)  # old ids below each added key: ins[j]
    add_pos = np.arange(A) + ins - np.searchsorted(dead, ins)
    # survivor i moves by the added keys below it minus the dead ids below it
    gmap = _shifted_range(G0, ins, dead + 1, index_dtype(max(G0, G1)))
    gmap[dead] = -1
    # new id j of a survivor comes from j + (dead ids before it) - (added keys before j)
    up = dead - np.arange(D) + np.searchsorted(ins, dead, side="right")
    src = _shifted_range(G1, up, add_pos + 1, np.int64)
    src[add_pos] = G0 + np.arange(A)
    keys = np.take(old_keys, src, mode="clip")  # added ones (src >= G0) overwritten
    keys[add_pos] = add
    return keys, gmap, src, add_src, add_pos


def _shifted_range(size: int, up: np.ndarray, down: np.ndarray, dtype) -> np.ndarray:
    """(size,) ``dtype``: i + #(up <= i) - #(down <= i), one cumulative sum of unit
    steps in place (no arange, sum or cast copies: 2M ids 6.7 -> 2.5 ms)."""
    step = np.ones(size + 1, dtype)
    step[0] = 0
    np.add.at(step, up, 1)
    np.add.at(step, down, -1)
    return np.cumsum(step[:size], dtype=dtype, out=step[:size])


def _touched(old_tet_ids, removed, nk: _NewKeys, n_old: int):
    """Sorted ids of the old faces (edges) the step touches: those of removed tets and
    those a new tet also has. ``old_tet_ids`` (m0, w) per-tet ids, ``nk`` the keys of
    the new tets' faces (edges), ``n_old`` the number of old faces (edges)."""
    hit = nk.hit
    return _ids(n_old, old_tet_ids[removed], hit[hit >= 0])


def _merged(old_rows, old_keys, dead, new_rows, nk: _NewKeys, old_tet_ids, keep_idx):
    """The new mesh's faces (edges) and every tet's face (edge) ids.

    Merges the surviving old entities with the new tets' ``new_rows`` (keys
    ``nk``, w per new tet) as ``_merge``. Returns (keys, gmap, src, add_pos) of
    ``_merge``, the rows (G1, k) and the per-tet ids (K + A_tets, w): kept tets
    renumbered through ``gmap``, new tets looked up.
    """
    keys, gmap, src, add_src, add_pos = _merge(old_keys, dead, nk)
    rows = _take_rows(old_rows, new_rows[add_src], src, add_pos)
    w = old_tet_ids.shape[1]
    tet_ids = np.empty((len(keep_idx) + len(nk.inverse) // w, w), old_tet_ids.dtype)
    tet_ids[: len(keep_idx)] = _renumbered_rows(gmap, old_tet_ids, keep_idx)
    tet_ids[len(keep_idx) :] = np.searchsorted(keys, nk.ukeys)[nk.inverse].reshape(-1, w)
    return keys, gmap, src, add_pos, rows, tet_ids


def _renumbered_rows(mapping, ids, rows):
    """``mapping[ids[rows]]`` (r, w) for ``ids`` (m, w) with entries in [-1, len(mapping))
    (-1 reads ``mapping[-1]``) and ``rows`` (r,) most of the m rows, in order.

    The whole ``ids`` is mapped first, then its rows taken: the row copy then moves the
    narrow (int32) mapped values instead of int64 ids (983k tets, ~99 % kept: 30 -> 22
    ms for the tet_faces ids). np.take, ~20 % faster than fancy indexing for these
    gathers; modes "wrap" / "clip" skip its bounds checks (same values: the ids are in
    range)."""
    return np.take(np.take(mapping, ids, mode="wrap"), rows, axis=0, mode="clip")


def _take_rows(old_rows, add_rows, src, add_pos):
    """Rows ``concat(old_rows, add_rows)[src]`` (``src`` >= len(old_rows) exactly at the
    added ones' positions ``add_pos``, in order); np.take along axis 0 is several times
    faster than fancy or boolean row indexing on large arrays, and no concatenated copy
    of the old rows is made."""
    rows = np.take(old_rows, src, axis=0, mode="clip")
    rows[add_pos] = add_rows
    return rows


def _csr_take(ptr: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pos, owner): positions of the CSR entries of groups ``ids`` (g,), concatenated
    (``csr_rows``), and the index into ``ids`` each came from."""
    pos, _ = csr_rows(ptr, ids)
    return pos, np.repeat(np.arange(len(ids)), ptr[ids + 1] - ptr[ids])


def _splice(old_vals, old_ptr, old_carry, new_lens, new_redo, redo_vals, mapping=None):
    """CSR of the new groups: carried-over groups copy their old entries, redone groups
    take ``redo_vals``.

    ``old_vals`` with (G0+1,) pointers ``old_ptr``; ``old_carry`` (G0,) bool marks the old
    groups carried over, which are exactly the new groups where ``new_redo`` (G1,) is
    False, in the same order. ``redo_vals`` lists the redone groups' entries in group
    order. ``mapping`` renumbers the carried entries. Returns (ptr (G1+1,), vals).
    """
    ptr = np.zeros(len(new_lens) + 1, old_ptr.dtype)
    np.cumsum(new_lens, out=ptr[1:])
    vals = np.empty(ptr[-1], old_vals.dtype)
    carried = old_vals[~_entry_mask(old_ptr, np.diff(old_ptr), ~old_carry)]
    redo = _entry_mask(ptr, new_lens, new_redo)
    vals[~redo] = carried if mapping is None else np.take(mapping, carried, mode="clip")
    vals[redo] = redo_vals
    return ptr, vals


# Below this many entries of the flagged groups per group, ``_entry_mask`` sets the
# flagged entries from their CSR positions instead of repeating every group's flag
# (np.repeat costs ~9 ns per group). Measured on a late 983k-tet step: edge CSRs (1.1M
# groups, 0.06 flagged entries per group) 51 -> 38 and 42 -> 28 ms per splice; vertex
# CSR (167k groups, 0.8 per group) 32 -> 36 ms, so it keeps the repeat.
SPARSE_ENTRIES = 0.25


def _entry_mask(ptr, lens, flags):
    """(ptr[-1],) bool: the entries of the CSR groups where ``flags`` (G,) is True."""
    ids = np.flatnonzero(flags)
    if lens[ids].sum() >= SPARSE_ENTRIES * len(lens):
        return np.repeat(flags, lens)
    mask = np.zeros(ptr[-1], bool)
    mask[csr_rows(ptr, ids)[0]] = True
    return mask


def _regroup(group, slot, n_slots):
    """Sort entries by (group, slot); returns (group, slot) sorted and the CSR pointers
    of the distinct groups. Packed into one int64 value sort (group < 2**31)."""
    packed = np.sort(group * np.int64(n_slots) + slot)
    group, slot = packed // n_slots, packed % n_slots
    new = np.empty(len(group), bool)
    new[:1] = True
    np.not_equal(group[1:], group[:-1], out=new[1:])
    ptr = np.append(np.flatnonzero(new), len(group)).astype(np.int64)
    return group, slot, ptr


# -------------------------------------------------------------------------- faces
class _Faces(NamedTuple):
    """The new mesh's faces (F1 of them) and how they relate to the old ones."""

    faces: np.ndarray  # (F1, 3)
    keys: np.ndarray  # (F1,) increasing row keys
    tet_faces: np.ndarray  # (m1, 4)
    face_tets: np.ndarray  # (F1, 2)
    face_apex: np.ndarray  # (F1, 2)
    tet_neighbors: np.ndarray  # (m1, 4)
    redo: np.ndarray  # new ids of the faces regrouped from their tets (sorted)
    src: np.ndarray  # (F1,) old id of each face, >= F0 for an added one
    fmap: np.ndarray  # (F0,) new id of each old face, -1 if gone
    touched: np.ndarray  # old ids of the faces of removed tets and those new tets share


def _update_faces(old: Topology, tets, keep, keep_idx, removed, renum, n):
    """Faces, tet_faces, face_tets, face keys, face_apex, tet_neighbors of the new mesh.

    Faces of removed and new tets are regrouped from their tets; the others keep their
    tets (renumbered) and slot order, since kept tets keep their relative order.
    Returns None when a face would lie in more than two tets (build raises).
    """
    K, m1 = int(keep.sum()), len(tets)
    added = tets[K:]
    nf = np.sort(added[:, TET_FACES], axis=2).reshape(-1, 3)  # (4A, 3)
    fk0 = old.face_keys  # increasing: faces are numbered in key order
    nk = _new_keys(fk0, row_keys(nf, n))
    # old faces touched: faces of removed tets and old faces a new tet also has
    touched = _touched(old.tet_faces, removed, nk, len(fk0))
    ft = old.face_tets[touched]  # (T, 2)
    kept_slot = (ft >= 0) & keep[np.maximum(ft, 0)]
    fkeys, fmap, src, add_pos, faces, tet_faces = _merged(
        old.faces, fk0, touched[~kept_slot.any(axis=1)], nf, nk, old.tet_faces, keep_idx
    )
    A = len(add_pos)

    # carried faces: renumbered tets, same slots (regrouped ones are overwritten below)
    it = old.face_tets.dtype
    none = np.full((A, 2), -1, it)
    face_tets = np.take(renum, _take_rows(old.face_tets, none, src, add_pos), mode="wrap")
    face_tets = face_tets.astype(it, copy=False)
    face_apex = _take_rows(old.face_apex, none, src, add_pos)
    # entries (face, slot = tet * 4 + local vertex) of the touched faces, as build sorts them
    kt = renum[ft[kept_slot]].astype(np.int64)
    apex = old.face_apex[touched][kept_slot]
    local = local_index(tets, kt, apex)
    kface = np.broadcast_to(fmap[touched][:, None], ft.shape)[kept_slot]
    group = np.concatenate([kface, tet_faces[K:].reshape(-1)])
    slot = np.concatenate([kt * 4 + local, np.arange(4 * K, 4 * m1)])
    group, slot, ptr = _regroup(group, slot, 4 * m1)
    counts = np.diff(ptr)
    if (counts > 2).any():
        return None
    redo = group[ptr[:-1]]
    flat = tets.reshape(-1)
    s0 = slot[ptr[:-1]]
    face_tets[redo, 0] = s0 // 4
    face_apex[redo, 0] = flat[s0]
    two = counts == 2
    s1 = slot[ptr[:-1][two] + 1]
    face_tets[redo, 1] = -1
    face_apex[redo, 1] = -1
    face_tets[redo[two], 1] = s1 // 4
    face_apex[redo[two], 1] = flat[s1]

    # neighbours: carried, except for tets on a regrouped face (as build computes them)
    tet_neighbors = np.empty((m1, 4), it)
    tet_neighbors[:K] = _renumbered_rows(renum, old.tet_neighbors, keep_idx)
    rows = _ids(m1, slot // 4)
    tf = tet_faces[rows]
    ftf = np.take(face_tets, tf, axis=0)  # (r, 4, 2): one row gather, not three columns
    tet_neighbors[rows] = np.where(ftf[:, :, 0] == rows[:, None], ftf[:, :, 1], ftf[:, :, 0])
    return _Faces(
        faces, fkeys, tet_faces, face_tets, face_apex, tet_neighbors, redo, src, fmap, touched
    )


# -------------------------------------------------------------------------- edges
class _Edges(NamedTuple):
    """The new mesh's edges (E1 of them) and how they relate to the old ones."""

    edges: np.ndarray  # (E1, 2)
    keys: np.ndarray  # (E1,) increasing keys a * n + b
    tet_edges: np.ndarray  # (m1, 6)
    edge_tets_ptr: np.ndarray  # (E1+1,)
    edge_tets: np.ndarray
    ring_ptr: np.ndarray  # (E1+1,)
    ring: np.ndarray
    boundary: np.ndarray  # (E1,)
    manifold: np.ndarray  # (E1,)
    redo: np.ndarray  # new ids of the edges regrouped from their tets (sorted)
    src: np.ndarray  # (E1,) old id of each edge, >= E0 for an added one
    touched: np.ndarray  # old ids of the edges of removed tets and those new tets share


def _ring_steps(tets, tet, local):
    """Ring step c -> d (each (q,)) of entries (tet, local edge), as ``Topology.build``:
    v_k -> v_l for local edge (i, j), reversed when tets[i] > tets[j]."""
    # the four local columns i, j, k, l of each entry's edge, read as flat positions:
    # np.take_along_axis over (q, 4) rows builds index grids (1.7M entries: 98 -> 75 ms)
    flat, base = tets.reshape(-1), tet * 4
    lo, hi, ck, cl = (np.take(flat, base + _STEP_COLUMNS[local, i], mode="clip") for i in range(4))
    swap = lo > hi
    return np.where(swap, cl, ck), np.where(swap, ck, cl)


_STEP_COLUMNS = np.concatenate([TET_EDGES, _EDGE_OTHERS], axis=1)


def _update_edges(old: Topology, tets, keep, keep_idx, removed, renum, n):
    """Edges, tet_edges, ring CSRs, boundary and manifold flags of the new mesh.

    Edges of removed and new tets get their tets regrouped (in build's slot order) and
    their rings ordered again by ``_order_rings``; the rings of all other edges are
    carried over, renumbered: their tets are all kept and keep their relative order, so
    the ring start (the lowest slot on a cycle) does not change either.
    """
    K, m1 = int(keep.sum()), len(tets)
    added = tets[K:]
    ne = np.sort(added[:, TET_EDGES], axis=2).reshape(-1, 2)  # (6A, 2)
    ek0 = old.edge_keys  # increasing: edges are numbered in key order
    nk = _new_keys(ek0, ne[:, 0] * np.int64(n) + ne[:, 1])
    touched = _touched(old.tet_edges, removed, nk, len(ek0))
    pos, owner = _csr_take(old.edge_tets_ptr, touched)
    rt = old.edge_tets[pos]
    kept = keep[rt]
    alive = np.bincount(owner[kept], minlength=len(touched)) > 0
    ekeys, emap, src, _, edges, tet_edges = _merged(
        old.edges, ek0, touched[~alive], ne, nk, old.tet_edges, keep_idx
    )
    E = len(ekeys)

    # entries (edge, slot = tet * 6 + local edge) of the redone edges, in build's order
    kt, ke = rt[kept], touched[owner[kept]]
    # each tet around an edge has it exactly once: the flat positions of the matches are
    # in row order (1M entries: 100 -> 40 ms for an argmax over the (q, 6) comparison)
    klocal = np.flatnonzero(np.take(old.tet_edges, kt, axis=0) == ke[:, None]) % 6
    group = np.concatenate([emap[ke], tet_edges[K:].reshape(-1)])
    slot = np.concatenate([renum[kt].astype(np.int64) * 6 + klocal, np.arange(6 * K, 6 * m1)])
    group, slot, ptr = _regroup(group, slot, 6 * m1)
    redo_ids = group[ptr[:-1]]
    etet, elocal = slot // 6, slot % 6
    c, d = _ring_steps(tets, etet, elocal)
    r_tets, r_ring_ptr, r_ring, r_bnd, r_man = _order_rings(ptr, c, d, etet)

    redo = np.zeros(E, bool)
    redo[redo_ids] = True
    # carried: the untouched edges (touched ones are either gone or regrouped)
    carry = np.ones(len(ek0), bool)
    carry[touched] = False
    # old and new ids of the carried edges (the new edges not regrouped, in order), found
    # once for the three per-edge copies below
    c_old, c_new = np.flatnonzero(carry), np.flatnonzero(~redo)
    lens1 = np.zeros(E, np.int64)
    lens1[c_new] = np.take(np.diff(old.edge_tets_ptr), c_old)
    lens1[redo_ids] = np.diff(ptr)
    edge_tets_ptr, edge_tets = _splice(
        old.edge_tets, old.edge_tets_ptr, carry, lens1, redo, r_tets, renum
    )
    bnd = np.zeros(E, bool)
    man = np.zeros(E, bool)
    bnd[c_new] = np.take(old.edge_boundary, c_old)
    man[c_new] = np.take(old.edge_manifold, c_old)
    bnd[redo_ids] = r_bnd
    man[redo_ids] = r_man
    ring_ptr, ring = _splice(old.edge_ring, old.edge_ring_ptr, carry, lens1 + bnd, redo, r_ring)
    return _Edges(
        edges, ekeys, tet_edges, edge_tets_ptr, edge_tets, ring_ptr, ring, bnd, man,
        redo_ids, src, touched,
    )  # fmt: skip


# -------------------------------------------------------------------------- vertices
def _update_vertices(old: Topology, old_tets, tets, keep, removed, renum):
    """(vert_tets_ptr (n+1,), vert_tets): tets around each vertex in increasing order."""
    n = len(old.vert_tets_ptr) - 1
    K, m1 = int(keep.sum()), len(tets)
    added = tets[K:]
    redo = np.zeros(n, bool)
    redo[old_tets[removed].reshape(-1)] = True
    redo[added.reshape(-1)] = True
    vids = np.flatnonzero(redo)
    pos, owner = _csr_take(old.vert_tets_ptr, vids)
    t = old.vert_tets[pos]
    k = keep[t]
    group = np.concatenate([vids[owner[k]], added.reshape(-1)])
    tet = np.concatenate([renum[t[k]].astype(np.int64), np.repeat(np.arange(K, m1), 4)])
    group, tet, _ = _regroup(group, tet, m1)
    lens0 = np.diff(old.vert_tets_ptr)
    lens1 = lens0.copy()
    lens1[vids] = np.bincount(group, minlength=n)[vids]
    return _splice(old.vert_tets, old.vert_tets_ptr, ~redo, lens1, redo, tet, renum)
