"""Point data (``TetMesh.point_data``): carried through a run (the values at the
vertices a run moved or inserted, read off the input mesh at their new positions), and
split into and joined from the scalar columns of the formats that have no arrays
(TetGen point attributes, Medit solutions of odd widths)."""

from __future__ import annotations

import re

import numpy as np
from jaxtyping import Bool, Float, Int

from ._mesh import TetMesh
from ._topology import _stable_sort, csr_rows, distinct_values, first_of_runs


def moved_vertices(before: TetMesh, after: TetMesh) -> Bool[np.ndarray, " n_after"]:
    """(n_after,) bool: the vertices of ``after`` that are not where they were in
    ``before``: moved ones, and those appended (ids from ``before.n_points`` on). A run
    never renumbers vertices, so vertex i of both meshes is one vertex."""
    n = min(before.n_points, after.n_points)
    moved = np.ones(after.n_points, bool)
    moved[:n] = (after.points[:n] != before.points[:n]).any(axis=1)
    return moved


# Candidate (point, tet) pairs whose weights are computed at once: bounds the
# temporaries (two dozen 1-D float64 arrays of this length, 2 MB each) whatever the
# mesh's size.
_PAIR_CHUNK = 1 << 18


# A tet holds a point when every barycentric weight of the point is at least -this: a
# vertex slid within a boundary face lies in its plane, and its weight towards the apex
# off that face rounds to +-1e-17 (all its tets may give a negative one). A weight of
# -1e-12 extrapolates a field by 1e-12 of its change over the tet, where the tet beyond
# that VTK's probe took was off by up to 0.03 (experiments/results/point_data.md).
WEIGHT_SLACK = 1e-12


def _cross(u: list, v: list) -> list:
    """u x v of vectors given as their three coordinate arrays."""
    return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]


def _dot(u: list, v: list) -> np.ndarray:
    """u . v of vectors given as their three coordinate arrays."""
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _holding_tets(
    mesh: TetMesh,
    where: Float[np.ndarray, "q 3"],
    point_of: Int[np.ndarray, " k"],
    tet_of: Int[np.ndarray, " k"],
    found: Bool[np.ndarray, " q"],
    corners: Int[np.ndarray, "q 4"],
    weights: Float[np.ndarray, "q 4"],
) -> None:
    """For every point ``where[i]`` not yet ``found``, the first of its candidate tets
    (the pairs ``(point_of, tet_of)``, grouped by point) of ``mesh`` that holds it,
    every barycentric weight >= -``WEIGHT_SLACK`` as computed (a point on a face shared
    by two candidates takes either: both give one value to rounding): its vertex ids and
    weights go to ``corners`` and ``weights`` and it is marked ``found`` (all three
    updated in place)."""
    tets = mesh.tets
    cols = [np.ascontiguousarray(mesh.points[:, k]) for k in range(3)]
    at = [np.ascontiguousarray(where[:, k]) for k in range(3)]
    for c0 in range(0, len(point_of), _PAIR_CHUNK):
        o, t = point_of[c0 : c0 + _PAIR_CHUNK], tet_of[c0 : c0 + _PAIR_CHUNK]
        corner = np.take(tets, t, axis=0)  # np.take: 3-4x faster than indexing rows
        # coordinates relative to corner 0, one 1-D array per axis (contiguous gathers
        # and arithmetic: ~3x faster than rows of (k, 3) arrays)
        p0 = [np.take(x, corner[:, 0]) for x in cols]
        a, b, c = ([np.take(x, corner[:, i]) - x0 for x, x0 in zip(cols, p0)] for i in (1, 2, 3))
        r = [np.take(x, o) - x0 for x, x0 in zip(at, p0)]
        bc, ca, ab = _cross(b, c), _cross(c, a), _cross(a, b)
        det = _dot(a, bc)  # six times the volume: > 0 for a positive tet
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.stack([_dot(r, bc), _dot(r, ca), _dot(r, ab)], axis=1) / det[:, None]
        w0 = 1.0 - w[:, 0] - w[:, 1] - w[:, 2]
        low = -WEIGHT_SLACK
        inside = (det > 0) & (w[:, 0] >= low) & (w[:, 1] >= low) & (w[:, 2] >= low) & (w0 >= low)
        hit = np.flatnonzero(inside & ~found[o])
        hit = hit[first_of_runs(o[hit])]  # one tet per point
        rows = o[hit]
        corners[rows] = corner[hit]
        weights[rows, 0], weights[rows, 1:] = w0[hit], w[hit]
        found[rows] = True


def _star_pairs(
    tets: Int[np.ndarray, "m 4"], index_of: Int[np.ndarray, " n"]
) -> tuple[Int[np.ndarray, " p"], Int[np.ndarray, " p"]]:
    """(index (p,), tet (p,)): a pair for every tet of ``tets`` at each vertex v with
    ``index_of[v] >= 0`` (-1: none), by increasing index (one scan of the tets' vertex
    slots and one sort of the pairs)."""
    flat = tets.reshape(-1)
    slots = np.flatnonzero(index_of[flat] >= 0)
    index = index_of[flat[slots]]
    perm, index = _stable_sort(index, int(index.max(initial=0)).bit_length())
    return index, slots[perm] // 4


