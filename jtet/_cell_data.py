"""Cell data (``TetMesh.cell_data``) carried through a run: the surfaces where an
integer array changes value are kept for the run, as region interfaces are, and every
tet of the result takes the values of an input tet it overlaps."""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int

from ._mesh import TetMesh
from ._point_data import moved_vertices, tet_grid
from ._predicates import orient3d
from ._topology import _stable_sort, distinct_values

# Points inside a tet (barycentric weights, rows) at which a new tet looks for the input
# tet that holds it: the centroid, then four points nearer one corner each, for when the
# centroid lies on a face of the input mesh (a test whose answer is not strict).
_SAMPLE_WEIGHTS = np.array(
    [[0.25, 0.25, 0.25, 0.25]] + [[0.4 if i == j else 0.2 for j in range(4)] for i in range(4)]
)


def interface_faces(mesh: TetMesh, ids: list[str]) -> Int[np.ndarray, "k 3"]:
    """(k, 3) sorted vertex triples of the inner faces between two tets of one region
    whose integer cell arrays differ: where an integer array (a material id, a
    partition) changes value inside a region. A run that keeps them in place keeps every
    tet inside one piece of constant values. The arrays of ids ``ids`` (``id_arrays``)
    are left out: kept in place, their faces would be every face of the mesh."""
    ints = [a for k, a in mesh.cell_data.items() if a.dtype.kind in "iu" and k not in ids]
    if not ints:
        return np.zeros((0, 3), np.int64)
    topo = mesh.topology
    inner = topo.face_tets[:, 1] >= 0
    t0 = topo.face_tets[inner, 0].astype(np.int64)
    t1 = topo.face_tets[inner, 1].astype(np.int64)
    differ = np.zeros(len(t0), bool)
    for a in ints:
        rows = a.reshape(len(a), -1)
        differ |= (rows[t0] != rows[t1]).any(axis=1)
    differ &= mesh.region[t0] == mesh.region[t1]
    return np.asarray(topo.faces[inner][differ], np.int64)


def id_arrays(mesh: TetMesh) -> list[str]:
    """The names of the integer cell arrays that hold a distinct value (or row) in every
    tet of a mesh of two or more: ids of the input's elements, not labels of pieces. A
    run carries them as provenance (a new tet gets the id of an input tet it overlaps)."""
    out = []
    for name, a in mesh.cell_data.items():
        if a.dtype.kind in "iu" and len(a) > 1:
            # rows of a 2-D array; a 1-D one by value (a sort: np.unique took 0.8 s on a
            # million ids)
            n_distinct = len(np.unique(a, axis=0) if a.ndim == 2 else distinct_values(a))
            if n_distinct == len(a):
                out.append(name)
    return out


