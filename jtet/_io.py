"""Mesh input and output: pyvista grids, mesh files, and the demo meshes shipped with jtet.

Readers: ``.vtu`` / ``.vtk`` through VTK's own readers; ``.msh`` (Gmsh 2.2 and 4.1),
``.mesh`` (Medit) and ``.node`` / ``.ele`` (TetGen) through meshio; ``.meshb`` (binary
Medit), ``.xdmf``, ``.inp``, ``.vol``, ``.exo`` and ``.med`` by jtet's own modules. Every
failure
is a ``MeshFileError`` (the file) or a ``MeshInputError`` (its contents) with the path and a
one-line reason; VTK's and meshio's console chatter is captured, never printed.

Region labels come from the first cell array found among ``REGION_ARRAYS``; Gmsh files
use their physical volume tags, or the elementary (volume entity) tags when no tet is in a
physical group, so the surfaces between volumes stay (``_gmsh_regions``). Cells of lower
dimension that are faces, edges and vertices of the tets become protected entities:
triangles with their labels (physical surface tags, references, facet markers), lines
and points (``_mesh_cells``, ``_mesh_vertices``), which the Gmsh and Medit savers write
back; other such cells are ignored with a warning. Any other 3-D cell
type is an error. meshio's Gmsh readers are mended during reads (``_gmsh_read``) for
files meshio alone refuses: ``Mesh.SaveAll``, views saved with the mesh, partitions.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import io
import itertools
import os
import re
import secrets
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np

from ._errors import MeshFileError, MeshInputError
from ._gmsh_read import gmsh_read_mends
from ._medit import (
    _append_required,
    _medit_readable_copy,
    _medit_required,
    _medit_required_tets,
)
from ._mesh import TetMesh
from ._tetgen import NAMES_COMMENT

#: Cell arrays read as region labels, in order of preference. ``region`` is jtet's own;
#: meshio names the others after the format (Gmsh physical tags, Medit references, TetGen
#: region attributes); Gmsh's own VTK export writes its elementary tags as ``CellEntityIds``.
REGION_ARRAYS = ("region", "gmsh:physical", "medit:ref", "CellEntityIds", "tetgen:ref")

#: Field-data arrays in which ``mesh_to_grid`` stores the protected faces / edges.
PROTECTED_FACES_ARRAY = "jtet:protected_faces"
PROTECTED_EDGES_ARRAY = "jtet:protected_edges"
PROTECTED_VERTICES_ARRAY = "jtet:protected_vertices"
PROTECTED_EDGE_LABELS_ARRAY = "jtet:protected_edge_labels"
PROTECTED_VERTEX_LABELS_ARRAY = "jtet:protected_vertex_labels"
#: field data of VTK files: the UTF-8 bytes (uint8) of a JSON list of [dim, label, name]
#: (VTK's string arrays, as pyvista handles them, hold ASCII only; Gmsh names are UTF-8)
LABEL_NAMES_ARRAY = "jtet:label_names"
#: field data of VTK files: the UTF-8 bytes of a JSON list of the periodic links,
#: [dim, slave tag, master tag, 16 affine numbers or null, [[slave, master], ...]]
PERIODIC_ARRAY = "jtet:periodic"
#: field data of VTK files: the UTF-8 bytes of a JSON list of the node sets, each
#: [name, [vertex ids], label or null]
NODE_SETS_ARRAY = "jtet:node_sets"
PROTECTED_TETS_ARRAY = "jtet:protected_tets"
PROTECTED_FACE_LABELS_ARRAY = "jtet:protected_face_labels"

_VTK_TETRA = 10
_VTK_VERTEX, _VTK_LINE, _VTK_TRIANGLE = 1, 3, 5
# Quadratic and higher-order tetrahedra: VTK_QUADRATIC_TETRA, VTK_HIGHER_ORDER_TETRAHEDRON,
# VTK_LAGRANGE_TETRAHEDRON, VTK_BEZIER_TETRAHEDRON.
_VTK_HIGH_ORDER_TETS = (24, 64, 71, 78)
# VTK_QUADRATIC_TETRA, _TRIANGLE, _EDGE -> the linear cell of their corners
_VTK_QUADRATIC = {24: 10, 22: 5, 21: 3}
_VTK_QUADRATIC_TETRA = 24
# the same for meshio's cell blocks: (linear type, its corners)
_MESHIO_QUADRATIC = {"tetra10": ("tetra", 4), "triangle6": ("triangle", 3), "line3": ("line", 2)}
# and the other way: the quadratic block of a linear one
_QUADRATIC_BLOCK = {linear: quadratic for quadratic, (linear, _) in _MESHIO_QUADRATIC.items()}

_READ_FORMATS = {
    ".vtu": "vtu",
    ".vtk": "vtk",
    ".msh": "gmsh",
    ".mesh": "medit",
    ".meshb": "medit",
    ".node": "tetgen",
    ".ele": "tetgen",
    ".xdmf": "xdmf",
    ".inp": "abaqus",
    ".vol": "netgen",
    ".exo": "exodus",
    ".e": "exodus",
    ".ex2": "exodus",
    ".g": "exodus",
    ".med": "med",
}
_FORMAT_NAMES = {
    "vtu": "VTK XML unstructured grid",
    "vtk": "legacy VTK",
    "gmsh": "Gmsh",
    "medit": "Medit",
    "tetgen": "TetGen",
    "xdmf": "XDMF",
    "abaqus": "Abaqus input",
    "netgen": "Netgen",
    "exodus": "Exodus II",
    "med": "MED",
}
_KNOWN_EXTENSIONS = ", ".join(_READ_FORMATS)


# ---------------------------------------------------------------------------------------
# pyvista bridge


def _vtk_cell_dimension(cell_type: int) -> int:
    """Topological dimension of a VTK cell type (3 when VTK cannot tell: be strict)."""
    try:
        from vtkmodules.vtkCommonDataModel import vtkCellTypeUtilities as _ctu
    except ImportError:  # VTK < 9.6
        from vtkmodules.vtkCommonDataModel import vtkCellTypes as _ctu
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            d = int(_ctu.GetDimension(int(cell_type)))
    except Exception:
        return 3
    return d if 0 <= d <= 3 else 3


def _vtk_cell_name(cell_type: int) -> str:
    import pyvista as pv

    try:
        return f"VTK_{pv.CellType(int(cell_type)).name}"
    except ValueError:
        return f"VTK cell type {int(cell_type)}"


def _non_tet_message(
    source: str, names: list[str], counts: list[int], high_order: bool, linear_reads: bool = True
) -> str:
    """The refusal of a file's non-tet 3-D cells, with their names and counts;
    ``high_order``: some are quadratic or higher-order tets, which ``--linear`` reads as
    linear ones (``linear_reads``: this reader can)."""
    total = sum(counts)
    listing = ", ".join(f"{n} x {c}" for n, c in zip(names, counts, strict=True))
    msg = f"{source}: {total} cells are not tetrahedra ({listing}); jtet needs a pure tet mesh"
    if high_order and linear_reads:
        msg += (
            " (quadratic / higher-order tetrahedra: jtet improves linear ones; --linear, "
            "jtet.load(path, linear=True), reads 10-node tets as their 4 corner vertices)"
        )
    elif high_order:
        msg += (
            " (quadratic / higher-order tetrahedra are not supported: keep only their 4 corner"
            " vertices to get a linear tet mesh)"
        )
    return msg


def _labels(values, name: str, source: str) -> np.ndarray:
    """Integer region labels from a cell array (integral floats are accepted)."""
    a = np.asarray(values)
    if a.ndim == 2 and a.shape[1] == 1:
        a = a[:, 0]
    if a.ndim != 1:
        raise MeshInputError(
            f"{source}: cell array {name!r} has shape {a.shape}, not one label per cell"
        )
    if np.issubdtype(a.dtype, np.integer) or a.dtype == bool:
        return a.astype(np.int64)
    if np.issubdtype(a.dtype, np.floating) and np.isfinite(a).all() and (a == np.round(a)).all():
        return a.astype(np.int64)
    raise MeshInputError(f"{source}: cell array {name!r} does not hold integer region labels")


def _pick_region(arrays: dict, n_cells: int, keep: np.ndarray, source: str) -> np.ndarray | None:
    """Region labels of the kept cells from the first of ``REGION_ARRAYS`` in ``arrays``."""
    for name in REGION_ARRAYS:
        if name in arrays:
            labels = _labels(arrays[name], name, source)
            if len(labels) != n_cells:
                raise MeshInputError(
                    f"{source}: cell array {name!r} has {len(labels)} values for {n_cells} cells"
                )
            return labels[keep]
    return None


def _field_entities(grid, name: str, k: int, source: str) -> np.ndarray | None:
    """The vertex-id rows (j, k) of field-data array ``name`` (``mesh_to_grid``'s)."""
    if name not in grid.field_data:
        return None
    a = np.asarray(grid.field_data[name])
    if a.size % k or not (np.issubdtype(a.dtype, np.integer) or a.size == 0):
        raise MeshInputError(
            f"{source}: field data {name!r} ({a.size} values of {a.dtype}) is not a list of "
            f"{k}-vertex rows of ids"
        )
    return a.reshape(-1, k).astype(np.int64)


# arrays a mesh file holds that jtet reads, or writes itself (its per-tet quality
# arrays: recomputed for every output), or that are bookkeeping of VTK and meshio (whose
# names hold their format's tag: "gmsh:physical", "walls-gmsh:bounding_entities")
_KNOWN_ARRAY_PREFIXES = ("quality_", "vtk")
_KNOWN_ARRAYS = {*REGION_ARRAYS, "min_dihedral", "max_dihedral", "volume"}


def _warn_dropped_arrays(point_arrays: list, cell_arrays: list, source: str) -> None:
    """Warn that a file's point and cell arrays (a temperature, a material id) do not
    reach the output: jtet carries region labels and arrays of numbers per vertex and per
    tet (``grid_point_data``, ``grid_cell_data``, Gmsh views: ``_gmsh_views``), not
    strings, tensors or views that do not parse, and its quality arrays it computes
    itself."""
    groups = []
    for what, names in (("point", point_arrays), ("cell", cell_arrays)):
        names = [n for n in names if _carried_array_name(n)]
        if names:
            shown = ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")
            groups.append(f"{len(names)} {what} array(s) ({shown})")
    if groups:
        warnings.warn(
            f"{source}: jtet reads region labels and the arrays of numbers its formats "
            f"hold per point and per tet; not read: {' and '.join(groups)}",
            stacklevel=3,
        )


def unstructured_grid(grid, source: str = "pyvista grid"):
    """``grid`` as a ``pyvista.UnstructuredGrid``: anything ``pyvista.wrap`` turns into
    a dataset (a VTK object, a ``meshio.Mesh``, ...), cast; ``MeshInputError`` for a
    MultiBlock or an object pyvista cannot wrap."""
    import pyvista as pv

    if not isinstance(grid, pv.UnstructuredGrid):
        try:
            wrapped = pv.wrap(grid)
        except Exception:
            wrapped = None
        if wrapped is None or isinstance(wrapped, pv.MultiBlock):
            what = "a pyvista MultiBlock (combine() it first)" if wrapped is not None else ""
            raise MeshInputError(
                f"{source}: cannot read a tet mesh from {what or type(grid).__name__}; "
                "pass a pyvista.UnstructuredGrid of tetra cells"
            )
        grid = (
            wrapped
            if isinstance(wrapped, pv.UnstructuredGrid)
            else wrapped.cast_to_unstructured_grid()
        )
    return grid


def grid_to_arrays(grid, source: str = "pyvista grid"):
    """Arrays of a tet mesh from a ``pyvista.UnstructuredGrid``.

    Accepts anything ``pyvista.wrap`` turns into a dataset (a VTK object, a ``meshio.Mesh``,
    ...). Cells of dimension 0-2 are ignored, but triangles that are faces of the tets
    become protected faces, labelled by the region array; every 3-D cell must be a linear
    tetrahedron (``VTK_TETRA``), otherwise ``MeshInputError`` names the offending types
    and counts.

    Returns:
        ``(points (n, 3) float64, tets (m, 4) int64, region (m,) int64 or None,
        protected_faces (k, 3) or None, protected_edges (k, 2) or None, protected face
        labels (k,) or None, protected_vertices (j,) or None)``: the arguments of
        ``TetMesh.from_arrays``. Region labels come from the first of ``REGION_ARRAYS``;
        protected entities from the field data written by ``mesh_to_grid`` and the
        triangle, line and vertex cells that are faces, edges and vertices of the tets.
    """
    grid = unstructured_grid(grid, source)

    n_cells = grid.n_cells
    if n_cells == 0:
        raise MeshInputError(f"{source}: the mesh is empty: it has no cells")
    celltypes = np.asarray(grid.celltypes).astype(np.int64)
    # quadratic cells as their linear cells (``load(linear=True)``)
    quadratic = np.isin(celltypes, list(_VTK_QUADRATIC)) if reading_linear() else None
    if quadratic is not None:
        for quad, lin in _VTK_QUADRATIC.items():
            celltypes[celltypes == quad] = lin
    is_tet = celltypes == _VTK_TETRA
    kinds, counts = np.unique(celltypes[~is_tet], return_counts=True)
    dims = np.array([_vtk_cell_dimension(t) for t in kinds], dtype=np.int64)
    bad = dims == 3
    if bad.any():
        raise MeshInputError(
            _non_tet_message(
                source,
                [_vtk_cell_name(t) for t in kinds[bad]],
                counts[bad].tolist(),
                bool(np.isin(kinds[bad], _VTK_HIGH_ORDER_TETS).any()),
            )
        )
    if not is_tet.any():
        only = ", ".join(f"{_vtk_cell_name(t)} x {c}" for t, c in zip(kinds, counts, strict=True))
        hint = ""
        if any(_vtk_cell_dimension(t) == 2 for t in kinds):
            hint = "; a surface: mesh the volume it bounds with jtet tetrahedralize"
        raise MeshInputError(f"{source}: the mesh has no tetrahedra (only {only}){hint}")

    # ``cell_offsets`` (pyvista >= 0.46) was called ``offset`` before.
    offsets = getattr(grid, "cell_offsets", None)
    offsets = np.asarray(grid.offset if offsets is None else offsets, dtype=np.int64)
    conn = np.asarray(grid.cell_connectivity, dtype=np.int64)
    sizes = np.diff(offsets)[is_tet]
    if quadratic is not None and quadratic.any():
        # a quadratic cell of another size than its type's (a damaged file) names no
        # corners and mid-edge nodes
        expected = np.where(is_tet, 10, np.where(celltypes == 5, 6, 3))
        wrong = np.flatnonzero(quadratic & (np.diff(offsets) != expected))
        if len(wrong):
            c = int(wrong[0])
            raise MeshInputError(
                f"{source}: cell {c} is a quadratic cell of {int(np.diff(offsets)[c])} "
                f"vertices ({len(wrong)} such cell(s)); its type has {int(expected[c])}"
            )
        sizes = np.where(quadratic[is_tet], 4, sizes)
        _skip_vtk_mid_nodes(conn, offsets, quadratic)
    if (sizes != 4).any():
        c = int(np.flatnonzero(is_tet)[np.flatnonzero(sizes != 4)[0]])
        raise MeshInputError(
            f"{source}: cell {c} is a tetrahedron with {int(np.diff(offsets)[c])} vertices "
            f"({int((sizes != 4).sum())} such cell(s)); a tetrahedron has 4"
        )
    tets = conn[offsets[:-1][is_tet][:, None] + np.arange(4)]
    points = np.asarray(grid.points, dtype=np.float64)
    # by name: a damaged file may hold an array without one (pyvista then refuses dict())
    # the other arrays: grid_point_data and grid_cell_data
    cell_arrays = {k: grid.cell_data[k] for k in grid.cell_data.keys() if isinstance(k, str)}
    region = _pick_region(cell_arrays, n_cells, is_tet, source)
    pf = _field_entities(grid, PROTECTED_FACES_ARRAY, 3, source)
    pe = _field_entities(grid, PROTECTED_EDGES_ARRAY, 2, source)
    pv = _field_entities(grid, PROTECTED_VERTICES_ARRAY, 1, source)
    pv = None if pv is None else pv[:, 0]
    face_labels = _field_labels(grid, PROTECTED_FACE_LABELS_ARRAY, pf, source)
    edge_labels = _field_labels(grid, PROTECTED_EDGE_LABELS_ARRAY, pe, source)
    vertex_labels = _field_labels(grid, PROTECTED_VERTEX_LABELS_ARRAY, pv, source)

    def cells(vtk_type: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        # the cells and their labels from the region array (Gmsh's VTK export writes its
        # triangles, lines and points as cells, labelled as in .msh)
        chosen = celltypes == vtk_type
        found = _pick_region(cell_arrays, n_cells, chosen, source)
        tags = np.zeros(int(chosen.sum()), np.int64) if found is None else found
        return conn[offsets[:-1][chosen][:, None] + np.arange(k)], tags

    n = len(points)
    # the field data's own entities first: their labels win
    pf, face_labels = _joined(
        pf, face_labels, *_mesh_cells(tets, *cells(_VTK_TRIANGLE, 3), n, source)
    )
    pe, edge_labels = _joined(pe, edge_labels, *_mesh_cells(tets, *cells(_VTK_LINE, 2), n, source))
    pv, vertex_labels = _joined(
        pv, vertex_labels, *_mesh_vertices(tets, *cells(_VTK_VERTEX, 1), n, source)
    )
    return points, tets, region, pf, pe, face_labels, pv, edge_labels, vertex_labels


def _skip_vtk_mid_nodes(conn: np.ndarray, offsets: np.ndarray, quadratic: np.ndarray) -> None:
    """Note the mid-edge nodes of a grid's ``quadratic`` (mask) cells, whose corners come
    first in VTK's order, for ``load`` to leave out (``quadratic_corners``), those of
    10-node tets with their edges."""
    start, stop = offsets[:-1][quadratic], offsets[1:][quadratic]
    tet = stop - start == 10
    quadratic_corners(conn[start[tet][:, None] + np.arange(10)], 4)
    start, stop = start[~tet], stop[~tet]
    corner_count = np.where(stop - start == 6, 3, 2)
    first = start + corner_count
    lengths = stop - first
    rows = np.repeat(first - np.cumsum(np.r_[0, lengths[:-1]]), lengths) + np.arange(lengths.sum())
    note_mid_nodes(conn[rows])


def _field_labels(grid, name: str, rows, source: str) -> np.ndarray | None:
    """Labels (k,) of the field-data ``rows`` from field-data array ``name``, zeros
    without one, None without rows."""
    if rows is None:
        return None
    if name not in grid.field_data:
        return np.zeros(len(rows), np.int64)
    return _labels(grid.field_data[name], name, source)


def _joined(rows, labels, more, more_labels):
    """(rows, labels) followed by (more, more_labels); None parts are left out."""
    if more is None:
        return rows, labels
    if rows is None:
        return more, more_labels
    return np.concatenate([rows, more]), np.concatenate([labels, more_labels])


def _check_cell_data(mesh: TetMesh, cell_data: dict | None) -> dict:
    out = {}
    for name, values in (cell_data or {}).items():
        if not isinstance(name, str) or not name:
            raise MeshInputError(f"cell_data keys must be non-empty strings, got {name!r}")
        if name == "region":
            raise MeshInputError(
                "cell_data may not hold 'region' (it is the mesh's own region array; "
                "use mesh.replace(region=...))"
            )
        a = np.asarray(values)
        if a.ndim == 0 or len(a) != mesh.n_tets:
            raise MeshInputError(
                f"cell_data[{name!r}] has shape {a.shape}; "
                f"it needs one value per tet ({mesh.n_tets})"
            )
        if a.dtype.kind not in "biuf":
            raise MeshInputError(f"cell_data[{name!r}] holds {a.dtype} values, not numbers")
        out[name] = a
    return out


def mesh_to_grid(mesh: TetMesh, cell_data: dict | None = None, quad=None):
    """A ``pyvista.UnstructuredGrid`` of ``mesh``: tetra cells, a ``region`` cell array,
    the arrays of ``cell_data`` (name -> (m, ...) array), and the protected faces, their
    labels, the protected edges and vertices (when any) as field data
    ``jtet:protected_faces``, ``jtet:protected_face_labels``, ``jtet:protected_edges``,
    ``jtet:protected_vertices``. With ``quad`` (``_quadratic.quadratic_mesh(mesh)``):
    quadratic tetra cells over its nodes, with its point data and node sets (the field
    data name corners, whose ids are the same)."""
    import pyvista as pv

    extra = _check_cell_data(mesh, cell_data)
    m = mesh.n_tets
    tets, points, kind = mesh.tets, mesh.points, _VTK_TETRA
    point_data, node_sets = mesh.point_data, mesh.node_sets
    if quad is not None:
        tets, points, kind = quad.tets, quad.points, _VTK_QUADRATIC_TETRA
        point_data, node_sets = quad.point_data, quad.node_sets
    width = tets.shape[1]
    cells = np.concatenate([np.full((m, 1), width, np.int64), tets], axis=1).ravel()
    celltypes = np.full(m, kind, np.uint8)
    grid = pv.UnstructuredGrid(cells, celltypes, np.array(points, dtype=np.float64))
    grid.cell_data["region"] = np.array(mesh.region, dtype=np.int64)
    for name, a in {**mesh.cell_data, **extra}.items():  # jtet's quality arrays win
        grid.cell_data[name] = np.array(a)
    for name, a in point_data.items():
        grid.point_data[name] = np.array(a)
    if len(mesh.protected_faces):
        grid.field_data[PROTECTED_FACES_ARRAY] = np.array(mesh.protected_faces)
        grid.field_data[PROTECTED_FACE_LABELS_ARRAY] = np.array(mesh.protected_face_labels)
    if len(mesh.protected_edges):
        grid.field_data[PROTECTED_EDGES_ARRAY] = np.array(mesh.protected_edges)
        grid.field_data[PROTECTED_EDGE_LABELS_ARRAY] = np.array(mesh.protected_edge_labels)
    if len(mesh.protected_vertices):
        grid.field_data[PROTECTED_VERTICES_ARRAY] = np.array(mesh.protected_vertices)
        grid.field_data[PROTECTED_VERTEX_LABELS_ARRAY] = np.array(mesh.protected_vertex_labels)
    if len(mesh.label_names):
        names = [[d, lb, name] for (d, lb), name in mesh.label_names.items()]
        grid.field_data[LABEL_NAMES_ARRAY] = _json_bytes(names)
    if mesh.periodic:
        links = [
            [p.dim, *p.tags, None if p.affine is None else list(p.affine), p.pairs.tolist()]
            for p in mesh.periodic
        ]
        grid.field_data[PERIODIC_ARRAY] = _json_bytes(links)
    if node_sets:
        sets = [[ns.name, ns.ids.tolist(), ns.label] for ns in node_sets]
        grid.field_data[NODE_SETS_ARRAY] = _json_bytes(sets)
    if len(mesh.protected_tets):
        grid.field_data[PROTECTED_TETS_ARRAY] = np.array(mesh.protected_tets)
    return grid


# ---------------------------------------------------------------------------------------
# VTK readers and writers (errors captured instead of printed)


@contextlib.contextmanager
def _vtk_capture():
    """Route VTK's error output into a string; yields a function returning the errors."""
    from vtkmodules.vtkCommonCore import vtkLogger, vtkOutputWindow, vtkStringOutputWindow

    window = vtkStringOutputWindow()
    old_window = vtkOutputWindow.GetInstance()
    old_verbosity = vtkLogger.GetCurrentVerbosityCutoff()
    vtkOutputWindow.SetInstance(window)
    # VTK >= 9 also logs every error to stderr through vtkLogger: silence it while we read.
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)

    def errors() -> list[str]:
        text = window.GetOutput()
        if isinstance(text, bytes):
            text = text.decode("utf-8", "replace")
        found = []
        # Blocks look like "ERROR: In file.cxx, line N\nvtkClass (0x...): message". Some
        # readers report a truncated file only as a warning ("Error reading binary data!").
        parts = re.split(r"(ERROR|Warning): In [^\n]*\n", text)
        for kind, block in zip(parts[1::2], parts[2::2], strict=True):
            lines = [ln.strip() for ln in block.splitlines() if ln.strip()]
            if not lines:
                continue
            first = lines[0]
            msg = first.split("): ", 1)[1] if "): " in first else first
            if "InformationKey" in msg:
                # Cached metadata (e.g. an array's L2_NORM_RANGE holding "inf"), not data:
                # let the finiteness check on the points report the real problem.
                continue
            if kind == "ERROR" or "error" in msg.lower():
                found.append(_clean(msg))
        return found

    try:
        yield errors
    finally:
        vtkOutputWindow.SetInstance(old_window)
        vtkLogger.SetStderrVerbosity(old_verbosity)


def _read_vtk_file(path: Path, fmt: str):
    import pyvista as pv

    with _vtk_capture() as errors:
        if fmt == "vtu":
            from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridReader

            reader = vtkXMLUnstructuredGridReader()
        else:
            from vtkmodules.vtkIOLegacy import vtkDataSetReader

            reader = vtkDataSetReader()
            for flag in (
                "ReadAllScalars",
                "ReadAllVectors",
                "ReadAllNormals",
                "ReadAllTensors",
                "ReadAllColorScalars",
                "ReadAllTCoords",
                "ReadAllFields",
            ):
                getattr(reader, flag + "On")()
        reader.SetFileName(str(path))
        reader.Update()
        out = reader.GetOutput()
        errs = errors()
    if errs:
        raise MeshFileError(f"{path}: not a readable {_FORMAT_NAMES[fmt]} file ({errs[0]})")
    if out is None:
        raise MeshFileError(f"{path}: not a readable {_FORMAT_NAMES[fmt]} file (no data)")
    return pv.wrap(out)


def _vtk_arrays_here(path: Path, fmt: str, source: str):
    """(``grid_to_arrays``, {``TetMesh.from_arrays`` keyword: value} of what field data
    holds besides) of the VTK file ``path``, read in this process."""
    try:
        grid = _read_vtk_file(path, fmt)
    except MeshFileError:
        raise
    except Exception as e:
        raise MeshFileError(
            f"{path}: not a readable {_FORMAT_NAMES[fmt]} file ({_reason(e)})"
        ) from None
    return grid_to_arrays(grid, source), grid_extras(grid, source)


def grid_extras(grid, source: str = "pyvista grid") -> dict:
    """{``TetMesh.from_arrays`` keyword: value} of what ``mesh_to_grid`` puts in field
    data besides the protected faces, edges and vertices: label names, periodic links,
    protected tets."""
    return {
        "label_names": grid_label_names(grid, source),
        "periodic": grid_periodic(grid, source),
        "protected_tets": _field_entities(grid, PROTECTED_TETS_ARRAY, 4, source),
        "node_sets": grid_node_sets(grid, source),
        "point_data": grid_point_data(grid, source),
        "cell_data": grid_cell_data(grid, source),
    }


def _carried_array_name(name) -> bool:
    """Whether an array of this name is data a mesh carries: not jtet's own (region
    labels, the quality arrays recomputed for every output), nor VTK's and meshio's
    bookkeeping (``vtkOriginalCellIds``, names with a format's tag: ``gmsh:physical``)."""
    return (
        isinstance(name, str)
        and name not in _KNOWN_ARRAYS
        and not name.startswith(_KNOWN_ARRAY_PREFIXES)
        and ":" not in name
    )


def grid_cell_data(grid, source: str = "pyvista grid") -> dict:
    """The cell arrays of ``grid`` as ``TetMesh.cell_data`` takes them: those of real
    numbers, one value or one row of values per cell, at its tetra cells (in their
    order). Region labels, jtet's quality arrays and VTK's and meshio's bookkeeping are
    left out; other arrays (strings, tensors) are left out with a warning."""
    out, dropped = {}, []
    is_tet = np.asarray(grid.celltypes) == _VTK_TETRA
    for name in grid.cell_data.keys():
        if not _carried_array_name(name):
            continue
        try:
            a = np.asarray(grid.cell_data[name])
        except Exception:
            a = np.zeros(0, object)
        if a.dtype.kind in "biuf" and a.ndim in (1, 2) and len(a) == grid.n_cells:
            out[name] = a[is_tet]
        else:
            dropped.append(name)
    _warn_dropped_arrays([], dropped, source)
    return out


def grid_point_data(grid, source: str = "pyvista grid") -> dict:
    """The point arrays of ``grid`` as ``TetMesh.point_data`` takes them: those of real
    numbers, one value or one row of values per point. VTK's and meshio's bookkeeping
    (``vtkOriginalPointIds``, names with a format's tag ``gmsh:...``) is left out; other
    arrays (strings, tensors) are left out with a warning."""
    out, dropped = {}, []
    for name in grid.point_data.keys():
        if not isinstance(name, str) or name.startswith("vtk") or ":" in name:
            continue
        try:
            a = np.asarray(grid.point_data[name])
        except Exception:
            a = np.zeros(0, object)
        numeric = a.dtype.kind in "biuf"
        if numeric and a.ndim in (1, 2) and len(a) == grid.n_points:
            out[name] = a
        else:
            dropped.append(name)
    _warn_dropped_arrays(dropped, [], source)
    return out


def grid_node_sets(grid, source: str = "pyvista grid") -> list | None:
    """The node sets in the ``NODE_SETS_ARRAY`` field data of ``grid`` (``mesh_to_grid``'s),
    as ``TetMesh.node_sets`` takes them; None without (or, with a warning, unreadable)."""
    sets = _json_field(grid, NODE_SETS_ARRAY, source)
    if sets is None:
        return None
    from ._mesh import _checked_node_sets

    try:
        return list(_checked_node_sets(sets, grid.n_points))
    except (TypeError, ValueError, MeshInputError) as e:
        warnings.warn(
            f"{source}: field data {NODE_SETS_ARRAY!r} is unreadable ({_reason(e)}); ignored",
            stacklevel=3,
        )
        return None


def _json_field(grid, name: str, source: str):
    """The JSON list in the uint8 field data ``name`` of ``grid`` (None without it, or,
    with a warning, when it does not decode)."""
    import json

    if name not in grid.field_data:
        return None
    try:
        raw = np.asarray(grid.field_data[name])
        if raw.dtype != np.uint8:
            raise ValueError(f"{raw.dtype} values, not the bytes of a JSON text")
        value = json.loads(raw.tobytes().decode("utf-8"))
        if not isinstance(value, list):
            raise ValueError("not a JSON list")
    except (ValueError, UnicodeDecodeError, RecursionError) as e:
        warnings.warn(
            f"{source}: field data {name!r} is unreadable ({_reason(e)}); ignored", stacklevel=4
        )
        return None
    return value


def _json_bytes(value) -> np.ndarray:
    import json

    return np.frombuffer(json.dumps(value).encode("utf-8"), np.uint8)


def grid_periodic(grid, source: str = "pyvista grid") -> list | None:
    """The periodic links in the ``PERIODIC_ARRAY`` field data of ``grid``
    (``mesh_to_grid``'s), as ``TetMesh.periodic`` takes them; None without."""
    links = _json_field(grid, PERIODIC_ARRAY, source)
    if links is None:
        return None
    from ._mesh import _checked_periodic

    try:
        return list(
            _checked_periodic(
                [(d, (s, m), a, np.asarray(pairs).reshape(-1, 2)) for d, s, m, a, pairs in links],
                grid.n_points,
            )
        )
    except (TypeError, ValueError, MeshInputError) as e:
        warnings.warn(
            f"{source}: field data {PERIODIC_ARRAY!r} is unreadable ({_reason(e)}); ignored",
            stacklevel=3,
        )
        return None


def grid_label_names(grid, source: str = "pyvista grid") -> dict:
    """(dim, label) -> name from the ``LABEL_NAMES_ARRAY`` field data of ``grid``
    (``mesh_to_grid``'s); a damaged array is ignored with a warning, and so are entries
    that are not [dimension 0..3, integer label, non-empty name]."""
    entries = _json_field(grid, LABEL_NAMES_ARRAY, source)
    if entries is None:
        return {}
    out, bad = {}, 0
    for entry in entries:
        ok = (
            isinstance(entry, list)
            and len(entry) == 3
            and all(type(v) is int for v in entry[:2])
            and 0 <= entry[0] <= 3
            and isinstance(entry[2], str)
            and entry[2] != ""
        )
        if ok:
            out.setdefault((entry[0], entry[1]), entry[2])
        else:
            bad += 1
    if bad:
        warnings.warn(
            f"{source}: {bad} entr(ies) of field data {LABEL_NAMES_ARRAY!r} are not "
            "[dimension, label, name]; ignored",
            stacklevel=3,
        )
    return out


def _limit_child_memory(*paths: Path) -> None:
    """Cap the address space of the reading child at what it has plus 1 GB plus 100x
    the size of the files ``paths`` (compressed tet meshes inflate 1-5x; VTK holds ~2
    copies). Damaged block headers may announce terabytes: VTK then spent 30 s
    allocating before its abort; with the cap it fails at once."""
    import resource

    try:
        with open("/proc/self/status") as f:
            now = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
        size = sum(p.stat().st_size for p in paths if p.is_file())
        budget = now + 2**30 + 100 * size
        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        if hard != resource.RLIM_INFINITY:
            budget = min(budget, hard)
        resource.setrlimit(resource.RLIMIT_AS, (budget, hard))
    except (OSError, ValueError, StopIteration):
        pass  # no /proc or no limits here: read without a cap


def _vtk_file_arrays(path: Path, fmt: str, source: str):
    """``_vtk_arrays_here`` of the VTK file ``path``, read in a forked child process
    (``_forked``; where there is none, in this process).

    VTK's readers take the whole process down on some damaged files: a truncated binary
    legacy file (segmentation fault), appended data whose block headers were damaged
    (``std::bad_alloc``, abort). A fuzz of single byte flips, truncations and deleted
    lines found such a file within 16-190 tries for each format. In a child the crash
    becomes a ``MeshFileError``; the child's warnings are raised again here. The fork
    costs ~10 ms, and the arrays come back through a pipe (~0.1 s for 1M tets).
    """
    from ._forked import call_in_child, can_fork

    if not can_fork():
        return _vtk_arrays_here(path, fmt, source)
    # VTK's modules are imported here, before the fork: each child inherits them instead
    # of importing them again (~0.25 s a read, most of a small file's load), and the
    # process needs them to write its output anyway
    import pyvista  # noqa: F401
    import vtkmodules.vtkIOLegacy  # noqa: F401
    import vtkmodules.vtkIOXML  # noqa: F401

    def read():
        _limit_child_memory(path)
        # the mid-edge nodes the child skips (``load(linear=True)``) come back with the
        # arrays: the child's list is its own copy
        return _vtk_arrays_here(path, fmt, source), _MID_NODES.get()

    def crashed(how: str) -> MeshFileError:
        return MeshFileError(
            f"{path}: not a readable {_FORMAT_NAMES[fmt]} file (VTK's reader {how}: the "
            "file is damaged)"
        )

    arrays, mid_nodes = call_in_child(read, crashed)
    if mid_nodes:
        _MID_NODES.get().extend(mid_nodes)
    return arrays


def _write_vtk_file(grid, path: Path, fmt: str) -> None:
    with _vtk_capture() as errors:
        if fmt == "vtu":
            from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridWriter

            writer = vtkXMLUnstructuredGridWriter()
            writer.SetDataModeToAppended()
            writer.EncodeAppendedDataOff()  # raw binary, no base64
            writer.SetCompressorTypeToZLib()
            # level 1, not VTK's 5: float64 coordinates and qualities hardly compress, so
            # the file is 1 % larger and written 1.6x faster (182k tets with their quality
            # arrays: 0.82 -> 0.51 s, 13.1 -> 13.3 MB)
            writer.SetCompressionLevel(1)
        else:
            from vtkmodules.vtkIOLegacy import vtkUnstructuredGridWriter

            writer = vtkUnstructuredGridWriter()
            writer.SetFileTypeToBinary()
        writer.SetFileName(str(path))
        writer.SetInputData(grid)
        ok = writer.Write()
        errs = errors()
    if errs or ok != 1:
        raise MeshFileError(
            f"{path}: VTK could not write the file ({errs[0] if errs else 'failed'})"
        )


# ---------------------------------------------------------------------------------------
# meshio readers and writers


@contextlib.contextmanager
def _quiet_meshio():
    """meshio prints warnings and errors to stdout/stderr through rich; capture them."""
    buf = io.StringIO()
    with (
        contextlib.redirect_stdout(buf),
        contextlib.redirect_stderr(buf),
        warnings.catch_warnings(),
    ):
        warnings.simplefilter("ignore")
        yield buf


def _meshio_module(fmt: str):
    import meshio

    # The per-format modules, not meshio.read(): on a parse error meshio.read prints the
    # error and calls sys.exit(1).
    return {"gmsh": meshio.gmsh, "medit": meshio.medit, "tetgen": meshio.tetgen}[fmt]


def _block_labels(m, blocks: list[int], name: str, source: str) -> np.ndarray | None:
    """The integer cell array ``name`` of the meshio mesh ``m`` over the cells of
    ``blocks``, concatenated (None when ``m`` has no such array)."""
    if name not in m.cell_data:
        return None
    return np.concatenate([_labels(m.cell_data[name][i], name, source) for i in blocks])


def _block_regions(m, blocks: list[int], source: str) -> np.ndarray | None:
    """Region labels of the cells in ``blocks`` of the meshio mesh ``m``, from the first
    of ``REGION_ARRAYS`` it has (None: no labels)."""
    name = next((a for a in REGION_ARRAYS if a in m.cell_data), None)
    return None if name is None else _block_labels(m, blocks, name, source)


def _gmsh_tags(m, blocks: list[int], source: str):
    """(physical, elementary) tags (each (k,) or None) of the cells in ``blocks`` of a
    Gmsh file read by meshio ``m``; physical 0: in no physical group."""
    return tuple(_block_labels(m, blocks, a, source) for a in ("gmsh:physical", "gmsh:geometrical"))


def _gmsh_regions(m, blocks: list[int], source: str) -> np.ndarray | None:
    """Region labels of the tets in ``blocks`` of a Gmsh file read by meshio ``m``.

    Physical volume tags when every tet has one. When none has (no physical volume, or
    a Gmsh 2.2 file written with ``Mesh.SaveAll``, which tags every element 0), the
    elementary tags: the volume entities, whose shared surfaces must stay. When only
    some have, the others are region 0, with a warning.
    """
    physical, entity = _gmsh_tags(m, blocks, source)
    if physical is not None and physical.all():
        return physical
    if physical is None or not physical.any():
        return entity
    warnings.warn(
        f"{source}: {int((physical == 0).sum())} of {len(physical)} tets are in no physical "
        "group; they get region 0",
        stacklevel=4,
    )
    return physical


def _gmsh_label_names(m, source: str) -> dict:
    """(dim, physical tag) -> name of the Gmsh file meshio read as ``m`` ($PhysicalNames),
    for the dimensions whose labels are physical tags: where no element of a dimension
    has one, its labels are entity tags (``_gmsh_regions``, ``_gmsh_surface_labels``),
    which a physical group's name does not name."""
    names = {}
    for name, value in (m.field_data or {}).items():
        v = np.asarray(value).reshape(-1)
        if len(v) != 2 or not np.issubdtype(v.dtype, np.number) or not str(name):
            continue
        tag, dim = int(v[0]), int(v[1])
        if 0 <= dim <= 3:
            names.setdefault((dim, tag), str(name))
    # a look at each block's physical tags (meshio's Gmsh reader makes integer arrays),
    # not their labels concatenated and checked again
    physical = m.cell_data.get("gmsh:physical") or []
    kinds = {"tetra": 3, "triangle": 2, "line": 1, "vertex": 0}
    physical_dims = {
        kinds[block.type]
        for block, tags in zip(m.cells, physical, strict=False)
        if block.type in kinds and np.any(tags)
    }
    return {key: name for key, name in names.items() if key[0] in physical_dims}


def _gmsh_periodic(m, source: str) -> list | None:
    """The periodic links of the Gmsh file meshio read as ``m`` (``$Periodic``), each
    checked: its vertex ids in range and, with an affine map, each slave vertex the
    image of its master (meshio takes node tag - 1 as the vertex id, wrong for files whose
    node tags have gaps). A link that fails is dropped with a warning."""
    links = getattr(m, "gmsh_periodic", None)
    if not links:
        return None
    points = np.asarray(m.points, np.float64)
    n = len(points)
    scale = float(np.ptp(points, axis=0).max()) if n else 1.0
    out, bad = [], 0
    for link in links:
        try:
            dim, (slave, master), affine, pairs = link
            pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
            ok = not len(pairs) or (pairs.min() >= 0 and pairs.max() < n)
            if ok and affine is not None and len(pairs):
                A = np.asarray(affine, np.float64).reshape(4, 4)
                image = points[pairs[:, 1]] @ A[:3, :3].T + A[:3, 3]
                ok = bool(np.abs(image - points[pairs[:, 0]]).max() <= 1e-6 * scale)
        except (TypeError, ValueError):
            ok = False
        if ok:
            out.append((int(dim), (int(slave), int(master)), affine, pairs))
        else:
            bad += 1
    if bad:
        warnings.warn(
            f"{source}: {bad} periodic link(s) whose vertex pairs do not match the mesh; "
            "ignored (their surfaces may lose their matching triangulations)",
            stacklevel=4,
        )
    return out or None


def _gmsh_surface_labels(m, blocks: list[int], source: str) -> np.ndarray | None:
    """Labels of the triangles in ``blocks`` of a Gmsh file: their physical surface tags
    (0 for a triangle in none) when any has one, else their surface entities."""
    physical, entity = _gmsh_tags(m, blocks, source)
    return physical if physical is not None and physical.any() else entity


def _mesh_cells(tets: np.ndarray, cells: np.ndarray, labels, n: int, source: str):
    """The triangles (k, 3) or lines (k, 2) ``cells`` of a file that are faces / edges of
    its tets ``tets`` (m, 4), as sorted rows with their ``labels`` (k,): ``(rows,
    labels)``, or ``(None, None)`` when there are none. A cell listed twice keeps its
    first label.

    They become protected faces / edges. A labelled patch of the boundary (a Gmsh
    physical surface, a Medit reference, a TetGen facet marker) keeps its border and is
    written back with its label; a surface between two tets (embedded in a volume, or
    between two volumes of one region) stays in place, where as ordinary faces flips
    would cut through it and smoothing would move its vertices off it. Gmsh writes its
    model curves as lines (all of them without physical groups, else those of physical
    curves): a curve embedded in a volume keeps its edges, as nodes stay on their model
    entities in Gmsh's own optimizer. Cells that are no face / edge of a tet are ignored
    with a warning.
    """
    from ._topology import TET_EDGES, TET_FACES, row_keys

    j = cells.shape[1]
    local, noun, part = (TET_FACES, "triangle", "faces") if j == 3 else (TET_EDGES, "line", "edges")
    if not len(cells) or not len(tets) or tets.min() < 0 or tets.max() >= n:
        return None, None  # from_arrays reports bad tets
    cells, labels = _on_features(tets, cells, np.asarray(labels, np.int64), n)
    inside = (cells.min(axis=1) >= 0) & (cells.max(axis=1) < n)
    rows, first = np.unique(np.sort(cells[inside], axis=1), axis=0, return_index=True)
    labels = np.asarray(labels, np.int64)[inside][first]
    # only tets with j marked vertices can have such a face or edge (a few percent of the
    # tets for boundary triangles: 0.7 -> 0.07 s for a 983k-tet cube)
    marked = np.zeros(n, bool)
    marked[rows.reshape(-1)] = True
    near = tets[marked[tets].sum(axis=1) >= j]
    parts = np.sort(near[:, local].reshape(-1, j), axis=1)
    parts = parts[marked[parts].all(axis=1)]
    keys = row_keys(np.concatenate([parts, rows]), n)  # one call: keys that compare
    found = np.isin(keys[len(parts) :], keys[: len(parts)])
    strays = int((~found).sum()) + int((~inside).sum())
    if strays:
        warnings.warn(
            f"{source}: {strays} {noun}(s) of the file are not {part} of its tets; ignored",
            stacklevel=4,
        )
    if not found.any():
        return None, None
    return rows[found], labels[found]


def _mesh_vertices(tets: np.ndarray, vertices, labels, n: int, source: str):
    """The vertex cells ``vertices`` (j,) of a file that are vertices of its tets, sorted
    and distinct, with their ``labels`` (j,): ``(ids, labels)``, ``(None, None)`` for
    none. A vertex listed twice keeps its first label.

    They become protected vertices: Gmsh writes its model points as such cells, so a
    point embedded in a volume stays where it is. The others are ignored with a warning.
    """
    vertices = np.asarray(vertices, np.int64).reshape(-1)
    if not len(vertices) or not len(tets) or tets.min() < 0 or tets.max() >= n:
        return None, None  # from_arrays reports bad tets
    in_tets = np.zeros(n, bool)
    in_tets[tets.reshape(-1)] = True
    ok = (vertices >= 0) & (vertices < n)
    ok[ok] = in_tets[vertices[ok]]
    if not ok.all():
        warnings.warn(
            f"{source}: {int((~ok).sum())} vertex cell(s) of the file are not vertices "
            "of its tets; ignored",
            stacklevel=4,
        )
    if not ok.any():
        return None, None
    ids, first = np.unique(vertices[ok], return_index=True)
    return ids, np.asarray(labels, np.int64)[ok][first]


def _meshio_to_arrays(m, source: str, fmt: str = "", triangles=None, required=None):
    """Like ``grid_to_arrays`` for a ``meshio.Mesh``: tets of every tetra block, region,
    as labelled protected faces the triangles of its triangle blocks and of
    ``triangles`` ((k, 3) ids, (k,) labels: a TetGen ``.face`` file) that are faces of
    the tets, as protected edges and vertices its line and vertex cells that are edges
    and vertices of the tets (``_mesh_cells``, ``_mesh_vertices``).

    ``required`` (a Medit file's, ``_medit_required``): {"RequiredVertices",
    "RequiredTriangles", "RequiredEdges": 0-based ids (k,) (vertex ids; ids in its
    triangle / edge sections), or None}. MMG never changes what these name;
    jtet keeps a required triangle exactly by protecting its edges and vertices too (a
    protected face alone may be flipped within a flat patch), a required edge by
    protecting its vertices too (with ``boundary="slide"`` they could slide)."""
    # a Gmsh file's $NodeData / $ElementData views, a Medit file's solution: not carried
    _warn_dropped_arrays(list(m.point_data), list(m.cell_data), source)
    if reading_linear():  # quadratic blocks as their corners (``load(linear=True)``)
        for block in m.cells:
            if block.type in _MESHIO_QUADRATIC:
                block.type, k = _MESHIO_QUADRATIC[block.type]
                block.data = quadratic_corners(block.data, k)
    keep_blocks, bad = [], {}
    for i, block in enumerate(m.cells):
        dim = getattr(block, "dim", 3)
        if block.type == "tetra":
            keep_blocks.append(i)
        elif dim == 3:
            bad[block.type] = bad.get(block.type, 0) + len(block.data)
    if bad:
        raise MeshInputError(
            _non_tet_message(
                source,
                list(bad),
                list(bad.values()),
                any(t.startswith("tetra") for t in bad),
            )
        )
    if not keep_blocks:
        only = ", ".join(f"{b.type} x {len(b.data)}" for b in m.cells) or "no cells"
        hint = ""
        if fmt == "gmsh":
            hint = (
                "; once physical groups are defined, Gmsh writes only their elements: add "
                "a physical volume, or set Mesh.SaveAll = 1"
            )
        raise MeshInputError(f"{source}: the mesh has no tetrahedra (only {only}){hint}")
    tets = np.concatenate(
        [np.asarray(m.cells[i].data, np.int64).reshape(-1, 4) for i in keep_blocks]
    )
    region = (_gmsh_regions if fmt == "gmsh" else _block_regions)(m, keep_blocks, source)
    if region is not None and len(region) != len(tets):
        raise MeshInputError(f"{source}: the region labels do not match the tets")
    points = np.asarray(m.points, dtype=np.float64)
    if points.ndim == 2 and points.shape[1] == 2:
        raise MeshInputError(f"{source}: the points are 2-D; jtet needs a 3-D tet mesh")

    def cells(kind: str, k: int) -> tuple[np.ndarray, np.ndarray]:
        # the cells of every block of this type and their labels (physical / entity tags,
        # references)
        chosen = [i for i, b in enumerate(m.cells) if b.type == kind]
        rows = [np.asarray(m.cells[i].data, np.int64).reshape(-1, k) for i in chosen]
        rows = np.concatenate([np.zeros((0, k), np.int64), *rows])
        found = None
        if chosen:
            found = (_gmsh_surface_labels if fmt == "gmsh" else _block_regions)(m, chosen, source)
        return rows, np.zeros(len(rows), np.int64) if found is None else found

    n = len(points)
    tri, tri_labels = cells("triangle", 3)
    if triangles is not None:
        tri = np.concatenate([tri, triangles[0]])
        tri_labels = np.concatenate([tri_labels, triangles[1]])
    faces, labels = _mesh_cells(tets, tri, tri_labels, n, source)
    lines, line_labels = cells("line", 2)
    pins, pin_labels = cells("vertex", 1)
    pins = pins.reshape(-1)
    if required is not None:  # Medit's Required* sections: no labels of their own
        sides, side_labels, corners = _required_cells(tri, tri_labels, lines, required, source)
        lines = np.concatenate([lines, sides])
        line_labels = np.concatenate([line_labels, side_labels])
        pins = np.concatenate([pins, corners])
        pin_labels = np.concatenate([pin_labels, np.zeros(len(corners), np.int64)])
    edges, edge_labels = _mesh_cells(tets, lines, line_labels, n, source)
    pinned, pinned_labels = _mesh_vertices(tets, pins, pin_labels, n, source)
    return points, tets, region, faces, edges, labels, pinned, edge_labels, pinned_labels


def _on_features(tets: np.ndarray, cells: np.ndarray, labels: np.ndarray, n: int):
    """(cells, labels): the triangles (k, 3) or lines (k, 2) of a file that lie on its
    surfaces / curves, which jtet protects. That is all of them, unless the file lists
    every face / edge of the mesh (``tetgen -f``, a dolfinx meshtags over all facets, an
    export of all faces): its inner faces (of two tets) or edges (on no boundary face)
    labelled 0, the label of a cell on no surface or curve (TetGen's marker, Gmsh's
    "no physical group"), are then left out. Protected, they would keep every flip from
    running."""
    from ._topology import TET_EDGES, TET_FACES, row_keys, sorted_lookup

    m, j = len(tets), cells.shape[1]
    # a mesh has at least 2m faces ((4m + boundary faces) / 2) and more than m edges: a
    # shorter list holds surfaces / curves only, as files usually do. Bad ids:
    # _mesh_cells warns about them
    if len(cells) < (2 * m if j == 3 else m) or not m or min(tets.min(), cells.min()) < 0:
        return cells, labels
    if max(tets.max(), cells.max()) >= n:
        return cells, labels
    sides = np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1)
    if j == 3:
        keys = row_keys(np.concatenate([sides, np.sort(cells, axis=1)]), n)  # one key space
        mesh_keys, tets_per_face = np.unique(keys[: 4 * m], return_counts=True)
        at = sorted_lookup(mesh_keys, keys[4 * m :])
        inner = tets_per_face[at] == 2
    else:
        _, first, tets_per_face = np.unique(
            row_keys(sides, n), return_index=True, return_counts=True
        )
        outer = sides[first[tets_per_face == 1]][:, [[0, 1], [1, 2], [0, 2]]].reshape(-1, 2)
        edges = np.sort(tets[:, TET_EDGES].reshape(-1, 2), axis=1)
        keys = row_keys(np.concatenate([edges, outer, np.sort(cells, axis=1)]), n)
        e, o = len(edges), len(outer)
        mesh_keys = np.unique(keys[:e])
        at = sorted_lookup(mesh_keys, keys[e + o :])
        inner = ~np.isin(keys[e + o :], keys[e : e + o])
    if (at < 0).any() or len(np.unique(at)) != len(mesh_keys):
        return cells, labels  # not every face / edge of the mesh
    keep = ~inner | (labels != 0)
    return cells[keep], labels[keep]


