"""The optimizer's guard on curved tets: no change folds or flattens a curved tet.

A quadratic mesh read with ``load(path, linear=True)`` keeps the mid-edge nodes of its
curved boundary (``TetMesh.curved_edges``), and ``save(..., quadratic=True)`` puts them
back on every tet around those edges. The optimizer flips, splits and smooths the
straight tets; a tet with a curved edge can then bend more than its straight tet shows,
down to folding over itself (a scaled Jacobian <= 0: a finite-element solver refuses it).

The guard rejects each flip, split or vertex move whose new tets have a smallest scaled
Jacobian (``_quadratic.jacobian_ratios``, Gmsh's ``minSJ``) below both the floor
``Options.min_scaled_jacobian`` and the smallest of the tets it replaces. Tets without
a curved edge count as 1 (straight-sided), so changes away from curved edges are never
rejected. The mesh's smallest scaled Jacobian thus never falls below the smaller of the
floor and the input's (``tests/test_curved_guard.py`` checks it after whole runs).

A curved edge on a bounding surface (the boundary, an interface between regions, a
protected face) whose node is off the plane of its faces is the geometry of that
surface: the surface bends there. A run never removes such an edge
(``surface_curved_edges`` pins it): a 2-2 or 4-4 flip of its two coplanar straight faces
would put a straight edge across the curved surface, and the quadratic output would lose
the surface's shape there. An edge bent within the plane of its two faces (a node moved
along a flat face) may be flipped: the two faces cover the same plane either way.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int

from ._quadratic import CURVED_TOL, MID_EDGES, jacobian_ratios_at
from ._topology import corner_counts, faces_at, match_rows, row_keys


def _curved_slots(mesh, points, tets) -> tuple[np.ndarray, np.ndarray]:
    """(rows (r,), at (r, 6)): the tets of ``tets`` with a curved edge (whose ends are
    where they are in ``mesh.points``) and, for each of their 6 edges in VTK's order,
    its row of ``mesh.curved_edges`` (-1: straight)."""
    curved = mesh.curved_edges
    n = len(points)
    ends = np.zeros(n, bool)
    ends[curved.edges.reshape(-1)] = True
    # a tet can hold a curved edge only with two corners on curved edges (cheap filter:
    # most tets of a pass have none)
    near = np.flatnonzero(corner_counts(ends, tets) >= 2)
    at = match_rows(curved.edges, tets[near][:, MID_EDGES[4]].reshape(-1, 2), n).reshape(-1, 6)
    if points is not mesh.points:
        hit = at >= 0
        pair = curved.edges[at[hit]]  # (h, 2): only the edges found are compared
        moved = (points[pair] != mesh.points[pair]).any(axis=(1, 2))
        at[hit] = np.where(moved, -1, at[hit])
    has = (at >= 0).any(axis=1)
    return near[has], at[has]


def scaled_jacobians(
    mesh, points: Float[np.ndarray, "N 3"], tets: Int[np.ndarray, "k 4"]
) -> Float[np.ndarray, " k"]:
    """(k,) scaled Jacobian of the quadratic tets over ``tets`` (k, 4), with the
    vertices at ``points`` (N >= mesh.n_points; vertex ids of ``mesh`` and beyond).

    An edge has the node of ``mesh.curved_edges`` while both its ends are where they are
    in ``mesh.points`` (the node stays on its curve only then), else its midpoint. A tet
    without such an edge is straight-sided: 1.0, whatever its orientation (the
    operations' own exact orientation checks judge those)."""
    out = np.ones(len(tets))
    if not mesh.has_curved_edges or not len(tets):
        return out
    rows, at = _curved_slots(mesh, points, tets)
    if not len(rows):
        return out
    corners = points[tets[rows]]  # (r, 4, 3)
    mids = 0.5 * (corners[:, MID_EDGES[4][:, 0]] + corners[:, MID_EDGES[4][:, 1]])
    hit = at >= 0
    mids[hit] = mesh.curved_edges.points[at[hit]]
    out[rows] = jacobian_ratios_at(np.concatenate([corners, mids], axis=1))
    return out


def curved_corners(mesh) -> Bool[np.ndarray, " n"]:
    """(n,) bool: the vertices of the tets of ``mesh`` with a curved edge (a change
    elsewhere leaves every curved tet as it is)."""
    out = np.zeros(mesh.n_points, bool)
    if mesh.has_curved_edges:
        out[mesh.tets[_curved_slots(mesh, mesh.points, mesh.tets)[0]]] = True
    return out


def surface_curved_edges(mesh) -> Int[np.ndarray, "k 2"]:
    """(k, 2) the curved edges of ``mesh`` (rows of ``curved_edges.edges``) that lie on a
    face of a bounding surface (a boundary face, a face between two regions or a
    protected face) with their node off that face's plane (by more than
    ``_quadratic.CURVED_TOL`` times the edge's length; a degenerate face counts as bent).

    Found among the tets with two or more corners on curved edges (both tets of a face
    holding a curved edge are among them), not through a whole-mesh topology."""
    curved = mesh.curved_edges
    n = mesh.n_points
    ends = np.zeros(n, bool)
    ends[curved.edges.reshape(-1)] = True
    faces, tet_of = faces_at(mesh.tets, ends, 2)  # only such faces can hold a curved edge
    # grouped by one int64 key per face (np.unique over rows sorts them 10x slower)
    _, first, inverse, count = np.unique(
        row_keys(faces, n), return_index=True, return_inverse=True, return_counts=True
    )
    rows, inverse = faces[first], inverse.reshape(-1)
    region = mesh.region[tet_of]
    low = np.full(len(rows), np.iinfo(np.int64).max)
    high = np.full(len(rows), np.iinfo(np.int64).min)
    np.minimum.at(low, inverse, region)
    np.maximum.at(high, inverse, region)
    on_surface = (count == 1) | (low != high)
    if len(mesh.protected_faces):
        on_surface |= match_rows(mesh.protected_faces, rows, n) >= 0
    surface = rows[on_surface]
    at = match_rows(curved.edges, surface[:, [[0, 1], [0, 2], [1, 2]]].reshape(-1, 2), n)
    hit = np.flatnonzero(at >= 0)
    corners = mesh.points[surface[hit // 3]]  # (h, 3, 3): the face of each curved side
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    node = curved.points[at[hit]]
    ends = mesh.points[curved.edges[at[hit]]]
    height = np.abs(np.einsum("ij,ij->i", node - corners[:, 0], normal))
    # |(node - c0) . normal| > tol * |b - a| * |normal|: no division by a zero normal
    length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    bent = height > CURVED_TOL * length * np.linalg.norm(normal, axis=1)
    bent |= ~normal.any(axis=1)
    return curved.edges[np.unique(at[hit[bent]])]


def worse_owners(
    mesh,
    floor: float | None,
    old: tuple[Float[np.ndarray, "N 3"], Int[np.ndarray, "c 4"], Int[np.ndarray, " c"]],
    new: tuple[Float[np.ndarray, "N 3"], Int[np.ndarray, "k 4"], Int[np.ndarray, " k"]],
    n_cand: int,
) -> Bool[np.ndarray, " n_cand"]:
    """(n_cand,) bool: the candidates whose new tets have a smallest scaled Jacobian
    below both ``floor`` and the smallest of the old tets they replace. ``old`` and
    ``new`` are (points, tets, owner candidate of each tet); ``scaled_jacobians`` says
    which edges are curved. All False when ``floor`` is None (no guard) or ``mesh`` has
    no curved edges."""
    if floor is None or not mesh.has_curved_edges or not len(new[1]):
        return np.zeros(n_cand, bool)
    (p0, t0, o0), (p1, t1, o1) = old, new
    return below(
        floor, scaled_jacobians(mesh, p0, t0), o0, scaled_jacobians(mesh, p1, t1), o1, n_cand
    )


def below(
    floor: float,
    old_ratios: Float[np.ndarray, " c"],
    old_owner: Int[np.ndarray, " c"],
    new_ratios: Float[np.ndarray, " k"],
    new_owner: Int[np.ndarray, " k"],
    n_cand: int,
) -> Bool[np.ndarray, " n_cand"]:
    """(n_cand,) bool: the candidates whose smallest new scaled Jacobian is below both
    ``floor`` and their smallest old one (each tet's ratio with its owner candidate)."""
    worst_old = np.full(n_cand, np.inf)
    np.minimum.at(worst_old, old_owner, old_ratios)
    worst_new = np.full(n_cand, np.inf)
    np.minimum.at(worst_new, new_owner, new_ratios)
    return worst_new < np.minimum(worst_old, floor)