def _same_tets(before: TetMesh, after: TetMesh) -> Int[np.ndarray, " m_after"]:
    """(after.n_tets,) id of the tet of ``before`` that each tet of ``after`` is (the
    same four vertex ids, moved or not), -1 for the others. Tets are keyed by their
    sorted vertex ids packed into two int64 and matched through one ordering by both."""
    n = max(before.n_points, after.n_points)

    def keys(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = np.sort(np.asarray(tets, np.int64), axis=1)
        return s[:, 0] * n + s[:, 1], s[:, 2] * n + s[:, 3]

    hb, lb = keys(before.tets)
    ha, la = keys(after.tets)
    hi, lo = np.concatenate([hb, ha]), np.concatenate([lb, la])
    # np.lexsort((lo, hi)) as two stable value sorts, low key first (983k-tet meshes:
    # 0.82 -> 0.38 s)
    by_lo, _ = _stable_sort(lo, int(lo.max(initial=0)).bit_length())
    by_hi, _ = _stable_sort(hi[by_lo], int(hi.max(initial=0)).bit_length())
    order = by_lo[by_hi]
    same = (hi[order[1:]] == hi[order[:-1]]) & (lo[order[1:]] == lo[order[:-1]])
    # a mesh holds no tet twice, so an equal pair is one tet of each mesh
    first, second = order[:-1][same], order[1:][same]
    b, a = np.minimum(first, second), np.maximum(first, second) - before.n_tets
    out = np.full(after.n_tets, -1, np.int64)
    out[a] = b
    return out


def _strictly_inside(
    x: Float[np.ndarray, "q 3"], points: Float[np.ndarray, "n 3"], tets: Int[np.ndarray, "q 4"]
) -> Bool[np.ndarray, " q"]:
    """(q,) whether x[i] lies strictly inside the positively oriented tet tets[i], by
    exact orientation tests (a point on a face, or a tet that is flat or inverted: no)."""
    p = points[tets]
    inside = orient3d(p[:, 0], p[:, 1], p[:, 2], p[:, 3]) > 0
    for i in range(4):
        corners = [p[:, j] if j != i else x for j in range(4)]
        inside &= orient3d(*corners) > 0
    return inside


def _holding_tets(
    before: TetMesh, after: TetMesh, which: Int[np.ndarray, " q"]
) -> tuple[Int[np.ndarray, " q"], Bool[np.ndarray, " q"]]:
    """(ids (q,) of tets of ``before``, overlaps (q,) bool): for the tets ``which`` of
    ``after``, a tet of ``before`` holding a point of each. VTK's probe filter finds the
    tet holding the sample point; exact orientation tests then confirm that the point is
    strictly inside both tets, so that the two overlap in a volume (``overlaps``). A tet
    for which no sample point confirms gets the input tet of the nearest centroid.

    The centroids are looked up among all tets of ``before``; the few tets whose
    centroid is not confirmed try their other sample points among the input tets at a
    vertex of theirs or of the tet VTK found (a locator over the whole mesh costs
    ~0.5 s at 1.1M tets, one over these tets next to nothing)."""
    import pyvista as pv
    from scipy.spatial import cKDTree

    corners = after.points[after.tets[which]]
    ids = np.full(len(which), -1, np.int64)
    overlaps = np.zeros(len(which), bool)
    todo = np.arange(len(which))
    source = tet_grid(before, np.arange(before.n_tets))
    for i, weights in enumerate(_SAMPLE_WEIGHTS):
        if not len(todo):
            break
        x = np.einsum("j,qjk->qk", weights, corners[todo])
        # no tolerance: with VTK's default a point near a face may come back in the tet
        # beyond it (~5 % of the centroids of a run's new tets)
        probed = pv.PolyData(x).sample(
            source, tolerance=0.0, pass_cell_data=False, pass_point_data=False
        )
        found = np.asarray(probed.point_data["vtkValidPointMask"]).astype(bool)
        hit = np.asarray(probed.point_data["jtet_tet"], np.int64)
        ok = found.copy()
        ok[found] = _strictly_inside(x[found], before.points, before.tets[hit[found]])
        ok[found] &= _strictly_inside(x[found], after.points, after.tets[which[todo[found]]])
        ids[todo[ok]], overlaps[todo[ok]] = hit[ok], True
        if i == 0 and (~ok).any():
            near = np.zeros(max(before.n_points, after.n_points), bool)
            near[after.tets[which[todo[~ok]]]] = True
            near[before.tets[hit[found & ~ok]]] = True
            source = tet_grid(before, np.flatnonzero(near[before.tets].any(axis=1)))
        todo = todo[~ok]
    if len(todo):
        centroids = before.points[before.tets].mean(axis=1)
        mine = after.points[after.tets[which[todo]]].mean(axis=1)
        ids[todo] = cKDTree(centroids).query(mine)[1]
    return ids, overlaps


def carried_cell_data(before: TetMesh, after: TetMesh) -> tuple[dict, int, int]:
    """``before.cell_data`` carried onto the tets of ``after``, the result of a run on
    ``before`` (same vertex ids; appended vertices are new).

    A tet of ``after`` that is a tet of ``before`` (the same vertices, none moved) keeps
    its values exactly. Any other tet takes the values of a tet of ``before`` that it
    overlaps in a volume: the tet with its vertex ids if that still holds its centroid,
    else one found at its centroid (or at a point nearer a corner), each confirmed by
    exact orientation tests; when none is confirmed (a tet slid off a curved boundary),
    the values of the input tet with the nearest centroid. Integer arrays are exact when
    the run kept the ``interface_faces`` in place: every tet then lies in one piece of
    constant values.

    Returns:
        ``({name: (after.n_tets, ...) array of the input's dtype}, number of tets that
        got values from an input tet, number of those without a confirmed overlap)``.
    """
    data = before.cell_data
    if not data:
        return {}, 0, 0
    same = _same_tets(before, after)
    unmoved = ~moved_vertices(before, after)[after.tets].any(axis=1)
    source = np.where(unmoved, same, -1)
    n_new = int((source < 0).sum())
    # A tet whose vertices moved but kept their ids nearly always still holds its
    # centroid strictly inside its input self (Gmsh cube, 182k tets: 99.7 % of 102k).
    # Input tets do not overlap, so that is the input tet holding the centroid, the one
    # the probe of ``_holding_tets`` looks for, confirmed by the same exact tests; only
    # the others are probed. (VTK's rounded test near a face sometimes returned the tet
    # beyond it, and the probe then took an input tet holding a point nearer a corner:
    # 54 of 788k tets at 983k.) The 983k-tet cube's carrying took 7.5 -> 3.3 s.
    moved_same = np.flatnonzero((same >= 0) & ~unmoved)
    if len(moved_same):
        x = np.einsum("j,qjk->qk", _SAMPLE_WEIGHTS[0], after.points[after.tets[moved_same]])
        held = _strictly_inside(x, before.points, before.tets[same[moved_same]])
        held &= _strictly_inside(x, after.points, after.tets[moved_same])
        source[moved_same[held]] = same[moved_same[held]]
    new = np.flatnonzero(source < 0)
    n_unconfirmed = 0
    if len(new):
        source[new], overlaps = _holding_tets(before, after, new)
        n_unconfirmed = int((~overlaps).sum())
    return {name: a[source] for name, a in data.items()}, n_new, n_unconfirmed