def _tets_around(
    before: TetMesh, point_of: Int[np.ndarray, " k"], vertex: Int[np.ndarray, " k"]
) -> tuple[Int[np.ndarray, " p"], Int[np.ndarray, " p"]]:
    """(point (p,), tet (p,)) candidate pairs, each once: for each pair (point, vertex
    of ``before``), the point with every tet of ``before`` at the vertex."""
    mark = np.zeros(before.n_points, bool)
    mark[vertex] = True
    vertices = np.flatnonzero(mark)
    index_of = np.full(before.n_points, -1, np.int64)
    index_of[vertices] = np.arange(len(vertices))
    index = index_of[vertex]
    star_index, star_tet = _star_pairs(before.tets, index_of)
    ptr = np.searchsorted(star_index, np.arange(len(vertices) + 1))
    pos, _ = csr_rows(ptr, index)
    # a tet at two of a point's vertices comes twice: tested once (~3x fewer pairs)
    m = np.int64(before.n_tets)
    pairs = distinct_values(np.repeat(point_of, ptr[index + 1] - ptr[index]) * m + star_tet[pos])
    return pairs // before.n_tets, pairs % before.n_tets


def _float_values(
    before: TetMesh, after: TetMesh, floats: dict, moved: Bool[np.ndarray, " n_after"], where
) -> tuple[dict, Bool[np.ndarray, " q"]]:
    """(values {name: (q, ...) float64}, found (q,) bool): the float64 point arrays
    ``floats`` of ``before`` interpolated linearly at the positions ``where`` (q, 3) of
    the ``moved`` vertices of ``after`` (q of them), in a tet of ``before`` holding each.

    A run moves a vertex within the neighbourhood of where it was. Each moved vertex
    looks for the tet holding it in its own input star first (the 983k-tet cube: all
    65.6k), then, with the inserted vertices, among the input tets at the vertices of
    its new star, each by barycentric weights (``_holding_tets``). The rest go to VTK's
    probe, over those tets and then over every tet, and then to the input tets at the
    vertices of the tet it found: its cells' inside test has a tolerance, and near a
    face it may return the tet beyond, whose extrapolation of a curved field was off by
    up to 5e-4 on real runs' outputs. A point in none of those takes the probe's value
    if the probe found one (a vertex slid just outside the input's boundary), else it is
    not ``found``."""
    q = len(where)
    ids = np.flatnonzero(moved)
    corners = np.zeros((q, 4), np.int64)
    weights = np.zeros((q, 4))
    found = np.zeros(q, bool)
    # own stars: the tets of before at each moved vertex that before has
    own = np.full(before.n_points, -1, np.int64)
    old = ids < before.n_points
    own[ids[old]] = np.flatnonzero(old)
    _holding_tets(before, where, *_star_pairs(before.tets, own), found, corners, weights)
    rest = np.flatnonzero(~found)
    local = None  # the input tets around the points still not found
    if len(rest):  # the input tets at the vertices of each one's star in after
        at = np.full(after.n_points, -1, np.int64)
        at[ids[rest]] = rest
        point_of, tet_of = _star_pairs(after.tets, at)
        near = distinct_values(point_of[:, None] * np.int64(after.n_points) + after.tets[tet_of])
        point_of, vertex = near // after.n_points, near % after.n_points
        old = vertex < before.n_points
        point_of, tet_of = _tets_around(before, point_of[old], vertex[old])
        _holding_tets(before, where, point_of, tet_of, found, corners, weights)
        local = np.zeros(before.n_tets, bool)
        local[tet_of[~found[point_of]]] = True
        local = np.flatnonzero(local)
    # VTK's probe (over those tets, then every tet), then the input tets at the vertices
    # of the tet it found; its own value where none of them holds the point
    probed = {name: np.zeros((q, *a.shape[1:])) for name, a in floats.items()}
    probe_hit = np.zeros(q, bool)
    rest = np.flatnonzero(~found)
    sources = [None] if local is None or len(local) == before.n_tets else [local, None]
    for tet_ids in sources if len(rest) else []:
        got, hit, tet = _probed(before, floats, where[rest], tet_ids)
        for name in floats:
            probed[name][rest[hit]] = got[name][hit]
        probe_hit[rest[hit]] = True
        pairs = _tets_around(before, np.repeat(rest[hit], 4), before.tets[tet[hit]].reshape(-1))
        _holding_tets(before, where, *pairs, found, corners, weights)
        rest = rest[~hit]
        if not len(rest):
            break
    values = {}
    extrapolated = probe_hit & ~found
    for name, a in floats.items():
        corner_values = np.take(a.reshape(len(a), -1), corners, axis=0)  # (q, 4, width)
        values[name] = np.einsum("qj,qjw->qw", weights, corner_values).reshape(q, *a.shape[1:])
        values[name][extrapolated] = probed[name][extrapolated]
    return values, found | probe_hit


