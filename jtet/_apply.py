"""Apply a batch of transformations at once: drop old tets, append new ones."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._mesh import TetMesh
from ._topology import local_index, match_rows, row_keys, sorted_lookup, sorted_rows


def kept_then_new(rows: np.ndarray, keep: np.ndarray, new: np.ndarray) -> np.ndarray:
    """``np.concatenate([rows[keep], new])`` (rows (m, ...), keep (m,) bool, new (k, ...)
    cast to ``rows.dtype``) written into one new array.

    A flip step or a spliced round keeps nearly every tet of the mesh: boolean indexing
    of (m, 4) rows gathers them row by row into a temporary that the concatenation copies
    again, while ``np.compress`` into the output's first rows copies them in runs (983k
    tets, 15k dropped: 23-58 ms -> 10-11 ms, measured with the results kept alive, as a
    run keeps its meshes)."""
    kept = int(np.count_nonzero(keep))
    out = np.empty((kept + len(new),) + rows.shape[1:], rows.dtype)
    np.compress(keep, rows, axis=0, out=out[:kept])
    out[kept:] = new
    return out


def replace_tets(
    mesh: TetMesh,
    remove: np.ndarray,
    new_tets: np.ndarray,
    new_region: np.ndarray,
    old_protected: np.ndarray | None = None,
    new_protected: np.ndarray | None = None,
) -> tuple[TetMesh, int]:
    """A new mesh without the tets where ``remove`` (m,) is True, plus ``new_tets`` (k, 4).

    Kept tets keep their order and come first; the new tets follow, so the returned
    ``start`` index marks the tets this step created (the optimizer's "dirty" set).
    User-protected faces a flip replaced (``old_protected`` (p,3)) are swapped for the
    faces that now carry the same surface (``new_protected`` (p,3)).
    When ``mesh``'s topology is already computed, the new mesh's is derived from it
    incrementally (identical to a full build, much cheaper for a small change).
    """
    tets = kept_then_new(mesh.tets, ~remove, new_tets)
    region = kept_then_new(mesh.region, ~remove, new_region)
    n_kept = len(tets) - len(new_tets)
    protected, labels = mesh.protected_faces, mesh.protected_face_labels
    if old_protected is not None and len(old_protected) and len(protected):
        idx = match_rows(protected, old_protected, mesh.n_points)
        hit = idx >= 0
        keep = np.ones(len(protected), bool)
        keep[idx[hit]] = False
        protected = np.concatenate([protected[keep], np.sort(new_protected[hit], axis=1)])
        # a new face carries the surface, hence the label, of the old face it replaces
        labels = np.concatenate([labels[keep], labels[idx[hit]]])
    # only the new tets are checked: the kept ones come from a checked mesh
    changes = {}
    if protected is not mesh.protected_faces:
        changes = {"protected_faces": protected, "protected_face_labels": labels}
    out = mesh._derive(tets=tets, region=region, tets_checked=n_kept, **changes)
    if "topology" in mesh.__dict__:  # cached_property already computed on the old mesh
        from ._topology_update import update_topology

        # None (large change, or a mesh the full build rejects): stays lazy, as before
        topo = update_topology(mesh.topology, mesh, out, ~remove, fallback=False, kept_first=True)
        if topo is not None:
            out.__dict__["topology"] = topo
    return out, n_kept


class FlipPlan(NamedTuple):
    """The winners of a flip step, chosen on a mesh and not applied yet: the old tets
    they remove, the tets they create and the user-protected faces they swap
    (``replace_tets``'s arguments). Plans of one mesh with disjoint ``remove`` sets are
    applied together by ``apply_plans``."""

    remove: np.ndarray  # (m,) bool
    new_tets: np.ndarray  # (k, 4)
    new_region: np.ndarray  # (k,)
    old_protected: np.ndarray | None = None  # (p, 3) or None
    new_protected: np.ndarray | None = None  # (p, 3) or None


def apply_plans(mesh: TetMesh, plans: list[FlipPlan]) -> tuple[TetMesh, np.ndarray | None]:
    """(new mesh, keep): ``mesh`` with the winners of every plan of ``plans`` (None
    entries skipped) applied by one ``replace_tets``, so that one topology update serves
    them all; ``keep`` (m,) marks the surviving tets (None and ``mesh`` itself when no
    plan has a winner). The plans' ``remove`` sets must be disjoint, and the new tets of
    all of them must make a conforming mesh together (``nonconforming_owners`` with the
    earlier plans as ``prior``)."""
    plans = [p for p in plans if p is not None]
    if not plans:
        return mesh, None
    remove = plans[0].remove.copy()
    for p in plans[1:]:
        remove |= p.remove
    old_p = [p.old_protected for p in plans if p.old_protected is not None]
    new_p = [p.new_protected for p in plans if p.new_protected is not None]
    out, _ = replace_tets(
        mesh,
        remove,
        np.concatenate([p.new_tets for p in plans]),
        np.concatenate([p.new_region for p in plans]),
        np.concatenate(old_p) if old_p else None,
        np.concatenate(new_p) if new_p else None,
    )
    return out, ~remove


# Faces of tet (v0, v1, v2, v3) opposite v0..v3, oriented outward for a positive tet; two
# consistently oriented tets sharing a face list it with opposite parities.
_OUT_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def _parity3(f: np.ndarray) -> np.ndarray:
    """(k,) parity of the permutation sorting each (k, 3) row."""
    return ((f[:, 0] > f[:, 1]).astype(np.int64) + (f[:, 0] > f[:, 2]) + (f[:, 1] > f[:, 2])) % 2


def worse_orientation_owners(mesh, new_tets, new_owner, claims, claim_owner, n_cand) -> np.ndarray:
    """(n_cand,) bool: candidates creating more non-positive tets than they remove.

    ``new_tets`` (N, 4) with ``new_owner`` (N,) candidate ids; ``claims`` (C,) old tets
    removed with ``claim_owner`` (C,). Signs from the exact orient3d.
    """
    from ._predicates import orient3d_tets

    bad_new = np.bincount(new_owner, orient3d_tets(mesh.points, new_tets) <= 0, minlength=n_cand)
    bad_old = np.bincount(
        claim_owner, orient3d_tets(mesh.points, mesh.tets[claims]) <= 0, minlength=n_cand
    )
    return bad_new > bad_old


def recreating_owners(new_tets, new_owner, forbidden, n_cand) -> np.ndarray:
    """(n_cand,) bool: candidates whose new tets (k, 4) (owners ``new_owner`` (k,))
    include one of the ``forbidden`` (f, 4) tets, as vertex sets (f is small: the tets a
    perturbation kick removed)."""
    out = np.zeros(n_cand, bool)
    if forbidden is None or not len(forbidden) or not len(new_tets):
        return out
    same = np.sort(new_tets, axis=1)[:, None, :] == np.sort(forbidden, axis=1)[None, :, :]
    out[new_owner[same.all(axis=2).any(axis=1)]] = True
    return out


def nonconforming_owners(mesh, remove, new_tets, new_owner, n_cand) -> np.ndarray:
    """(n_cand,) bool: candidates one of whose new faces would lie in more than two tets
    of the new mesh, or in two tets on the same side (same orientation), or is a
    boundary face of ``mesh`` that two tets of the new mesh would share.

    The new mesh is ``mesh`` without the tets where ``remove`` (m,) plus ``new_tets``
    (N, 4) owned by candidates ``new_owner`` (N,). Needed around inverted / degenerate
    tets, where a cavity is not star-shaped and a new face (or a whole new tet) can
    coincide with an existing one; costs a lookup of the new faces only. Rejecting a
    candidate restores its old tets, so callers repeat until nothing is rejected.
    """
    from ._topology_update import _regroup

    T = mesh.topology
    n = mesh.n_points
    nf = new_tets[:, _OUT_FACES].reshape(-1, 3)
    rows = sorted_rows(new_tets, _OUT_FACES).reshape(-1, 3)
    if T.face_keys is not None:
        face_keys, keys = T.face_keys, row_keys(rows, n)
    else:  # keys are per-call ranks: the mesh's faces and the new ones ranked together
        both = row_keys(np.concatenate([T.faces, rows]), n)
        face_keys, keys = both[: len(T.faces)], both[len(T.faces) :]
    # ONE sort of the new faces by (key, orientation parity): it groups equal new faces
    # and makes the lookup of the old faces a search with increasing queries. Before, new
    # and old faces were grouped by a second sort, after a lookup of the new faces in
    # their own order. 983k-tet cube, first edge pass (207k new tets): 420-570 -> 180-200
    # ms; all steps of a run: 0.71 -> 0.31 s.
    group_key, parity, ptr = _regroup(keys, _parity3(nf), 2)
    starts = ptr[:-1]
    face_key = group_key[starts]
    count = np.diff(ptr)
    odd = np.add.reduceat(parity, starts) if len(starts) else np.zeros(0, np.int64)
    # the kept old tets on the new faces that are faces of the mesh already
    fid = sorted_lookup(face_keys, face_key)
    on_old = np.flatnonzero(fid >= 0)
    kt, ka = T.face_tets[fid[on_old]].reshape(-1), T.face_apex[fid[on_old]].reshape(-1)
    kept = kt >= 0
    kept[kept] = ~remove[kt[kept]]
    owner_face = np.repeat(on_old, 2)[kept]
    kt, ka = kt[kept], ka[kept]
    local = local_index(mesh.tets, kt, ka)
    k_par = _parity3(np.take_along_axis(mesh.tets[kt], _OUT_FACES[local], 1))
    count += np.bincount(owner_face, minlength=len(count))
    odd += np.bincount(owner_face, k_par, minlength=len(count)).astype(np.int64)
    bad_face = (count > 2) | ((count == 2) & (odd != 1))
    # A boundary face that stays in the mesh stays a boundary face. In two tets, the
    # boundary would fold onto itself there, enclosing a boundary vertex: a flip of bent
    # boundary faces under a feature angle that gives a kept tet's boundary face a second
    # tet, or two flips of one pass whose new tets share a boundary face that one of
    # them re-creates (fuzz: a dimple of three boundary faces filled, its apex gone from
    # the boundary). Count and orientations are those of an interior face.
    bad_face[on_old] |= T.boundary_face[fid[on_old]] & (count[on_old] >= 2)
    reject = np.zeros(n_cand, bool)
    if bad_face.any():  # rare: inverted or degenerate tets around
        bad = np.isin(keys, face_key[bad_face])
        reject[np.repeat(new_owner, 4)[bad]] = True
    return reject


def split_tets(
    mesh: TetMesh, which: np.ndarray, min_scaled_jacobian: float | None = None
) -> tuple[TetMesh, np.ndarray]:
    """1-4 split: a new vertex at the centroid of every tet where ``which`` (m,) bool,
    joined to the tet's four faces.

    Tets whose four new tets would not all be positive (exact orient3d; only a nearly
    flat tet's rounded centroid can fail) are left alone. Returns (new mesh, keep (m,)):
    the kept tets first, in order, then four new tets per split tet; the new vertices
    are appended to the points, in the order of the split tets. Faces and edges of the
    old tets all stay, so subfacets and subsegments are untouched. With
    ``min_scaled_jacobian``, tets whose split the guard on curved tets rejects
    (``_curved_guard``) are left alone too.
    """
    from ._predicates import orient3d_tets

    split = np.flatnonzero(which)
    old = mesh.tets[split]
    centroids = mesh.points[old].mean(axis=1)
    ids = mesh.n_points + np.arange(len(split))
    # replacing vertex i of a positive tet by a point inside it keeps the orientation
    new = np.repeat(old[:, None, :], 4, axis=1)
    new[:, np.arange(4), np.arange(4)] = ids[:, None]
    points = np.concatenate([mesh.points, centroids])
    positive = (orient3d_tets(points, new.reshape(-1, 4)) > 0).reshape(-1, 4).all(axis=1)
    if min_scaled_jacobian is not None and mesh.has_curved_edges:
        from ._curved_guard import worse_owners

        own = np.arange(len(split))
        positive &= ~worse_owners(
            mesh,
            min_scaled_jacobian,
            (mesh.points, old, own),
            (points, new.reshape(-1, 4), np.repeat(own, 4)),
            len(split),
        )
    split, new, centroids = split[positive], new[positive], centroids[positive]
    if not len(split):
        return mesh, np.ones(mesh.n_tets, bool)
    # renumber the kept centroids' vertices so that the new points have no gaps
    ids = mesh.n_points + np.arange(len(split))
    new[:, np.arange(4), np.arange(4)] = ids[:, None]
    keep = np.ones(mesh.n_tets, bool)
    keep[split] = False
    out = mesh._derive(
        points=np.concatenate([mesh.points, centroids]),
        tets=kept_then_new(mesh.tets, keep, new.reshape(-1, 4)),
        tets_checked=int(keep.sum()),
        region=kept_then_new(mesh.region, keep, np.repeat(mesh.region[split], 4)),
    )
    return out, keep
