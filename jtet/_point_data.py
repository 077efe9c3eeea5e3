"""Point data (``TetMesh.point_data``): carried through a run (the values at the
vertices a run moved or inserted, read off the input mesh at their new positions), and
split into and joined from the scalar columns of the formats that have no arrays
(TetGen point attributes, Medit solutions of odd widths)."""

from __future__ import annotations

import re

import numpy as np
from jaxtyping import Bool, Float

from ._mesh import TetMesh


def moved_vertices(before: TetMesh, after: TetMesh) -> Bool[np.ndarray, " n_after"]:
    """(n_after,) bool: the vertices of ``after`` that are not where they were in
    ``before``: moved ones, and those appended (ids from ``before.n_points`` on). A run
    never renumbers vertices, so vertex i of both meshes is one vertex."""
    n = min(before.n_points, after.n_points)
    moved = np.ones(after.n_points, bool)
    moved[:n] = (after.points[:n] != before.points[:n]).any(axis=1)
    return moved


def _interpolated(
    before: TetMesh, arrays: dict, where: Float[np.ndarray, "q 3"]
) -> tuple[dict, Bool[np.ndarray, " q"]]:
    """(values {name: (q, ...) float64 array}, found (q,) bool): the float64 point
    ``arrays`` of ``before`` interpolated linearly at the points ``where`` in the tet of
    ``before`` holding each, by VTK's probe filter (a static cell locator over the tets).
    Points in no tet are not ``found`` (their values are garbage)."""
    import pyvista as pv

    cells = np.concatenate([np.full((before.n_tets, 1), 4, np.int64), before.tets], axis=1)
    source = pv.UnstructuredGrid(
        cells.ravel(), np.full(before.n_tets, pv.CellType.TETRA, np.uint8), before.points
    )
    for name, a in arrays.items():
        source.point_data[name] = a
    probed = pv.PolyData(where).sample(source, pass_cell_data=False, pass_point_data=False)
    found = np.asarray(probed.point_data["vtkValidPointMask"]).astype(bool)
    return {name: np.asarray(probed.point_data[name]) for name in arrays}, found


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
    values, found = _interpolated(before, floats, where) if floats else ({}, None)
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