def _required_cells(tri, tri_labels, lines, required: dict, source: str):
    """(edges (k, 2), their labels (k,), vertices (j,)) that keep a Medit file's required
    triangles and edges exactly (``_meshio_to_arrays``): the edges of each required
    triangle, labelled with its reference; the vertices of those and of the required
    edges; the required vertices. ``MeshInputError`` for an id past its section."""
    none = np.zeros(0, np.int64)
    t_ids, e_ids, v_ids = (
        none if required.get(k) is None else required[k]
        for k in ("RequiredTriangles", "RequiredEdges", "RequiredVertices")
    )
    for section, noun, ids, rows in (
        ("RequiredTriangles", "triangle", t_ids, tri),
        ("RequiredEdges", "edge", e_ids, lines),
    ):
        if len(ids) and ids.max() >= len(rows):
            raise MeshInputError(
                f"{source}: {section} lists {noun} {int(ids.max()) + 1} of {len(rows)}"
            )
    sides = tri[t_ids][:, [[0, 1], [1, 2], [0, 2]]].reshape(-1, 2)
    side_labels = np.repeat(tri_labels[t_ids], 3)
    vertices = np.concatenate([sides.reshape(-1), lines[e_ids].reshape(-1), v_ids])
    return sides, side_labels, vertices


