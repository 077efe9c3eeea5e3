"""Quadratic output of a linear mesh: a node on every edge (``save(..., quadratic=True)``).

A 10-node tet is the 4 corners of a linear tet and a node on each of its 6 edges; a
6-node triangle and a 3-node line likewise. Each edge of the mesh gets one node, shared
by every cell around it: the node ``TetMesh.curved_edges`` gives it (a curved
boundary's, read with ``load(path, linear=True)``), or else its midpoint. The mid-edge
nodes are numbered after the mesh's points, so every vertex id (protected entities,
node sets, periodic pairs) keeps its meaning.

Orders (every format lists the corners first, in the order of its linear cell): VTK, XDMF,
meshio, Abaqus and Exodus put the mid-edge nodes of a tet on the edges ``TET10_EDGES``
(01, 12, 02, 03, 13, 23), of a triangle on ``TRI6_EDGES`` (01, 12, 02); Gmsh swaps the
last two of a tet (meshio does it for us), MED lists its corners the other way round
(``_med``) and TetGen has an order of its own (``_tetgen``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from jaxtyping import Float, Int

from ._errors import MeshInputError
from ._mesh import NodeSet, TetMesh, unmoved_edges
from ._topology import match_rows, row_keys

# corner pairs of the mid-edge nodes of a 10-node tet, a 6-node triangle and a 3-node
# line, in VTK's order (keyed by the number of corners)
MID_EDGES = {
    4: np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]]),
    3: np.array([[0, 1], [1, 2], [0, 2]]),
    2: np.array([[0, 1]]),
}
# A mid-edge node bends its edge (a curved edge, ``TetMesh.curved_edges``) when it lies
# farther than this times the edge's length off the edge's midpoint, and a bounding
# surface when that far off the plane of a face holding the edge: more than the rounding
# of a node written as text with a few digits
CURVED_TOL = 1e-6


def vtk_edge_columns(pairs: np.ndarray) -> np.ndarray:
    """(k,) for each corner pair of ``pairs`` (k, 2) (a 10-node tet's edges in another
    format's order, its corners numbered as VTK's), that edge's column among VTK's edge
    nodes (``MID_EDGES[4]``)."""
    vtk = np.sort(MID_EDGES[4], axis=1)
    hit = (np.sort(np.asarray(pairs), axis=1)[:, None, :] == vtk[None]).all(axis=2)
    return hit.argmax(axis=1)


class QuadraticMesh(NamedTuple):
    """A mesh's quadratic cells. ``points`` (n + e, 3): the mesh's points, then one node
    per edge (node ``n + i`` on ``edges[i]``); ``tets`` (m, 10) in VTK's order;
    ``point_data`` and ``node_sets`` over all n + e nodes."""

    points: Float[np.ndarray, "N 3"]
    tets: Int[np.ndarray, "m 10"]
    edges: Int[np.ndarray, "e 2"]  # sorted vertex pairs
    n_corners: int
    curved: np.ndarray  # (e,) bool: the edges whose node is a curved edge's, not the midpoint
    point_data: dict
    node_sets: tuple

    def cells(self, rows: np.ndarray) -> np.ndarray:
        """Quadratic cells (k, 6) or (k, 3) in VTK's order of linear triangles or lines
        ``rows`` (k, 3) / (k, 2), edges of the mesh."""
        rows = np.asarray(rows, np.int64)
        corners = rows.shape[1]
        pairs = rows[:, MID_EDGES[corners]].reshape(-1, 2)
        at = match_rows(self.edges, pairs, self.n_corners)
        if (at < 0).any():
            raise MeshInputError(
                f"{int((at < 0).sum())} protected face or edge side(s) are no edge of the "
                "tets: no quadratic cell for them"
            )
        mids = (at + self.n_corners).reshape(len(rows), len(MID_EDGES[corners]))
        return np.concatenate([rows, mids], axis=1)


def quadratic_mesh(mesh: TetMesh) -> QuadraticMesh:
    """The quadratic cells of ``mesh``: a node on each edge, its ``curved_edges`` node
    or its midpoint. Point data on the mid-edge nodes: the mean of the two ends (integer
    arrays: the smaller end value); node sets take the mid-edge nodes of their edges
    (both ends in the set)."""
    n = mesh.n_points
    pairs = np.sort(mesh.tets[:, MID_EDGES[4]].reshape(-1, 2), axis=1)
    _, first, inverse = np.unique(row_keys(pairs, n), return_index=True, return_inverse=True)
    edges = pairs[first]
    mids = 0.5 * (mesh.points[edges[:, 0]] + mesh.points[edges[:, 1]])
    curved = np.zeros(len(edges), bool)
    if mesh.has_curved_edges:
        at = match_rows(edges, mesh.curved_edges.edges, n)
        found = at >= 0
        mids[at[found]] = mesh.curved_edges.points[found]
        curved[at[found]] = True
    tets = np.concatenate([mesh.tets, n + inverse.reshape(-1, 6)], axis=1)
    point_data = {}
    for name, a in mesh.point_data.items():
        ends = a[edges]  # (e, 2, ...)
        if np.issubdtype(a.dtype, np.integer):
            on_edge = ends.min(axis=1)
        else:
            on_edge = ends.mean(axis=1, dtype=np.float64).astype(a.dtype)
        point_data[name] = np.concatenate([a, on_edge])
    sets = []
    for ns in mesh.node_sets:
        inside = np.zeros(n, bool)
        inside[ns.ids] = True
        on = np.flatnonzero(inside[edges].all(axis=1)) + n
        sets.append(NodeSet(ns.name, np.concatenate([ns.ids, on]), ns.label))
    return QuadraticMesh(
        np.concatenate([mesh.points, mids]), tets, edges, n, curved, point_data, tuple(sets)
    )


# shape-function derivative coefficients of a 10-node tet (VTK order), at its 10 nodes:
# x(L) = sum_i x_i L_i (2 L_i - 1) + sum_(i,j) 4 x_ij L_i L_j over barycentrics L, so
# dx/dL_k = x_k (4 L_k - 1) + 4 sum_j x_kj L_j; row [s, k] holds the weights of the 10
# nodes in dx/dL_k at node s
def _derivative_weights() -> np.ndarray:
    bary = np.zeros((10, 4))
    bary[np.arange(4), np.arange(4)] = 1.0
    for e, (i, j) in enumerate(MID_EDGES[4]):
        bary[4 + e, [i, j]] = 0.5
    w = np.zeros((10, 4, 10))
    for s in range(10):
        for k in range(4):
            w[s, k, k] = 4 * bary[s, k] - 1
            for e, (i, j) in enumerate(MID_EDGES[4]):
                if k in (i, j):
                    w[s, k, 4 + e] = 4 * bary[s, j if k == i else i]
    return w


_DERIVATIVE_WEIGHTS = _derivative_weights()


def jacobian_ratios(points: np.ndarray, tets10: np.ndarray) -> np.ndarray:
    """(m,) the scaled Jacobian of each 10-node tet ``tets10`` (m, 10): its smallest
    Jacobian determinant at its 10 nodes over that of its straight-sided tet (1 when its
    mid-edge nodes are the midpoints; <= 0: the curved tet folds over itself there).
    Gmsh's ``minSJ`` element quality, tet for tet (``tests/test_quadratic_output.py``).
    A tet whose straight-sided tet has no volume gets -inf."""
    return jacobian_ratios_at(points[tets10])


def jacobian_ratios_at(x: Float[np.ndarray, "m 10 3"]) -> Float[np.ndarray, " m"]:
    """``jacobian_ratios`` of 10-node tets given by their node coordinates ``x``
    (m, 10, 3), VTK's order."""
    d = np.einsum("skn,mnc->mskc", _DERIVATIVE_WEIGHTS, x)  # dx/dL_k at node s
    jac = d[:, :, 1:, :] - d[:, :, :1, :]  # (m, 10, 3 directions, 3 coordinates)
    det = np.linalg.det(jac)  # (m, 10)
    c = x[:, :4]
    straight = np.linalg.det(c[:, 1:] - c[:, :1])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = det.min(axis=1) / straight
    return np.where(straight > 0, ratio, -np.inf)