def tet_grid(mesh: TetMesh, tet_ids: Int[np.ndarray, " k"]):
    """A ``pyvista.UnstructuredGrid`` of the tets ``tet_ids`` of ``mesh`` (all its points),
    each cell holding its tet id in the cell array ``jtet_tet``."""
    import pyvista as pv

    tets = mesh.tets[tet_ids]
    cells = np.concatenate([np.full((len(tets), 1), 4, np.int64), tets], axis=1)
    grid = pv.UnstructuredGrid(
        cells.ravel(), np.full(len(tets), pv.CellType.TETRA, np.uint8), mesh.points
    )
    grid.cell_data["jtet_tet"] = np.asarray(tet_ids, np.int64)
    return grid


def _probed(
    before: TetMesh,
    arrays: dict,
    where: Float[np.ndarray, "q 3"],
    tet_ids: Int[np.ndarray, " k"] | None = None,
) -> tuple[dict, Bool[np.ndarray, " q"], Int[np.ndarray, " q"]]:
    """(values {name: (q, ...) float64 array}, found (q,) bool, tet (q,)): the float64
    point ``arrays`` of ``before`` interpolated linearly at the points ``where`` by VTK's
    probe filter, in the tet ``tet`` of ``before`` (among ``tet_ids``, default all) it
    found holding each point (within its tolerance). Points in none are not ``found``
    (their values are garbage)."""
    import pyvista as pv

    source = tet_grid(before, np.arange(before.n_tets) if tet_ids is None else tet_ids)
    for name, a in arrays.items():
        source.point_data[name] = a
    probed = pv.PolyData(where).sample(source, pass_cell_data=False, pass_point_data=False)
    found = np.asarray(probed.point_data["vtkValidPointMask"]).astype(bool)
    values = {name: np.asarray(probed.point_data[name]).reshape(len(where), *a.shape[1:])
              for name, a in arrays.items()}  # fmt: skip
    return values, found, np.asarray(probed.point_data["jtet_tet"], np.int64)


def carried_point_data(before: TetMesh, after: TetMesh) -> tuple[dict, int]:
    """``before.point_data`` carried onto the vertices of ``after``, the result of a run
    on ``before`` (same vertex ids; appended vertices are new).

    A vertex left in place keeps its values exactly. At a moved or new vertex the
    floating-point arrays are interpolated linearly in the tet of ``before`` holding its
    position (exact for a field linear over the mesh, to rounding), and integer arrays
    (markers, ids) take the value of the nearest vertex of ``before``, as do the float
    arrays at a position in no tet of ``before`` (a vertex slid off a curved boundary).

    Returns:
        ``({name: (after.n_points, ...) array of the input's dtype}, number of moved or
        new vertices in no tet of ``before``)``.
    """
    data = before.point_data
    moved = moved_vertices(before, after)
    if not data or not moved.any():
        return dict(data), 0
    from scipy.spatial import cKDTree

    where = np.ascontiguousarray(after.points[moved])
    floats = {k: a.astype(np.float64) for k, a in data.items() if a.dtype.kind == "f"}
    values, found = _float_values(before, after, floats, moved, where) if floats else ({}, None)
    n_outside = 0 if found is None else int((~found).sum())
    need_nearest = len(floats) < len(data) or n_outside
    nearest = cKDTree(before.points).query(where)[1] if need_nearest else None
    kept = min(before.n_points, after.n_points)
    carried = {}
    for name, a in data.items():
        out = np.empty((after.n_points, *a.shape[1:]), a.dtype)
        out[:kept] = a[:kept]
        if name in values:
            v = values[name].reshape(len(where), *a.shape[1:])
            if n_outside:
                v[~found] = a[nearest[~found]]
            out[moved] = v.astype(a.dtype)
        else:
            out[moved] = a[nearest]
        carried[name] = out
    return carried, n_outside


def scalar_columns(point_data: dict) -> dict:
    """``point_data`` as float64 scalar columns {name: (n,)}: an (n, k) array as the k
    columns ``name[0]`` ... ``name[k-1]`` (``joined_columns`` joins them again)."""
    out = {}
    for name, a in point_data.items():
        a = np.asarray(a, np.float64)
        if a.ndim == 1:
            out[name] = a
        else:
            out.update({f"{name}[{i}]": a[:, i] for i in range(a.shape[1])})
    return out


def joined_columns(columns: dict) -> dict:
    """The arrays of ``scalar_columns``' output: runs of columns ``name[0]``,
    ``name[1]``, ... become one (n, k) array ``name``; other entries stay as they are."""
    names = list(columns)
    out: dict = {}
    i = 0
    while i < len(names):
        first = re.fullmatch(r"(.+)\[0\]", names[i])
        if first and first.group(1) not in columns and first.group(1) not in out:
            base, j = first.group(1), i
            while j < len(names) and names[j] == f"{base}[{j - i}]":
                j += 1
            out[base] = np.column_stack([columns[n] for n in names[i:j]])
            i = j
            continue
        out.setdefault(names[i], columns[names[i]])
        i += 1
    return out