def _tetgen_faces(node: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(k, 3) 0-based vertex ids of the triangles in the TetGen ``.face`` file next to
    ``node`` and their (k,) boundary markers (0 without): TetGen lists the boundary and
    the constrained internal facets of its mesh there. None when there is no such file;
    an unreadable one is ignored with a warning (the mesh is in ``.node`` / ``.ele``)."""
    from ._tetgen import _node_count_and_base, _numbers

    face = node.with_suffix(".face")
    if not face.is_file():
        return None
    try:
        _, base = _node_count_and_base(node)
        # one C-level parse of every number (a million faces: 0.14 s; a Python loop over
        # the lines took 1.5 s); a word among them: MeshFileError, an OSError
        values = _numbers(face)
        if values.dtype.kind != "i":
            raise ValueError("a number that is no integer")
        count, with_markers = int(values[0]), int(values[1]) == 1
        # a row: id, 3 nodes, [3 edge nodes (tetgen -o2)], [marker], [2 adjacent tets
        # (tetgen -nn)]: 4 or 6 columns, 7 or 9 with the edge nodes, one more with markers
        cols = (len(values) - 2) // count if count > 0 else 4 + with_markers
        if count < 0 or cols < 4 + with_markers or len(values) - 2 != cols * count:
            raise ValueError(f"{count} faces announced, {len(values) - 2} numbers read")
        table = values[2:].reshape(count, cols)
        if cols - with_markers in (7, 9):  # the edge nodes: the tets' (load drops them)
            table = np.delete(table, [4, 5, 6], axis=1)
    except (OSError, ValueError, IndexError, StopIteration) as e:
        warnings.warn(
            f"{face}: not a readable TetGen face file ({_reason(e)}); ignored", stacklevel=3
        )
        return None
    markers = table[:, 4] if with_markers else np.zeros(count, np.int64)
    return table[:, 1:4] - base, markers


def _tetgen_point_data(m, node: Path) -> dict:
    """``TetMesh.point_data`` of the point attributes meshio read from the TetGen
    ``.node`` file (``tetgen:attr1``, ...): named as the file's names comment says
    (meshio's and jtet's files; columns ``name[i]`` joined into an (n, k) array), else
    ``attr1``, ``attr2``, ..."""
    from ._point_data import joined_columns

    attrs = []
    while f"tetgen:attr{len(attrs) + 1}" in m.point_data:
        attrs.append(np.asarray(m.point_data[f"tetgen:attr{len(attrs) + 1}"], np.float64))
    if not attrs:
        return {}
    names = [f"attr{k + 1}" for k in range(len(attrs))]
    with open(node, errors="replace") as f:
        for line in itertools.islice(f, 8):
            if line.startswith(NAMES_COMMENT):
                given = [n.strip() for n in line[len(NAMES_COMMENT) :].split(",")]
                if len(given) >= len(attrs) and all(given[: len(attrs)]):
                    names = given[: len(attrs)]
                break
    return joined_columns(dict(zip(names, attrs, strict=True)))


def _meshio_mesh(mesh: TetMesh, fmt: str, quad=None):
    """A ``meshio.Mesh`` of ``mesh`` for a Gmsh or Medit file; with ``quad``
    (``_quadratic.quadratic_mesh(mesh)``, Gmsh only) its cells are quadratic (meshio
    puts a tet's nodes in Gmsh's order)."""
    import meshio

    region = np.array(mesh.region, dtype=np.int64)
    blocks = [meshio.CellBlock("tetra", np.array(mesh.tets, dtype=np.int64))]
    if quad is not None:
        blocks = [meshio.CellBlock("tetra10", quad.tets)]
    data = {name: [region] for name in _TAG_ARRAYS[fmt]}
    extra = _lower_blocks(mesh, fmt)
    for kind, cells, tags in extra:
        if quad is not None and kind in _QUADRATIC_BLOCK:
            kind, cells = _QUADRATIC_BLOCK[kind], quad.cells(cells)
        blocks.append(meshio.CellBlock(kind, np.array(cells, np.int64)))
        for arrays in data.values():
            arrays.append(np.array(tags, np.int64))
    field_data = {}
    if fmt == "gmsh":  # $PhysicalNames: meshio keys them by name (a name names one group)
        for (dim, label), name in mesh.label_names.items():
            field_data.setdefault(name, np.array([label, dim]))
    periodic = None
    if fmt == "gmsh" and mesh.periodic:
        periodic = [
            [p.dim, p.tags, None if p.affine is None else np.array(p.affine), np.array(p.pairs)]
            for p in mesh.periodic
        ]
    return meshio.Mesh(
        np.array(mesh.points if quad is None else quad.points, dtype=np.float64),
        blocks,
        cell_data=data,
        field_data=field_data,
        gmsh_periodic=periodic,
    )


def _append_gmsh_views(
    mesh: TetMesh, path: Path, cell_data: dict, tets_only: bool, point_data: dict | None = None
) -> None:
    """Append the point data and cell data of ``mesh`` and, for a file of tets only
    (``tets_only``: no protected entities written as elements), the arrays of
    ``cell_data`` (which win) to the Gmsh file ``path`` as views
    (``_gmsh_views.write_views``). Element data beside other element blocks make the
    file unreadable to meshio 5.3, which splits them at the wrong places (``save``
    warns)."""
    from ._gmsh_views import write_views

    cells = dict(mesh.cell_data) | (cell_data if tets_only else {})
    point_data = dict(mesh.point_data if point_data is None else point_data)
    if point_data or cells:
        with open(path, "ab") as fh:
            write_views(fh, point_data, cells)


#: the cell arrays meshio writes as a Gmsh / Medit file's element tags
_TAG_ARRAYS = {"gmsh": ("gmsh:physical", "gmsh:geometrical"), "medit": ("medit:ref",)}


def _lower_blocks(mesh: TetMesh, fmt: str) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(meshio cell type, cells, tags) of the protected entities a Gmsh / Medit file
    stores as elements: the faces as triangles tagged with their labels (Gmsh physical
    surfaces, Medit references: what solvers read), the edges as lines and, in Gmsh
    files, the vertices as point elements, each tagged with its label (Medit files get
    ``RequiredVertices``, which hold no labels: ``_append_required``)."""
    out = []
    if len(mesh.protected_faces):
        out.append(("triangle", mesh.protected_faces, mesh.protected_face_labels))
    if len(mesh.protected_edges):
        out.append(("line", mesh.protected_edges, mesh.protected_edge_labels))
    if fmt == "gmsh" and len(mesh.protected_vertices):
        pv = mesh.protected_vertices
        out.append(("vertex", pv[:, None], mesh.protected_vertex_labels))
    return out


# ---------------------------------------------------------------------------------------
# load / save


def _clean(text: str, limit: int = 160) -> str:
    """One printable line: binary garbage from a corrupt file must not reach the terminal."""
    text = "".join(c if c.isascii() and c.isprintable() else "?" for c in " ".join(text.split()))
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _reason(e: BaseException, captured: str = "") -> str:
    msg = str(e).strip().splitlines()
    text = msg[0] if msg else ""
    if not text and captured.strip():
        text = captured.strip().splitlines()[-1].strip()
    text = _clean(text)
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _tetgen_header(path: Path) -> str:
    """The first line of a TetGen file that is no comment; ``MeshFileError`` when there
    is none (meshio's reader would wait for one forever)."""
    try:
        with open(path, errors="replace") as f:
            header = next((line for line in f if line.strip() and line.lstrip()[0] != "#"), "")
    except OSError as e:
        raise MeshFileError(f"{path}: cannot read ({_reason(e)})") from None
    if not header:
        raise MeshFileError(f"{path}: not a readable TetGen file (no header line, only comments)")
    return header


def _check_tetgen_elements(ele: Path) -> bool:
    """Whether the TetGen ``.ele`` file holds 10-node tets (``tetgen -o2``) that
    ``load(..., linear=True)`` reads (``_tetgen``). Raise ``MeshInputError`` when
    its header gives other elements than 4-node tets or, without ``linear``, 10-node
    ones (meshio refuses both without a reason), and ``MeshFileError`` when either file
    has no header."""
    _tetgen_header(ele.with_suffix(".node"))
    header = _tetgen_header(ele)
    fields = header.split("#")[0].split()  # elements, nodes per element, attributes
    if len(fields) < 2 or not fields[1].isdigit() or int(fields[1]) == 4:
        # meshio reads it, or fails with its own reason; but for an attribute on the
        # last line that is no integer, which it would read wrong (the others make it
        # fail: ``load`` then looks at every line)
        last = _last_line(ele)
        if last.strip() != header.strip():
            _check_tetgen_attributes(ele, last)
        return False
    if int(fields[1]) == 10:
        if reading_linear():
            return True
        count = int(fields[0]) if fields[0].isdigit() else 0
        raise MeshInputError(_non_tet_message(str(ele), ["10-node tetrahedron"], [count], True))
    raise MeshInputError(f"{ele}: {fields[1]} nodes per element; jtet reads 4-node tetrahedra")


# An element line of a TetGen ``.ele`` file (a number and four node ids, then integer
# attributes) with an attribute written as a decimal number that is no integer literal
# ("1.5", "2.0", "3e2"): group 1 is the element's number, group 2 that attribute.
_TETGEN_DECIMAL_ATTRIBUTE = re.compile(
    r"^[ \t]*(-?\d+)(?:[ \t]+-?\d+){4}(?:[ \t]+-?\d+)*[ \t]+"
    r"([-+]?(?:(?:\d+\.\d*|\.\d+)(?:[eE][-+]?\d+)?|\d+[eE][-+]?\d+))(?=[ \t#]|$)",
    re.MULTILINE,
)


def _check_tetgen_attributes(ele: Path, text: str | None = None) -> None:
    """Raise ``MeshInputError`` when an element line of the TetGen ``.ele`` file (or of
    ``text``, some of its lines) holds an attribute that is no integer (a region
    attribute of 1.5 in the ``.poly`` file): meshio reads element attributes as
    integers, and fails without saying so or, on the last line, reads 1.5 as 1; jtet's
    region labels are integers. Lines that are no element lines (a damaged file) are
    left to meshio's reason."""
    if text is None:
        try:
            text = ele.read_text(errors="replace")
        except OSError:
            return
    bad = _TETGEN_DECIMAL_ATTRIBUTE.search(text)
    if bad:
        raise MeshInputError(
            f"{ele}: element {bad.group(1)} has the attribute {bad.group(2)!r}, not written "
            "as an integer; jtet reads TetGen's element attributes as integer region "
            "labels (give the regions integer attributes in the .poly file)"
        )


def _last_line(path: Path) -> str:
    """The last line of ``path`` that holds more than a comment ("" without one in its
    last 64 kB)."""
    with open(path, "rb") as f:
        f.seek(0, os.SEEK_END)
        f.seek(max(0, f.tell() - 65536))
        tail = f.read().decode(errors="replace")
    return next((ln for ln in reversed(tail.splitlines()) if ln.split("#")[0].split()), "")


# ``load(path, linear=True)``: the readers read quadratic cells (10-node tets, 6-node
# triangles, 3-node lines) as their corners and put the ids of the mid-edge nodes they
# skip here; None (the default): they refuse quadratic tets
_MID_NODES: contextvars.ContextVar[list | None] = contextvars.ContextVar(
    "jtet_mid_nodes", default=None
)


def reading_linear() -> bool:
    """Whether the file being loaded is read with quadratic cells as linear ones."""
    return _MID_NODES.get() is not None


def quadratic_corners(cells: np.ndarray, k: int, *, carry: bool = True) -> np.ndarray:
    """The first ``k`` columns of quadratic ``cells`` (every format lists a quadratic
    cell's corners first, in the order of its linear cell), noting the other columns as
    mid-edge nodes that ``load`` drops unless a cell uses them. The mid-edge nodes of
    10-node tets in VTK's order (``_quadratic.MID_EDGES``: VTK, meshio, Abaqus, Exodus,
    MED) are noted with their edges (``carry``; False: a format of another order), so
    the curved ones become ``TetMesh.curved_edges``."""
    from ._quadratic import MID_EDGES

    cells = np.asarray(cells, np.int64)
    ends = None
    if carry and k == 4 and cells.shape[1] == 10:
        ends = cells[:, MID_EDGES[4]]
    note_mid_nodes(cells[:, k:], ends)
    return cells[:, :k]


def note_mid_nodes(ids: np.ndarray, ends: np.ndarray | None = None) -> None:
    """Note vertex ids of mid-edge nodes that a reader skipped, for ``load`` to leave out;
    ``ends``: the two corners of each one's edge (ids' shape + (2,)), when known."""
    ids = np.asarray(ids, np.int64).reshape(-1)
    if ends is not None:
        ends = np.asarray(ends, np.int64).reshape(-1, 2)
    _MID_NODES.get().append((ids, ends))


def noted_mid_nodes(found: list | None = None) -> np.ndarray:
    """The sorted distinct ids of the mid-edge nodes in ``found`` (default: those noted
    so far in this ``load``, ``note_mid_nodes``); empty when the file is not read as
    linear."""
    found = (_MID_NODES.get() or []) if found is None else found
    return np.unique(np.concatenate([np.zeros(0, np.int64), *(ids for ids, _ in found)]))


def _curved_edges(points: np.ndarray, found: list):
    """(edges (k, 2), points (k, 3)) of the mid-edge nodes in ``found`` (see
    ``note_mid_nodes``) that lie off their edge's midpoint by more than a millionth of
    the edge's length (more than the rounding of a midpoint written as text with a few
    digits: those are written back as midpoints); a node listed by several cells comes
    once, with the edge its first listing gives."""
    known = [(ids, ends) for ids, ends in found if ends is not None]
    if not known:
        return np.zeros((0, 2), np.int64), np.zeros((0, 3))
    ids = np.concatenate([i for i, _ in known])
    ends = np.concatenate([e for _, e in known])
    inside = (ids >= 0) & (ids < len(points)) & (ends >= 0).all(axis=1)
    inside &= (ends < len(points)).all(axis=1)
    ids, ends = ids[inside], ends[inside]
    # the first listing of each node (a scatter, reversed so the first write wins: each
    # edge node is listed by every tet around its edge, ~6 times; 4M listings 1.7 ->
    # 0.5 s against computing every one)
    first = np.full(len(points), -1, np.int64)
    first[ids[::-1]] = np.arange(len(ids) - 1, -1, -1)
    first = first[first >= 0]
    ids, ends = ids[first], np.sort(ends[first], axis=1)
    from ._quadratic import CURVED_TOL

    a, b = points[ends[:, 0]], points[ends[:, 1]]
    off = np.linalg.norm(points[ids] - 0.5 * (a + b), axis=1)
    bent = off > CURVED_TOL * np.linalg.norm(b - a, axis=1)
    return ends[bent], points[ids[bent]]


def _without_points(mesh: TetMesh, drop: np.ndarray) -> TetMesh:
    """``mesh`` without the points ``drop`` (ids no tet or protected entity uses), its ids
    renumbered; node sets, periodic links and point data follow."""
    keep = np.ones(mesh.n_points, bool)
    keep[drop] = False
    new = np.cumsum(keep) - 1

    def ids(a):
        return new[np.asarray(a, np.int64)]

    periodic = [
        (link.dim, link.tags, link.affine, ids(link.pairs[keep[link.pairs].all(axis=1)]))
        for link in mesh.periodic
        if keep[link.pairs].all(axis=1).any()
    ]
    return TetMesh.from_arrays(
        mesh.points[keep],
        ids(mesh.tets),
        mesh.region,
        ids(mesh.protected_faces),
        ids(mesh.protected_edges),
        mesh.protected_face_labels,
        ids(mesh.protected_vertices),
        mesh.protected_edge_labels,
        mesh.protected_vertex_labels,
        label_names=dict(mesh.label_names),
        periodic=periodic,
        protected_tets=ids(mesh.protected_tets),
        node_sets=[(ns.name, ids(ns.ids[keep[ns.ids]]), ns.label) for ns in mesh.node_sets],
        point_data={k: v[keep] for k, v in mesh.point_data.items()},
        cell_data=dict(mesh.cell_data),
        curved_edges=(ids(mesh.curved_edges.edges), mesh.curved_edges.points),
    )


def _drop_mid_nodes(mesh: TetMesh, found: list, source: str) -> TetMesh:
    """``mesh`` read with quadratic cells as linear ones, without the mid-edge nodes in
    ``found`` (``note_mid_nodes``) that no cell or protected entity uses (with a
    warning), its curved edges (``TetMesh.curved_edges``) those of the nodes off their
    edges' midpoints; periodic links keep their pairs of corners."""
    mid = noted_mid_nodes(found)
    if not len(mid):
        return mesh
    used = np.zeros(mesh.n_points, bool)
    for a in (mesh.tets, mesh.protected_faces, mesh.protected_edges, mesh.protected_vertices):
        used[np.asarray(a, np.int64).reshape(-1)] = True
    drop = mid[(mid >= 0) & (mid < mesh.n_points)]
    drop = drop[~used[drop]]
    mesh = mesh.replace(curved_edges=_curved_edges(mesh.points, found))
    n_curved = len(mesh.curved_edges.edges)
    warnings.warn(
        f"{source}: quadratic cells read as linear ones (their corners); {len(drop)} "
        "mid-edge node(s) left out"
        + (
            f", the {n_curved} off their edges' midpoints (a curved boundary) kept "
            "for a quadratic output (jtet improve --quadratic)"
            if n_curved
            else ""
        )
        + ". jtet improves linear tets: write the result with --quadratic (save(..., "
        "quadratic=True)) to get 10-node tets back",
        stacklevel=3,
    )
    return _without_points(mesh, drop) if len(drop) else mesh


def load(path: str | os.PathLike, *, linear: bool = False) -> TetMesh:
    """Read a tetrahedral mesh file.

    Formats by extension: ``.vtu``, ``.vtk`` (VTK), ``.msh`` (Gmsh 2.2 / 4.1; physical
    tags -> region), ``.mesh`` / ``.meshb`` (Medit; references -> region), ``.node`` /
    ``.ele`` (TetGen, both files next to each other; first element attribute -> region;
    the ``.face`` file, if there is one, with its facet markers), ``.xdmf`` (dolfinx's,
    meshio's, VTK's and jtet's; cell tags or a region attribute -> region, facet tags ->
    labelled protected faces), ``.inp`` (flat Abaqus / CalculiX input files; element
    sets -> regions, element-face surfaces -> labelled protected faces), ``.vol`` /
    ``.vol.gz`` (Netgen / NGSolve; materials -> regions, surface elements -> labelled
    protected faces, ``_netgen``), ``.med`` (MED: Salome, code_aster; groups of tets ->
    regions, of triangles, segments and point cells -> labelled protected faces, edges and
    vertices, node groups -> node sets, ``_med``). Triangles that are faces of the tets become protected
    faces, labelled by their physical tags / references / markers; lines and points (Medit: ``Edges``, ``RequiredVertices``) that are edges and
    vertices of the tets become protected edges and vertices. Point arrays of numbers
    (``.vtu``, ``.vtk``; ``.xdmf`` node attributes; TetGen point attributes; the Medit
    ``.sol`` file beside a ``.mesh`` / ``.meshb``; Exodus nodal variables and Gmsh
    ``$NodeData`` views at the last time step) become ``TetMesh.point_data``; cell
    arrays of numbers (``.vtu``, ``.vtk``; ``.xdmf`` cell attributes; Exodus element
    variables and Gmsh ``$ElementData`` views over every tet at the last time step) become
    ``TetMesh.cell_data``, but for region labels and jtet's own quality arrays. A
    globally reversed orientation is fixed with a warning (see ``TetMesh.from_arrays``).

    ``linear=True`` reads quadratic cells (10-node tets, 6-node triangles, 3-node lines;
    ``jtet improve --linear``) as their corners, and leaves out the mid-edge nodes no
    other cell uses (node sets and point data follow), with a warning: jtet improves
    linear tets. The nodes of 10-node tets off their edges' midpoints (a curved
    boundary) are kept as ``TetMesh.curved_edges``
    for a quadratic output (``save(..., quadratic=True)``). Without it such a file is
    refused.

    Raises:
        MeshFileError: the file is missing, a directory, of unknown extension, or unreadable.
        MeshInputError: the file was read but does not hold a valid pure tet mesh.
    """
    token = _MID_NODES.set([] if linear else None)
    try:
        mesh = _load(path)
        found = _MID_NODES.get()
    finally:
        _MID_NODES.reset(token)
    return _drop_mid_nodes(mesh, found, str(path)) if found else mesh


def _load(path) -> TetMesh:
    """``load`` without the mid-edge nodes' removal."""
    p = Path(path)
    if not p.exists():
        raise MeshFileError(f"{p}: no such file")
    if p.is_dir():
        raise MeshFileError(f"{p}: is a directory, not a mesh file")
    ext = p.suffix.lower()
    if p.name.lower().endswith(".vol.gz"):  # NGSolve's gzipped meshes
        ext = ".vol"
    fmt = _READ_FORMATS.get(ext)
    if fmt is None:
        from ._tetrahedralize import SURFACE_EXTENSIONS

        hint = ""
        if ext in SURFACE_EXTENSIONS:
            hint = " (a surface: mesh the volume it bounds with jtet tetrahedralize)"
        elif ext in (".h5", ".hdf5"):
            hint = " (HDF5 data of an XDMF mesh: read the .xdmf file that names it)"
        raise MeshFileError(
            f"{p}: unknown mesh file extension {ext or '(none)'!r}; jtet reads "
            f"{_KNOWN_EXTENSIONS}{hint}"
        )
    if p.stat().st_size == 0:
        raise MeshFileError(f"{p}: the file is empty")
    quadratic_tetgen = False
    if fmt == "tetgen":
        other = p.with_suffix(".ele" if ext == ".node" else ".node")
        if not other.is_file():
            raise MeshFileError(f"{p}: the TetGen companion file {other.name} is missing")
        quadratic_tetgen = _check_tetgen_elements(p.with_suffix(".ele"))
    source = str(p)
    extras = {}
    if fmt in ("vtu", "vtk"):
        arrays, extras = _vtk_file_arrays(p, fmt, source)
    elif fmt == "abaqus":
        arrays, extras = _abaqus_arrays(p, source)
    elif fmt == "netgen":
        arrays, extras = _netgen_arrays(p, source)
    elif fmt == "exodus":
        arrays, extras = _exodus_arrays(p, source)
    elif fmt == "med":
        arrays, extras = _med_arrays(p, source)
    elif fmt == "xdmf":
        from ._xdmf import read_xdmf, xdmf_to_meshio

        found = read_xdmf(p, source)
        arrays = _meshio_to_arrays(xdmf_to_meshio(found), source, fmt)
        extras = {
            "label_names": _xdmf_label_names(found["names"], source),
            "protected_tets": None
            if found["protected"] is None
            # (the corners of 10-node tets, which ``load(linear=True)`` reads)
            else found["blocks"][0][1][found["protected"], :4],
            "point_data": found["point_data"],
            "cell_data": found["cell_data"],
        }
    elif ext == ".meshb":
        arrays, extras = _meshb_arrays(p, source)
    else:
        captured = ""
        readable = _medit_readable_copy(p) if ext == ".mesh" else None
        linear_dir = None
        if quadratic_tetgen:  # meshio reads a 4-node copy of the 10-node tets
            from ._tetgen import linear_copy

            linear_dir = Path(tempfile.mkdtemp(prefix="jtet-tetgen-o2-"))
            try:
                readable = linear_copy(p.with_suffix(".ele"), linear_dir)
            except BaseException:
                shutil.rmtree(linear_dir, ignore_errors=True)
                raise
        try:
            with _quiet_meshio() as buf, gmsh_read_mends() as views:
                m = _meshio_module(fmt).read(str(readable or p))
        except Exception as e:
            captured = buf.getvalue()
            if fmt == "tetgen":
                _check_tetgen_attributes(p.with_suffix(".ele"))
            raise MeshFileError(
                f"{p}: not a readable {_FORMAT_NAMES[fmt]} file ({_reason(e, captured)})"
            ) from None
        finally:
            if linear_dir is not None:
                shutil.rmtree(linear_dir, ignore_errors=True)
            elif readable is not None:
                readable.unlink(missing_ok=True)
        # the Gmsh views whose sections do not parse (read ones: ``_gmsh_view_data``)
        _warn_dropped_arrays(views.get("point", []), views.get("cell", []), source)
        faces = _tetgen_faces(p.with_suffix(".node")) if fmt == "tetgen" else None
        required = None
        if ext == ".mesh":
            kinds = ("Vertices", "Edges", "Triangles", "Tetrahedra")
            required = _medit_required(p, tuple("Required" + k for k in kinds))
        arrays = _meshio_to_arrays(m, source, fmt, faces, required)
        if fmt == "gmsh":
            extras = {
                "label_names": _gmsh_label_names(m, source),
                "periodic": _gmsh_periodic(m, source),
                **_gmsh_view_data(views, len(arrays[0]), len(arrays[1]), source),
            }
        if fmt == "tetgen":
            extras = {"point_data": _tetgen_point_data(m, p.with_suffix(".node"))}
        if ext == ".mesh":
            extras["protected_tets"] = _medit_required_tets(
                required["RequiredTetrahedra"], arrays[1], p
            )
    if fmt == "medit":
        extras = {**extras, "point_data": _medit_point_data(p, len(arrays[0]), source)}
    try:
        return TetMesh.from_arrays(*arrays, **extras, source=source)
    except MeshInputError as e:
        msg = str(e)
        raise MeshInputError(msg if msg.startswith(source) else f"{source}: {msg}") from None


def _gmsh_view_data(found: dict, n_points: int, n_tets: int, source: str) -> dict:
    """``point_data`` and ``cell_data`` of a Gmsh file from the views ``gmsh_read_mends``
    ``found`` while reading it (``_gmsh_views.view_data``), with a warning for each view
    not read and each read at the last of several time steps."""
    from ._gmsh_views import view_data

    nodes, tets = found.get("nodes"), found.get("tets")
    if nodes is not None and len(nodes) != n_points:
        nodes = None
    if tets is not None and len(tets) != n_tets:
        tets = None
    views = found.get("views", [])
    point_data, cell_data, not_read, last_steps = view_data(views, nodes, tets)
    for note in [f"{n}; not read" for n in not_read] + last_steps:
        warnings.warn(f"{source}: {note}", stacklevel=3)
    return {"point_data": point_data, "cell_data": cell_data}


def _medit_point_data(path: Path, n_points: int, source: str) -> dict:
    """The point data of the Medit mesh ``path`` (``n_points`` vertices): the values at
    its vertices in the ``.sol`` file beside it, as MMG reads them (``_medit_sol``);
    none without one (a binary ``.solb`` is not read: a warning says so)."""
    from ._medit_sol import read_sol, sol_path

    sol = sol_path(path)
    if sol.is_file():
        return read_sol(sol, n_points, source)
    if sol.with_suffix(".solb").is_file():
        warnings.warn(
            f"{source}: the binary solution file {sol.with_suffix('.solb').name} is not "
            "read (jtet reads .sol files)",
            stacklevel=3,
        )
    return {}


def _candidate_arrays(read, path: Path, source: str):
    """``from_arrays``' arguments and extras of a file whose reader ``read(path, source)``
    returns (points, tets, region, candidate faces, their labels, candidate edges, their
    labels, candidate vertices, their labels, {``from_arrays`` keyword: value}): the
    candidates that are faces, edges and vertices of the tets become protected ones
    (``_mesh_cells``, ``_mesh_vertices``)."""
    points, tets, region, faces, face_labels, lines, line_labels, pins, pin_labels, extras = read(
        path, source
    )
    n = len(points)
    faces, face_labels = _mesh_cells(tets, faces, face_labels, n, source)
    edges, edge_labels = _mesh_cells(tets, lines, line_labels, n, source)
    pinned, pinned_labels = _mesh_vertices(tets, pins, pin_labels, n, source)
    arrays = (points, tets, region, faces, edges, face_labels, pinned, edge_labels, pinned_labels)
    return arrays, extras


def _abaqus_arrays(path: Path, source: str):
    """An Abaqus input file (``_abaqus``): element sets -> regions, surfaces and triangle
    elements -> labelled protected faces, line elements -> edges, node sets -> vertices."""
    from ._abaqus import read_inp

    return _candidate_arrays(read_inp, path, source)


def _exodus_arrays(path: Path, source: str):
    """An Exodus II file (``_exodus``): element blocks -> regions, side sets and triangle
    blocks -> labelled protected faces, bar blocks -> edges, node sets and sphere blocks
    -> vertices, with their names."""
    from ._exodus import read_exo

    return _candidate_arrays(read_exo, path, source)


def _med_arrays(path: Path, source: str):
    """A MED file (``_med``): tet groups -> regions, triangle, segment and point-cell
    groups -> labelled protected faces, edges and vertices, node groups -> node sets,
    fields on the nodes and tets -> point and cell data."""
    from ._med import read_med

    return _candidate_arrays(read_med, path, source)


def _xdmf_label_names(names, source: str) -> dict:
    """{(dim, label): name} from an XDMF file's ``[[dim, label, name], ...]``."""
    try:
        return {(int(d), int(label)): str(name) for d, label, name in names}
    except (TypeError, ValueError):
        raise MeshInputError(f"{source}: damaged label names") from None


def _netgen_arrays(path: Path, source: str):
    """A Netgen mesh file (``_netgen``): surface elements -> labelled protected faces,
    edge segments and point elements -> edges and vertices, names, identifications ->
    periodic links."""
    from ._netgen import read_vol

    return _candidate_arrays(read_vol, path, source)


def _meshb_arrays(path: Path, source: str):
    """``from_arrays``' arguments and extras of a binary Medit file (``_meshb``), read as
    an ASCII one is: references -> regions and labels, triangles and edges of the tets ->
    protected faces and edges, MMG's required entities kept exactly."""
    import meshio

    from ._meshb import read_meshb

    points, blocks, required = read_meshb(path, source)
    m = meshio.Mesh(
        points,
        [(kind, cells) for kind, cells, _ in blocks],
        cell_data={"medit:ref": [refs for _, _, refs in blocks]},
    )
    arrays = _meshio_to_arrays(m, source, "medit", None, required)
    tets = _medit_required_tets(required.get("RequiredTetrahedra"), arrays[1], path)
    return arrays, {"protected_tets": tets}


def _node_set_names(mesh: TetMesh) -> list[str]:
    """How warnings name the node sets: their names, else their labels."""
    return [ns.name or f"id {ns.label}" for ns in mesh.node_sets]


def _medit_sections(mesh: TetMesh) -> dict[str, np.ndarray]:
    """The Required* sections of a Medit output of ``mesh`` (0-based ids), empty ones
    left out: its protected vertices and tets, and the edges and faces it keeps exactly
    (``_kept_exactly``)."""
    edge_ids, face_ids = _kept_exactly(mesh)
    sections = {
        "RequiredVertices": mesh.protected_vertices,
        "RequiredEdges": edge_ids,
        "RequiredTriangles": face_ids,
        "RequiredTetrahedra": np.flatnonzero(mesh.protected_tet_mask()),
    }
    return {k: v for k, v in sections.items() if len(v)}


def _write(
    mesh: TetMesh, tmp: Path, fmt: str, cell_data: dict, heavy_name: str = "", quad=None
) -> None:
    """Write ``mesh`` as a ``fmt`` file at ``tmp``; with ``quad``
    (``_quadratic.quadratic_mesh(mesh)``) its cells are quadratic."""
    if fmt == "netgen":
        from ._netgen import write_vol

        write_vol(mesh, tmp, quad)
        return
    if fmt == "abaqus":
        from ._abaqus import write_inp

        write_inp(mesh, tmp, quad)
        return
    if fmt == "exodus":
        from ._exodus import write_exo

        write_exo(mesh, tmp, cell_data, quad)
        return
    if fmt == "med":
        from ._med import write_med

        write_med(mesh, tmp, cell_data, name_from=Path(heavy_name or tmp.name), quad=quad)
        return
    if fmt == "xdmf":
        from ._xdmf import companion, write_xdmf

        write_xdmf(mesh, tmp, companion(tmp), heavy_name, cell_data, quad)
        return
    if fmt in ("vtu", "vtk"):
        _write_vtk_file(mesh_to_grid(mesh, cell_data, quad), tmp, fmt)
        return
    if fmt == "medit" and mesh.point_data:
        from ._medit_sol import sol_path, write_sol

        write_sol(sol_path(tmp), mesh.point_data if quad is None else quad.point_data)
    if fmt == "medit" and (quad is not None or tmp.suffix.lower() == ".meshb"):
        from ._medit import write_medit_p2
        from ._meshb import write_meshb

        lower = _lower_blocks(mesh, fmt)
        points, blocks = mesh.points, [("tetra", mesh.tets, mesh.region), *lower]
        if quad is not None:  # P2 sections: the corners, then the edge nodes (VTK's order)
            points, blocks = quad.points, [("tetra10", quad.tets, mesh.region)]
            blocks += [(_QUADRATIC_BLOCK[k], quad.cells(c), tags) for k, c, tags in lower]
        if tmp.suffix.lower() == ".meshb":
            write_meshb(tmp, points, blocks, _medit_sections(mesh))
            return
        write_medit_p2(tmp, points, blocks)
        sections = _medit_sections(mesh)
        if sections:
            _append_required(tmp, sections)
        return
    if fmt == "tetgen":
        from ._tetgen import write_tetgen

        cells = mesh if quad is None else quad
        node = tmp.with_suffix(".node")
        write_tetgen(node, cells.points, cells.point_data, cells.tets, mesh.region)
        if len(mesh.protected_faces):
            _write_tetgen_faces(tmp.with_suffix(".face"), mesh, quad)
        return
    with _quiet_meshio():
        m = _meshio_mesh(mesh, fmt, quad)
        if fmt == "gmsh":
            # Gmsh 2.2 binary: meshio 5.3's 4.1 writer drops physical tags (no $Entities)
            # and its ASCII writers print NumPy 2 scalars as "np.float64(...)".
            _meshio_module(fmt).write(str(tmp), m, fmt_version="2.2", binary=True)
            point_data = None if quad is None else quad.point_data
            _append_gmsh_views(mesh, tmp, cell_data, len(m.cells) == 1, point_data)
        else:
            _meshio_module(fmt).write(str(tmp), m)
    if fmt == "medit":
        sections = _medit_sections(mesh)
        if sections:
            _append_required(tmp, sections)


def _kept_exactly(mesh: TetMesh) -> tuple[np.ndarray, np.ndarray]:
    """Ids (into ``protected_edges`` / ``protected_faces``: a Medit output's ``Edges`` /
    ``Triangles``) of the protected edges whose vertices are protected too, and of the
    protected faces whose edges and vertices all are: what ``improve`` keeps exactly as
    it is, as MMG keeps its required edges and triangles (how jtet reads those
    sections: ``_required_cells``), so a file read with them writes them back."""
    from ._topology import match_rows

    pinned = np.zeros(mesh.n_points, bool)
    pinned[np.asarray(mesh.protected_vertices, np.int64)] = True
    edges = np.asarray(mesh.protected_edges, np.int64).reshape(-1, 2)
    faces = np.asarray(mesh.protected_faces, np.int64).reshape(-1, 3)
    edge_ids = np.flatnonzero(pinned[edges].all(axis=1))
    sides = faces[:, [[0, 1], [1, 2], [0, 2]]].reshape(-1, 2)
    sides_kept = (match_rows(edges[edge_ids], sides, mesh.n_points) >= 0).reshape(-1, 3)
    face_ids = np.flatnonzero(sides_kept.all(axis=1) & pinned[faces].all(axis=1))
    return edge_ids, face_ids


def format_rows(table: np.ndarray, fmt: str) -> str:
    """The rows of ``table`` (k, c), each formatted by ``fmt`` (one row's format), in
    one C-level formatting of every number (np.savetxt formats row by row in Python:
    100k rows 0.18 s against 0.04 s)."""
    if not len(table):
        return ""
    return (fmt * len(table)) % tuple(np.asarray(table).ravel().tolist())


def _write_tetgen_faces(path: Path, mesh: TetMesh, quad=None) -> None:
    """The protected faces of ``mesh`` as a TetGen ``.face`` file with their labels as
    boundary markers (what TetGen writes for the boundary and the constrained facets of
    its meshes, and what ``load`` reads back), numbered from 0 like the ``.node`` file
    (``_tetgen.write_tetgen``). With ``quad`` (``_quadratic.quadratic_mesh(mesh)``),
    each face also lists the nodes of its edges ab, bc, ca, as ``tetgen -o2`` writes
    them (VTK's quadratic triangle order is the same)."""
    faces = np.asarray(mesh.protected_faces, np.int64)
    rows = faces if quad is None else quad.cells(faces)
    table = np.column_stack(
        [np.arange(len(faces)), rows, np.asarray(mesh.protected_face_labels, np.int64)]
    )
    nodes = "3 nodes" if quad is None else "3 corners a b c, the nodes of edges ab bc ca"
    with open(path, "w") as f:
        f.write(f"# faces of the mesh that stay (jtet's protected faces): id, {nodes}, label\n")
        f.write(f"{len(faces)} 1\n")
        f.write(format_rows(table, "%d" + " %d" * (rows.shape[1] + 1) + "\n"))


def output_format(path) -> str:
    """The format ``save`` writes to ``path`` ("vtu", "gmsh", ...), from its extension.

    Raises:
        MeshFileError: an extension jtet does not write.
    """
    p = Path(path)
    ext = p.suffix.lower()
    fmt = _READ_FORMATS.get(ext)
    if fmt is None:
        raise MeshFileError(
            f"{p}: unknown mesh file extension {ext or '(none)'!r}; jtet writes {_KNOWN_EXTENSIONS}"
        )
    return fmt


def written_files(path) -> list[Path]:
    """The files ``save(mesh, path)`` may write or replace: ``path``; for TetGen the
    ``.node``, ``.ele`` and ``.face`` files of its name; for XDMF ``path`` and the
    ``.h5`` file of its name (its heavy data); for Medit ``path`` and the ``.sol`` file
    of its name (its point data)."""
    p = Path(path)
    fmt = output_format(p)
    if fmt == "tetgen":
        return _tetgen_files(p)
    if fmt == "xdmf":
        from ._xdmf import companion

        return [p, companion(p)]
    if fmt == "medit":
        from ._medit_sol import sol_path

        return [p, sol_path(p)]
    return [p]


def _tetgen_files(p: Path) -> list[Path]:
    """The ``.node``, ``.ele`` and ``.face`` files of a TetGen mesh named ``p``."""
    return [p.with_suffix(s) for s in (".node", ".ele", ".face")]


def read_files(path) -> list[Path]:
    """The files ``load(path)`` reads: ``path``; for TetGen its ``.node``, ``.ele`` and
    ``.face`` files; for XDMF the HDF5 and binary files it names too; for Medit the
    ``.sol`` file of its name when there is one. Unknown extensions: ``[path]``."""
    p = Path(path)
    fmt = _READ_FORMATS.get(p.suffix.lower())
    if fmt == "tetgen":
        return _tetgen_files(p)
    if fmt == "xdmf":
        from ._xdmf import heavy_files

        return [p, *heavy_files(p)]
    if fmt == "medit":
        from ._medit_sol import sol_path

        return [p, sol_path(p)] if sol_path(p).is_file() else [p]
    return [p]


def new_temp_file(parent: Path, prefix: str, suffix: str) -> Path:
    """Create an empty file with a fresh random name in ``parent`` and return its path.

    Its mode is 0o666 under the process's umask, as for any new file: ``tempfile.mkstemp``
    makes 0o600 files, which the rename into place would pass on to reports and meshes
    that other users could not read. (Reading the umask means setting it, which races
    with threads creating files meanwhile: the kernel applies it here instead.)

    Raises:
        OSError: the directory is missing or not writable.
    """
    for _ in range(100):
        path = parent / f"{prefix}{secrets.token_hex(6)}{suffix}"
        try:
            os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
        except FileExistsError:
            continue
        return path
    raise FileExistsError(f"no free temporary file name in {parent}")


def move_into_place(tmp: Path, target: Path) -> None:
    """Rename the finished file ``tmp`` onto ``target`` (atomic on one file system); an
    existing ``target`` keeps its mode."""
    if target.exists():
        os.chmod(tmp, target.stat().st_mode & 0o7777)
    os.replace(tmp, target)


def _quadratic_output(mesh: TetMesh, path: Path):
    """``_quadratic.quadratic_mesh(mesh)`` for ``save(..., quadratic=True)``, with a
    warning when curved tets fold (a non-positive Jacobian at a node)."""
    from ._quadratic import folded_tets, quadratic_mesh

    quad = quadratic_mesh(mesh)
    n_folded, worst = folded_tets(quad)
    if n_folded:
        warnings.warn(
            f"{path}: {n_folded} quadratic tet(s) have a non-positive Jacobian at a node "
            f"(smallest scaled Jacobian, Gmsh's minSJ: {worst:.3g}): a curved edge bends into "
            "a tet too thin for it (Gmsh's SetOrder 2 leaves such tets too). A solver that "
            "checks the Jacobian at the nodes refuses them: refine there, or write the "
            "mesh linear",
            stacklevel=3,
        )
    return quad


def save(
    mesh: TetMesh,
    path: str | os.PathLike,
    *,
    cell_data: dict | None = None,
    overwrite: bool = True,
    quadratic: bool = False,
) -> Path:
    """Write ``mesh`` to ``path``, atomically; the format follows the extension.

    ``.vtu`` (zlib-compressed binary XML) and ``.vtk`` (binary legacy) store the region as a
    ``region`` cell array plus the arrays of ``mesh.cell_data`` and of ``cell_data`` (name
    -> one value per tet, which wins; ``.xdmf`` and Exodus too, as cell attributes and
    element variables), the protected entities as field data, and ``mesh.point_data`` as
    point arrays (also
    ``.xdmf``: node attributes; ``.msh``: views; TetGen: point attributes, float64
    columns named in a comment line; Medit: the ``.sol`` file beside the mesh,
    ``_medit_sol``; Exodus: nodal variables; the other formats leave it out with a
    warning). ``.msh`` (Gmsh 2.2 binary, which every
    Gmsh-aware tool reads) stores the region as physical and elementary tags, the
    protected faces as triangles tagged with their labels, edges and vertices as line and
    point elements, ``mesh.point_data`` and ``mesh.cell_data`` as views (``$NodeData``,
    ``$ElementData`` over the tets; ``_gmsh_views``), and ``cell_data`` as element data
    when there are no protected entities (meshio 5.3 reads no element data beside
    other element blocks: a warning says so for ``mesh.cell_data``). ``.mesh`` / ``.meshb`` (Medit) store the region as references, the protected
    faces and edges as ``Triangles`` and ``Edges``, the vertices and tets as
    ``RequiredVertices`` and ``RequiredTetrahedra``, and what ``improve`` keeps exactly
    as MMG's required edges and triangles (``.meshb``: version 2, which MMG reads,
    ``_meshb``). ``.node`` / ``.ele`` (TetGen, both files are written; region ->
    element attribute) store the region, and the protected faces with their labels as
    boundary markers in a ``.face`` file beside them (an old ``.face`` of that name is
    replaced or, for a mesh without protected faces, removed). ``.xdmf`` (with its heavy
    data in the ``.h5`` file of the same name) stores everything but periodic links, in
    dolfinx's layout (``_xdmf``). ``.inp`` (Abaqus / CalculiX) stores the regions as
    element sets and the protected faces as element-face surfaces (``_abaqus``). ``.vol``
    (Netgen / NGSolve) stores the regions as materials, every boundary, interface and
    protected face as a surface element, the protected edges and vertices and the names
    (``_netgen``). ``.med`` (MED 3.0) stores everything but periodic links and protected
    tets: a group per label, node groups, the point data and cell arrays as fields
    (``_med``). What a format cannot store is dropped with a warning.

    ``quadratic=True`` writes 10-node tets (and 6-node protected faces, 3-node protected
    edges), in every format (``.inp``: C3D10, ``.med``: T10, ``.exo``: TETRA10, Medit:
    P2 sections, TetGen and Netgen: their own node orders): a node on each edge, that of ``mesh.curved_edges`` (a
    curved boundary read with ``load(path, linear=True)``) or the midpoint
    (``_quadratic``), numbered after the mesh's points. A warning counts the curved tets
    whose Jacobian is not positive at every node.

    The file is written to a temporary file in the same directory and moved into place, so
    ``path`` is either the complete new file or left untouched.

    Returns the path written (for TetGen, the ``.node`` file).

    Raises:
        MeshFileError: unknown extension, missing directory, existing file with
            ``overwrite=False``, or any failure while writing.
        MeshInputError: ``cell_data`` does not have one value per tet.
    """
    p = Path(path)
    fmt = output_format(p)
    cell_data = _check_cell_data(mesh, cell_data)
    quad = _quadratic_output(mesh, p) if quadratic else None
    if fmt in ("medit", "tetgen", "abaqus", "netgen", "exodus", "med"):
        dropped = list(cell_data) if fmt not in ("exodus", "med") else []
        if len(dropped) > 4:
            dropped = [f"{len(dropped)} cell arrays ({', '.join(dropped[:3])}, ...)"]
        if fmt in ("tetgen", "abaqus", "exodus") and len(mesh.protected_edges):
            dropped.append("protected edges")
        no_vertices = fmt == "tetgen"
        if len(mesh.protected_vertices) and no_vertices:
            dropped.append("protected vertices")
        if len(mesh.label_names) and fmt not in ("abaqus", "netgen", "exodus", "med"):
            dropped.append(f"{len(mesh.label_names)} label name(s) (Gmsh physical names)")
        if mesh.periodic and fmt != "netgen":
            dropped.append(f"{len(mesh.periodic)} periodic link(s)")
        if len(mesh.protected_tets) and fmt != "medit":
            dropped.append("protected tets")
        if dropped:
            stored = {
                "medit": "region labels and protected faces, edges, vertices and tets",
                "abaqus": "regions (element sets, with their names), protected faces "
                "(element-face surfaces) and protected vertices (node sets)",
                "netgen": "regions (materials, with their names) and protected faces, "
                "edges and vertices (surface elements, edge segments, point elements)",
                "exodus": "regions (element blocks), protected faces (side sets) and "
                "vertices (node sets), their names, the cell arrays (element variables) "
                "and the point data (nodal variables)",
                "med": "regions, protected faces, edges and vertices (groups of tets, "
                "triangles, segments and point cells, with their names), node sets (node "
                "groups), the point data and the cell arrays (fields)",
            }.get(fmt, "region labels and protected faces")
            warnings.warn(
                f"{p}: the {_FORMAT_NAMES[fmt]} format stores only the {stored}; "
                f"not saved: {', '.join(dropped)}",
                stacklevel=2,
            )
        low = np.unique(mesh.region[mesh.region < 1]) if fmt == "netgen" else []
        if len(low):
            warnings.warn(
                f"{p}: Netgen numbers materials from 1: the regions are written as "
                f"materials 1, 2, ... in label order (region {int(low[0])} among them); each "
                "material is named after its region's name or label",
                stacklevel=2,
            )
    elif fmt == "xdmf" and mesh.periodic:
        warnings.warn(
            f"{p}: the XDMF format has no periodic links; not saved: "
            f"{len(mesh.periodic)} periodic link(s)",
            stacklevel=2,
        )
    elif fmt == "gmsh":
        if len(mesh.protected_tets):
            warnings.warn(
                f"{p}: the Gmsh format has no protected tets; not saved: "
                f"{len(mesh.protected_tets)} protected tet(s) (a physical volume of their "
                "own keeps them apart: improve --regions)",
                stacklevel=2,
            )
        n_unlabelled = int(np.count_nonzero(mesh.region == 0))
        if n_unlabelled:
            # physical tag 0 is "in no physical group": Gmsh reads such tets into no
            # physical volume, and solvers that take cells from physical groups skip them
            warnings.warn(
                f"{p}: {n_unlabelled} tet(s) of region 0, which Gmsh files cannot put in a "
                "physical volume (tag 0 is none): Gmsh and solvers that read cells by "
                "physical group (dolfinx) will not see them; give them a label of their "
                "own (TetMesh.relabel({0: 1}); jtet improve / convert --relabel 0:1)",
                stacklevel=2,
            )
        # meshio 5.3's Gmsh 2.2 reader splits element data over two or more element
        # blocks at element 2 and refuses its own file ("Incompatible cell data"), and
        # meshio is how many solvers read .msh: beside protected triangles, lines or
        # points, the arrays of ``cell_data`` (jtet's quality arrays) are left out, and
        # the mesh's own cell data are written (they are the user's) with a warning
        lower = bool(_lower_blocks(mesh, fmt))
        if lower and cell_data:
            warnings.warn(
                f"{p}: not saved in the Gmsh file: {len(cell_data)} cell array(s) (with "
                "protected triangles, lines or points) (use .vtu)",
                stacklevel=2,
            )
        if lower and mesh.cell_data:
            names = list(mesh.cell_data)
            warnings.warn(
                f"{p}: the cell data ({', '.join(names[:3])}{', ...' if len(names) > 3 else ''}) "
                "are written as element data beside protected triangles, lines or "
                "points: Gmsh and jtet read such a file, meshio 5.3 does not (use .vtu "
                "or .xdmf for meshio)",
                stacklevel=2,
            )
    for what, data, formats, where in (
        ("point", mesh.point_data,
         ("vtu", "vtk", "xdmf", "gmsh", "tetgen", "medit", "exodus", "med"),
         ".vtu, .vtk, .xdmf, Gmsh, TetGen, Medit, Exodus and MED"),
        ("cell", mesh.cell_data, ("vtu", "vtk", "xdmf", "gmsh", "exodus", "med"),
         ".vtu, .vtk, .xdmf, Gmsh, Exodus and MED"),
    ):  # fmt: skip
        if data and fmt not in formats:
            names = list(data)
            warnings.warn(
                f"{p}: jtet writes {what} data to {where} files only; not saved: "
                f"{len(names)} {what} array(s) ({', '.join(names[:3])}"
                f"{', ...' if len(names) > 3 else ''})",
                stacklevel=2,
            )
    if mesh.node_sets and fmt not in ("vtu", "vtk", "abaqus", "exodus", "med"):
        warnings.warn(
            f"{p}: the {_FORMAT_NAMES[fmt]} format has no node sets; not saved: "
            f"{len(mesh.node_sets)} node set(s) ({', '.join(_node_set_names(mesh)[:3])}"
            f"{', ...' if len(mesh.node_sets) > 3 else ''}) (use .inp, .exo, .med or .vtu)",
            stacklevel=2,
        )
    for what, values in (
        ("region", mesh.region),
        ("surface", mesh.protected_face_labels),
        ("edge", mesh.protected_edge_labels),
        ("vertex", mesh.protected_vertex_labels),
    ):
        if fmt in ("gmsh", "medit") and len(values):
            lo, hi = int(values.min()), int(values.max())
            if lo < -(2**31) or hi >= 2**31:
                raise MeshFileError(
                    f"{p}: {what} labels [{lo}, {hi}] do not fit the 32-bit tags of the "
                    f"{_FORMAT_NAMES[fmt]} format"
                )
    targets = [p] if fmt != "xdmf" else written_files(p)
    # a companion of the mesh being replaced that the new one has nothing for: a TetGen
    # .face file (no protected faces), a Medit .sol file (no point data). Left in
    # place, ``load`` (and MMG, for the .sol) would read it as the new mesh's.
    stale = None
    if fmt == "tetgen":
        targets = [p.with_suffix(".node"), p.with_suffix(".ele")]
        if len(mesh.protected_faces):
            targets.append(p.with_suffix(".face"))
        elif p.with_suffix(".face").exists():
            stale = p.with_suffix(".face")
    if fmt == "medit":
        from ._medit_sol import sol_path

        if mesh.point_data:
            targets.append(sol_path(p))
        elif sol_path(p).exists():
            stale = sol_path(p)
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise MeshFileError(f"{p}: {parent} is not an existing directory")
    for t in targets + ([stale] if stale else []):
        if t.is_dir():
            raise MeshFileError(f"{t}: is a directory")
        if t.exists() and not overwrite:
            raise MeshFileError(f"{t}: the file exists (pass overwrite=True to replace it)")

    temps: list[Path] = []
    try:
        try:
            temps = [new_temp_file(parent, f".{p.stem}.tmp-", targets[0].suffix)]
        except OSError as e:
            raise MeshFileError(f"{p}: cannot create a file in {parent} ({_reason(e)})") from None
        if fmt in ("tetgen", "xdmf", "medit"):
            # meshio writes the .ele next to the .node, with the same stem, and
            # ``_write_tetgen_faces`` the .face; ``write_xdmf`` the .h5 beside the .xdmf;
            # ``write_sol`` the .sol beside the .mesh
            temps += [temps[0].with_suffix(s.suffix) for s in targets[1:]]
        try:
            _write(mesh, temps[0], fmt, cell_data, targets[-1].name, quad)
            for tmp, target in zip(temps, targets, strict=True):
                if not tmp.is_file():
                    raise MeshFileError(f"{target}: the writer produced no file")
            # the companion files first: the file that names them is the last to change
            for tmp, target in reversed(list(zip(temps, targets, strict=True))):
                move_into_place(tmp, target)
            if stale is not None:
                try:
                    stale.unlink()
                except OSError as e:
                    warnings.warn(
                        f"{stale}: could not remove the old file ({_reason(e)}); delete "
                        "it, or loading the new mesh reads it as its own",
                        stacklevel=2,
                    )
        except MeshFileError:
            raise
        except Exception as e:
            raise MeshFileError(
                f"{p}: could not write {_FORMAT_NAMES[fmt]} file ({_reason(e)})"
            ) from None
    finally:
        for tmp in temps:
            with contextlib.suppress(OSError):
                tmp.unlink()
    return targets[0]


# ---------------------------------------------------------------------------------------
# demo meshes

_DEMO_FILES = {"demo": "demo.vtu", "two_regions": "demo_two_regions.vtu"}


def demo_mesh(name: str = "demo") -> TetMesh:
    """A small tet mesh shipped with jtet (generated by ``experiments/make_demo_mesh.py``).

    ``"demo"``: an unoptimized Gmsh Delaunay mesh of a 2 x 1 x 1 box with a spherical hole,
    6209 tets, one region (label 0), with slivers (worst dihedral angle 1.14 degrees).
    ``"two_regions"``: a unit box split by the plane z = 0.45 into regions 1 (below) and 2
    (above), 1928 tets, for interface tests. The result is cached (meshes are immutable).
    """
    if name not in _DEMO_FILES:
        raise MeshInputError(f"unknown demo mesh {name!r}; choose one of {sorted(_DEMO_FILES)}")
    return _load_demo(name)


@functools.cache
def _load_demo(name: str) -> TetMesh:
    from importlib import resources

    ref = resources.files("jtet") / "data" / _DEMO_FILES[name]
    with resources.as_file(ref) as p:
        return load(p)