def folded_tets(quad: QuadraticMesh) -> tuple[int, float]:
    """(count, smallest scaled Jacobian) of the quadratic tets with a non-positive
    Jacobian at a node (``jacobian_ratios``); only tets with a curved edge's node can
    fold (the others are straight-sided, of scaled Jacobian 1: 1.0 without curved ones)."""
    rows = np.flatnonzero(quad.curved[quad.tets[:, 4:] - quad.n_corners].any(axis=1))
    if not len(rows):
        return 0, 1.0
    ratios = jacobian_ratios(quad.points, quad.tets[rows])
    return int((ratios <= 0).sum()), float(ratios.min())


def curved_edges_kept(before: TetMesh, after: TetMesh) -> np.ndarray:
    """(k,) bool over ``before.curved_edges``: the edge is an edge of ``after``'s tets
    and its two ends are where they were (a mid-edge node stays on its curve only then)."""
    edges = before.curved_edges.edges
    keep = unmoved_edges(edges, before.points, after.points)
    on = np.zeros(after.n_points, bool)
    on[edges[keep].reshape(-1)] = True
    near = after.tets[on[after.tets].sum(axis=1) >= 2]  # the tets that can hold one
    pairs = near[:, MID_EDGES[4]].reshape(-1, 2)
    keep[keep] = match_rows(pairs, edges[keep], after.n_points) >= 0
    return keep
