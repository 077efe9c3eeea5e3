"""TetMesh: the immutable host-side mesh every stage of jtet reads and returns."""

from __future__ import annotations

import functools
import numbers
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from jaxtyping import Float, Int

from ._errors import MeshInputError


def _readonly(a: np.ndarray) -> np.ndarray:
    """A read-only array that shares no memory with the caller's (never freeze user data)."""
    if a.flags.writeable or a.base is not None:
        a = np.array(a, order="C", copy=True)
    a.flags.writeable = False
    return a


class _ReadOnlyMapping(Mapping):
    """A read-only mapping that, unlike ``types.MappingProxyType``, pickles, as the
    meshes that hold it do."""

    def __init__(self, items: dict):
        self._items = dict(items)

    def __getitem__(self, key):
        return self._items[key]

    def __iter__(self):
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)


class LabelNames(_ReadOnlyMapping):
    """A read-only mapping (dimension, label) -> name (``TetMesh.label_names``)."""

    def __repr__(self) -> str:
        return f"LabelNames({self._items!r})"


class _ArrayData(_ReadOnlyMapping):
    """A read-only mapping name -> read-only array of one value (or one row of k
    components) per vertex or per tet."""

    def __repr__(self) -> str:
        shapes = ", ".join(f"{k!r}: {a.dtype}{list(a.shape)}" for k, a in self._items.items())
        return f"{type(self).__name__}({{{shapes}}})"


class PointData(_ArrayData):
    """A read-only mapping name -> read-only (n,) or (n, k) array of one value (or k
    components) per vertex (``TetMesh.point_data``): a temperature, a displacement, a
    node marker."""


class CellData(_ArrayData):
    """A read-only mapping name -> read-only (m,) or (m, k) array of one value (or k
    components) per tet (``TetMesh.cell_data``): a material id, a partition, a density."""


def _checked_arrays(data, n: int, kind: type[_ArrayData]) -> _ArrayData:
    """``TetMesh.point_data`` (``kind`` ``PointData``, ``n`` vertices) or ``cell_data``
    (``CellData``, ``n`` tets) as a read-only mapping of read-only (n,) or (n, k) arrays
    of real numbers (integers kept integers, bools as int8)."""
    if isinstance(data, kind) and all(len(a) == n for a in data.values()):
        return data
    if data is None:
        return kind({})
    field_name, per = ("point_data", "vertex") if kind is PointData else ("cell_data", "tet")
    if not hasattr(data, "items"):
        raise MeshInputError(f"{field_name} must be a mapping name -> array, got {data!r}")
    out = {}
    for name, values in data.items():
        if not isinstance(name, str) or not name:
            raise MeshInputError(f"{field_name} names must be non-empty strings, got {name!r}")
        if kind is CellData and name == "region":
            raise MeshInputError(
                "cell_data may not hold 'region': it is the mesh's own region array "
                "(TetMesh.region)"
            )
        a = np.asarray(values)
        if a.dtype == np.bool_:
            a = a.astype(np.int8)
        numeric = np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)
        if not numeric:
            raise MeshInputError(f"{field_name}[{name!r}] holds {a.dtype} values, not numbers")
        if a.ndim not in (1, 2) or len(a) != n:
            raise MeshInputError(
                f"{field_name}[{name!r}] has shape {a.shape}; it needs one value or one row "
                f"of values per {per}: ({n},) or ({n}, k)"
            )
        out[name] = _readonly(a)
    return kind(out)


def _checked_names(names) -> LabelNames:
    """``TetMesh.label_names`` as a read-only mapping (dim, label) -> name, sorted."""
    if isinstance(names, LabelNames):
        return names
    if names is None:
        return LabelNames({})
    if not hasattr(names, "items"):
        raise MeshInputError(f"label_names must be a mapping (dim, label) -> name, got {names!r}")
    out = {}
    for key, name in names.items():
        ok = (
            isinstance(key, tuple)
            and len(key) == 2
            and all(isinstance(k, numbers.Integral) and not isinstance(k, bool) for k in key)
            and 0 <= key[0] <= 3
        )
        if not ok or not isinstance(name, str) or not name:
            raise MeshInputError(
                "label_names must map (dimension 0..3, integer label) to a non-empty name, "
                f"got {key!r}: {name!r}"
            )
        out[(int(key[0]), int(key[1]))] = name
    return LabelNames(dict(sorted(out.items())))


class Periodic(NamedTuple):
    """One periodic link of a Gmsh mesh (``$Periodic``): the nodes of entity
    ``tags[0]`` (dimension ``dim``) are images of those of entity ``tags[1]``."""

    dim: int
    tags: tuple[int, int]
    affine: tuple[float, ...] | None  # 16 numbers, row-major 4 x 4: master -> slave
    pairs: np.ndarray  # (k, 2) int64 vertex ids (slave, master), read-only


class NodeSet(NamedTuple):
    """A set of vertices a solver's input names (an Abaqus ``*NSET``, an Exodus node
    set): what its boundary conditions, loads and outputs are applied to. ``improve``
    never moves these vertices (unless the set holds every vertex: it constrains
    nothing), and the Abaqus, Exodus and VTK savers write the set back. ``name`` may be
    "" (an Exodus node set without a name); ``label`` is an Exodus node set id (None:
    none)."""

    name: str
    ids: np.ndarray  # (k,) int64 sorted distinct vertex ids, read-only
    label: int | None = None


def _checked_node_sets(sets, n_points: int) -> tuple[NodeSet, ...]:
    """``TetMesh.node_sets`` as a tuple of ``NodeSet`` (items: ``NodeSet`` or (name,
    ids[, label])) with sorted, distinct, in-range vertex ids."""
    if sets is None:
        return ()
    out = []
    for item in sets:
        try:
            name, ids, *rest = item
            label = None if not rest or rest[0] is None else int(rest[0])
            ids = np.asarray(ids)
            if not np.issubdtype(ids.dtype, np.integer) and ids.size:
                raise ValueError("ids must be integer vertex ids")
            ids = np.unique(ids.astype(np.int64).reshape(-1))
        except (TypeError, ValueError) as e:
            raise MeshInputError(
                f"node_sets must hold (name, vertex ids[, label]) items: {e}"
            ) from None
        if not isinstance(name, str):
            raise MeshInputError(f"node set names must be strings, got {name!r}")
        if len(ids) and (ids[0] < 0 or ids[-1] >= n_points):
            raise MeshInputError(
                f"node set {name or label!r} holds vertex ids out of range [0, {n_points})"
            )
        out.append(NodeSet(name, _readonly(ids), label))
    return tuple(out)


class CurvedEdges(NamedTuple):
    """Mid-edge nodes off their edge's midpoint: those of a quadratic mesh's curved
    boundary, read with ``load(path, linear=True)``. ``edges`` (k, 2) int64 sorted
    distinct vertex pairs in lexicographic order, ``points`` (k, 3) float64 the node of
    each, both read-only. A quadratic output (``save(..., quadratic=True)``) puts its node on each edge of
    the mesh listed here and the midpoint on every other edge."""

    edges: np.ndarray
    points: np.ndarray


def _checked_curved_edges(curved, n_points: int) -> CurvedEdges:
    """``TetMesh.curved_edges`` as a ``CurvedEdges`` of sorted, distinct, in-range vertex
    pairs in lexicographic order (the first of duplicates kept) and finite float64
    points."""
    if curved is None:
        return CurvedEdges(_readonly(np.zeros((0, 2), np.int64)), _readonly(np.zeros((0, 3))))
    try:
        edges, points = curved
        edges, points = np.asarray(edges), np.asarray(points, np.float64)
        if not np.issubdtype(edges.dtype, np.integer) and edges.size:
            raise ValueError("edges must be integer vertex ids")
        edges, points = edges.astype(np.int64).reshape(-1, 2), points.reshape(-1, 3)
    except (TypeError, ValueError) as e:
        raise MeshInputError(
            f"curved_edges must be ((k, 2) vertex pairs, (k, 3) mid-edge points): {e}"
        ) from None
    if len(edges) != len(points):
        raise MeshInputError(
            f"curved_edges has {len(edges)} edges and {len(points)} mid-edge points"
        )
    if len(edges) and (edges.min() < 0 or edges.max() >= n_points):
        raise MeshInputError(f"curved_edges holds vertex ids out of range [0, {n_points})")
    if len(edges) and (edges[:, 0] == edges[:, 1]).any():
        raise MeshInputError("curved_edges holds an edge from a vertex to itself")
    if not np.isfinite(points).all():
        raise MeshInputError("curved_edges holds NaN or infinite mid-edge points")
    edges, first = np.unique(np.sort(edges, axis=1), axis=0, return_index=True)
    return CurvedEdges(_readonly(edges), _readonly(points[first]))


def unmoved_edges(edges: np.ndarray, old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """(k,) bool: the rows of ``edges`` (k, 2) whose two end vertices are at the same
    coordinates among the ``new`` points (n', 3) as among the ``old`` ones (n, 3): a
    curved edge's node stays on its curve only while the ends of its edge do."""
    keep = (edges < min(len(old), len(new))).all(axis=1)
    ends = edges[keep]
    keep[keep] = (new[ends] == old[ends]).all(axis=(1, 2))
    return keep


def _checked_periodic(links, n_points: int) -> tuple[Periodic, ...]:
    """``TetMesh.periodic`` as a tuple of ``Periodic`` with in-range vertex ids."""
    if links is None:
        return ()
    out = []
    for link in links:
        try:
            dim, tags, affine, pairs = link
            dim, tags = int(dim), (int(tags[0]), int(tags[1]))
            affine = None if affine is None else tuple(float(a) for a in np.ravel(affine))
            pairs = np.asarray(pairs)
            if not np.issubdtype(pairs.dtype, np.integer) and pairs.size:
                raise ValueError("pairs must be integer vertex ids")
            pairs = pairs.astype(np.int64).reshape(-1, 2)
        except (TypeError, ValueError, IndexError) as e:
            raise MeshInputError(
                "periodic must hold (dim, (slave tag, master tag), affine or None, (k, 2) "
                f"vertex pairs) links: {e}"
            ) from None
        if not 0 <= dim <= 2 or (affine is not None and len(affine) != 16):
            raise MeshInputError(
                f"periodic link {tags}: dimension {dim} (0..2) with {len(affine or ())} "
                "affine numbers (16 or none)"
            )
        if len(pairs) and (pairs.min() < 0 or pairs.max() >= n_points):
            raise MeshInputError(
                f"periodic link {tags} holds vertex ids out of range [0, {n_points})"
            )
        out.append(Periodic(dim, tags, affine, _readonly(pairs)))
    return tuple(out)


def _orient_volumes6(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """6 x signed volume (m,) of every tet in plain float64 NumPy (no robustness filter).

    Coordinates gathered per axis from contiguous rows and the triple product written out:
    ~3x faster than ``np.cross`` and ``einsum`` on (m, 3) rows (983k tets: 0.55 -> 0.17 s;
    the statistics compute it before and after every run). Equal to that form up to the
    order of the last two additions (an ulp).
    """
    x, y, z = np.ascontiguousarray(np.asarray(points, np.float64).T)
    i0, i1, i2, i3 = np.ascontiguousarray(np.asarray(tets).T)
    ax, ay, az = x[i1] - x[i0], y[i1] - y[i0], z[i1] - z[i0]
    bx, by, bz = x[i2] - x[i0], y[i2] - y[i0], z[i2] - z[i0]
    cx, cy, cz = x[i3] - x[i0], y[i3] - y[i0], z[i3] - z[i0]
    return ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)


def _checked_points(points) -> np.ndarray:
    """(n, 3) float64 points, or ``MeshInputError`` (shape, dtype, NaN / inf)."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshInputError(f"points must have shape (n, 3), got {points.shape}")
    if not (np.issubdtype(points.dtype, np.floating) or np.issubdtype(points.dtype, np.integer)):
        raise MeshInputError(f"points must be real numbers, got dtype {points.dtype}")
    points = points.astype(np.float64, copy=False)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise MeshInputError(
            f"{int(bad.sum())} point(s) have NaN or infinite coordinates "
            f"(first: point {i} = {points[i].tolist()})"
        )
    return points


def _checked_tets(tets, n_points: int, start: int = 0) -> np.ndarray:
    """(m, 4) int64 tets, or ``MeshInputError`` (shape, dtype, empty, index range,
    repeated vertex). Rows before ``start`` are trusted (taken from a checked mesh)."""
    tets = np.asarray(tets)
    if tets.size == 0:
        tets = tets.reshape(0, 4)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshInputError(f"tets must have shape (m, 4), got {tets.shape}")
    if not np.issubdtype(tets.dtype, np.integer):
        if np.issubdtype(tets.dtype, np.floating) and np.all(tets == np.round(tets)):
            tets = tets.astype(np.int64)
        else:
            raise MeshInputError(f"tets must hold integer indices, got dtype {tets.dtype}")
    tets = tets.astype(np.int64, copy=False)
    if len(tets) == 0:
        raise MeshInputError("the mesh is empty: it has no tetrahedra")
    new = tets[start:]
    out = (new < 0) | (new >= n_points)
    if out.any():
        t = start + int(np.flatnonzero(out.any(axis=1))[0])
        raise MeshInputError(
            f"tet {t} has vertex indices {tets[t].tolist()} out of range "
            f"[0, {n_points}) ({int(out.any(axis=1).sum())} such tet(s))"
        )
    s = np.sort(new, axis=1)
    rep = (s[:, 1:] == s[:, :-1]).any(axis=1)
    if rep.any():
        t = start + int(np.flatnonzero(rep)[0])
        raise MeshInputError(
            f"tet {t} repeats a vertex: {tets[t].tolist()} ({int(rep.sum())} such tet(s))"
        )
    return tets


# faces of tet (v0, v1, v2, v3) opposite v0..v3, outward for a positively oriented tet
_OUT_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def face_conflicts(tets: np.ndarray, n_points: int) -> tuple[int, np.ndarray, np.ndarray]:
    """Combinatorial conformity of a tet list (no geometry), by one sort of its 4m faces.

    Returns ``(n_overshared, misoriented, duplicates)``: the number of faces in more than
    two tets; (k, 2) pairs of tets that share a face and induce the same orientation on it
    (their vertex orders disagree: one is listed "inside out" relative to the other); and
    (d, 2) pairs of tets with the same four vertices. A conforming, consistently ordered
    mesh has (0, empty, empty); its tets may still be geometrically inverted.
    """
    from ._topology import _group, row_keys

    f = tets[:, _OUT_FACES].reshape(-1, 3)
    par = ((f[:, 0] > f[:, 1]).astype(np.int8) + (f[:, 0] > f[:, 2]) + (f[:, 1] > f[:, 2])) % 2
    perm, ptr, _ = _group(row_keys(np.sort(f, axis=1), n_points))
    cnt = np.diff(ptr)
    two = ptr[:-1][cnt == 2]
    s0, s1 = perm[two], perm[two + 1]
    pairs = np.column_stack([s0 // 4, s1 // 4])
    dup = tets.reshape(-1)[s0] == tets.reshape(-1)[s1]  # same apex: same vertex set
    mis = (par[s0] == par[s1]) & ~dup
    return int((cnt > 2).sum()), pairs[mis], np.unique(pairs[dup], axis=0)


def topology_face_conflicts(tets: np.ndarray, topology) -> tuple[np.ndarray, np.ndarray]:
    """``face_conflicts(tets, n)[1:]`` (misoriented and duplicate pairs, same order) read
    from a built ``topology`` of ``tets`` (no face in more than two tets then): its faces
    are grouped already, so no sort of the 4m faces is needed again.

    The orientation a tet induces on its face F (sorted) with apex a is the parity of the
    permutation taking its vertex row to (F, a): the row's own inversions plus the
    number of F's vertices above a. Two tets on a face must induce different ones.
    """
    t = topology.face_tets  # (F, 2): the face's tets, lower slot first; -1: none
    apex = topology.face_apex
    # every face is computed and the boundary ones (slot 1 empty) are masked out at the
    # end; parities are XORs of comparisons of contiguous columns (983k tets: the (k, 3)
    # comparisons summed along rows and the gathers of the interior faces took 148 ms)
    f0, f1, f2 = (np.ascontiguousarray(c) for c in topology.faces.T)
    col = [np.ascontiguousarray(c) for c in np.asarray(tets).T]
    odd = np.zeros(len(tets), bool)
    for i in range(4):  # a loop over the 6 vertex pairs of a row, not over tets
        for j in range(i + 1, 4):
            odd ^= col[i] > col[j]
    par = []
    for s in (0, 1):
        a = np.ascontiguousarray(apex[:, s])
        par.append(odd[np.ascontiguousarray(t[:, s])] ^ (f0 > a) ^ (f1 > a) ^ (f2 > a))
    two = t[:, 1] >= 0
    dup = two & (apex[:, 0] == apex[:, 1])  # same apex: same vertex set
    mis = two & (par[0] == par[1]) & ~dup
    return t[mis], np.unique(t[dup], axis=0)


#: label of the edges and vertices ``TetMesh._with_pinned`` protects for a run
PIN_LABEL = -1

#: the kinds of protected entities: their field, their labels' field, their vertex count
PROTECTED = {
    "face": ("protected_faces", "protected_face_labels", 3),
    "edge": ("protected_edges", "protected_edge_labels", 2),
    "vertex": ("protected_vertices", "protected_vertex_labels", 1),
}


@dataclass(frozen=True, eq=False, repr=False)
class TetMesh:
    """An immutable tetrahedral mesh.

    Attributes:
        points: (n, 3) float64 vertex coordinates.
        tets: (m, 4) int64 vertex indices. Orientation convention (VTK / pyvista): a tet
            is correct when ``det[p1-p0, p2-p0, p3-p0] > 0``.
        region: (m,) int64 region label of every tet (all 0 when the input had none).
        protected_faces: (k, 3) int64 user-protected triangles (sorted vertex triples);
            they are subfacets in addition to the boundary and region interfaces.
        protected_edges: (k, 2) int64 user-protected edges (sorted pairs); subsegments.
        protected_face_labels: (k,) int64 label of every protected face (0 when the
            input gave none): a Gmsh physical surface, a Medit reference, a TetGen facet
            marker. Faces of different labels are different surfaces, so flips never move
            the border between two labels, and the savers write the labels back.
        protected_vertices: (k,) int64 user-protected vertices (sorted, distinct): never
            moved (a Gmsh point embedded in a volume, a point source, a probe).
        protected_edge_labels, protected_vertex_labels: (k,) int64 labels of the
            protected edges and vertices (0 when the input gave none: Gmsh physical
            curves and points, Medit references), written back by the savers.
        label_names: read-only mapping (dimension, label) -> name of the labels that have
            one: Gmsh physical names (dimension 3: ``region`` labels, 2: protected face
            labels, 1: edge labels, 0: vertex labels), written back to Gmsh and VTK files.
        periodic: tuple of ``Periodic`` links (Gmsh ``$Periodic``: pairs of vertices of
            periodic surfaces, curves and points). ``improve`` keeps these vertices in
            place and the boundary edges between them, so the periodic surfaces keep
            matching triangulations, and the savers write the links back.
        protected_tets: (k, 4) int64 tets that ``improve`` leaves exactly as they are
            (sorted vertex rows; MMG's ``RequiredTetrahedra``, the VTK field data
            ``jtet:protected_tets``), with their vertices and faces.
        node_sets: tuple of ``NodeSet`` (Abaqus ``*NSET``, Exodus node sets): named
            vertex sets a solver's input refers to, which may overlap. ``improve`` never
            moves their vertices and never renumbers vertices, so each set stays valid.
        point_data: read-only mapping name -> (n,) or (n, k) array of values at the
            vertices (a temperature, a displacement; VTK point arrays). ``improve``
            interpolates them onto the vertices it moves and inserts, linearly in the
            input tet that holds the new position (integer arrays: the value of the
            nearest input vertex); the vertices it leaves in place keep their values.
            Read and written by the VTK, XDMF, TetGen (point attributes), Medit
            (``.sol``) and Exodus (nodal variables) formats.
        cell_data: read-only mapping name -> (m,) or (m, k) array of values per tet (a
            material id, a partition, a density; VTK cell arrays). ``improve`` gives the
            tets it leaves in place their values and every new tet the values of an
            input tet it overlaps (the one holding its centroid, as a rule); it keeps
            the surfaces where an integer array changes value in place, as it keeps
            region interfaces, so integer arrays come through exactly (but arrays of
            distinct ids, which become provenance). Read and written by the VTK, XDMF
            and Exodus (element variables) formats.
        curved_edges: ``CurvedEdges``: the mid-edge nodes of a quadratic input that lie
            off their edge's midpoint (a curved boundary), read with ``load(path,
            linear=True)``, for a quadratic output (``save(..., quadratic=True)``).
            ``improve`` keeps those whose edge and end vertices it leaves in place
            (every one bending a bounding surface: it flips none of them and moves
            none of their ends); ``replace`` with new points drops those whose end
            vertices moved.

    Methods that transform a mesh return a new ``TetMesh``. The constructor checks
    shapes, finiteness and index ranges; use ``TetMesh.from_arrays`` for user input (it
    also handles all-inverted orientation).
    """

    points: Float[np.ndarray, "n 3"]
    tets: Int[np.ndarray, "m 4"]
    region: Int[np.ndarray, " m"] = field(default=None)
    protected_faces: Int[np.ndarray, "k 3"] = field(default=None)
    protected_edges: Int[np.ndarray, "k 2"] = field(default=None)
    protected_face_labels: Int[np.ndarray, " k"] = field(default=None)
    protected_vertices: Int[np.ndarray, " k"] = field(default=None)
    protected_edge_labels: Int[np.ndarray, " k"] = field(default=None)
    protected_vertex_labels: Int[np.ndarray, " k"] = field(default=None)
    label_names: dict = field(default=None)
    periodic: tuple = field(default=None)
    protected_tets: Int[np.ndarray, "k 4"] = field(default=None)
    node_sets: tuple = field(default=None)
    point_data: dict = field(default=None)
    cell_data: dict = field(default=None)
    curved_edges: CurvedEdges = field(default=None)

    def __post_init__(self):
        points = _checked_points(self.points)
        tets = _checked_tets(self.tets, len(points))
        region = self._labels(self.region, len(tets))
        if region.shape != (len(tets),):
            raise MeshInputError(
                f"region must have one label per tet ({len(tets)}), got {region.shape}"
            )
        object.__setattr__(self, "points", _readonly(points))
        object.__setattr__(self, "tets", _readonly(tets))
        object.__setattr__(self, "region", _readonly(region))
        for what, (name, label_name, _) in PROTECTED.items():
            rows, labels = self._labelled(
                getattr(self, name), getattr(self, label_name), what, len(points)
            )
            object.__setattr__(self, name, _readonly(rows))
            object.__setattr__(self, label_name, _readonly(labels))
        object.__setattr__(self, "label_names", _checked_names(self.label_names))
        object.__setattr__(self, "periodic", _checked_periodic(self.periodic, len(points)))
        object.__setattr__(self, "node_sets", _checked_node_sets(self.node_sets, len(points)))
        object.__setattr__(
            self, "point_data", _checked_arrays(self.point_data, len(points), PointData)
        )
        object.__setattr__(self, "cell_data", _checked_arrays(self.cell_data, len(tets), CellData))
        pt = self._entity_array(self.protected_tets, 4, "protected_tets", len(points))
        object.__setattr__(self, "protected_tets", _readonly(pt))
        curved = _checked_curved_edges(self.curved_edges, len(points))
        object.__setattr__(self, "curved_edges", curved)

    def _derive(self, *, tets_checked: int = 0, **changes) -> TetMesh:
        """``replace(**changes)`` checking only what is new.

        This mesh's arrays were checked when it was made and are read-only, so fields not
        in ``changes`` are reused as they are, and the first ``tets_checked`` rows of new
        ``tets`` are trusted to be rows of a checked mesh over the same points, or over
        their first ones when points were appended (a flip step keeps most tets: checking
        only the appended ones keeps its cost with the change, not the mesh). The same
        errors as the constructor otherwise.
        """
        unknown = set(changes) - {f for f in self.__dataclass_fields__}
        if unknown:
            raise TypeError(f"unknown TetMesh field(s): {sorted(unknown)}")
        points = self.points
        if "points" in changes:
            points = _checked_points(changes["points"])
            if len(points) < self.n_points:  # appended points keep old rows in range
                tets_checked = 0
        tets = self.tets
        if "tets" in changes:
            tets = _checked_tets(changes["tets"], len(points), tets_checked)
        elif len(points) < self.n_points:
            tets = _checked_tets(tets, len(points))
        region = self.region
        if "region" in changes or len(tets) != self.n_tets:
            region = self._labels(changes.get("region", region), len(tets))
            if region.shape != (len(tets),):
                raise MeshInputError(
                    f"region must have one label per tet ({len(tets)}), got {region.shape}"
                )
        fields = {"points": points, "tets": tets, "region": region}
        for what, (name, label_name, _) in PROTECTED.items():
            rows, labels = getattr(self, name), getattr(self, label_name)
            if name in changes:  # new entities: new labels, 0 unless given
                rows, labels = self._labelled(
                    changes[name], changes.get(label_name), what, len(points)
                )
            elif label_name in changes or len(points) != self.n_points:
                rows, labels = self._labelled(
                    rows, changes.get(label_name, labels), what, len(points)
                )
            fields[name], fields[label_name] = rows, labels
        out = object.__new__(type(self))
        object.__setattr__(out, "_feature_angle", self._feature_angle)
        for name, value in fields.items():
            object.__setattr__(out, name, _readonly(value))
        names = self.label_names
        if "label_names" in changes:
            names = _checked_names(changes["label_names"])
        object.__setattr__(out, "label_names", names)
        periodic = self.periodic
        if "periodic" in changes or len(points) < self.n_points:
            periodic = _checked_periodic(changes.get("periodic", periodic), len(points))
        object.__setattr__(out, "periodic", periodic)
        node_sets = self.node_sets
        if "node_sets" in changes or len(points) < self.n_points:
            node_sets = _checked_node_sets(changes.get("node_sets", node_sets), len(points))
        object.__setattr__(out, "node_sets", node_sets)
        for name, kind, rows, what in (
            ("point_data", PointData, len(points), "points"),
            ("cell_data", CellData, len(tets), "tets"),
        ):
            data = getattr(self, name)
            if name in changes:
                data = _checked_arrays(changes[name], rows, kind)
            elif data and rows != len(next(iter(data.values()))):
                raise MeshInputError(
                    f"the mesh's {name} has {len(next(iter(data.values())))} rows, the new "
                    f"{what} {rows}: pass {name} for the new {what} too (or {name}=None)"
                )
            object.__setattr__(out, name, data)
        pt = self.protected_tets
        if "protected_tets" in changes or len(points) < self.n_points:
            pt = self._entity_array(
                changes.get("protected_tets", pt), 4, "protected_tets", len(points)
            )
        object.__setattr__(out, "protected_tets", _readonly(pt))
        curved = self.curved_edges
        if "curved_edges" in changes:
            curved = _checked_curved_edges(changes["curved_edges"], len(points))
        elif "points" in changes and len(curved.edges):
            keep = unmoved_edges(curved.edges, self.points, points)
            curved = CurvedEdges(_readonly(curved.edges[keep]), _readonly(curved.points[keep]))
        object.__setattr__(out, "curved_edges", curved)
        if changes and set(changes) <= {"point_data", "cell_data", "curved_edges"}:
            # nothing the topology and the volumes depend on changed: keep what this
            # mesh computed of them (``improve`` strips a mesh's data arrays for its run;
            # not a bare copy: ``_with_feature_angle`` changes the topology's angle)
            for cached in ("topology", "volumes"):
                if cached in self.__dict__:
                    out.__dict__[cached] = self.__dict__[cached]
        return out

    def relabel(self, mapping) -> TetMesh:
        """A copy whose region labels are renamed by ``mapping`` (old label -> new
        label, integers); regions not in it keep theirs, two regions given one label
        become one. The names of Gmsh physical volumes follow their labels (a name moved
        onto a label that keeps a name of its own is dropped). E.g. ``relabel({0: 1})``
        puts the tets of a mesh without region labels into region 1, a physical volume
        of its own in a ``.msh`` output (Gmsh's tag 0 is none).

        Raises:
            MeshInputError: a label is no integer, or the mesh has no tet of an old label.
        """
        try:
            pairs = {int(a): int(b) for a, b in dict(mapping).items()}
        except (TypeError, ValueError):
            raise MeshInputError(
                f"relabel takes integer labels old -> new, got {mapping!r}"
            ) from None
        present = set(np.unique(self.region).tolist())
        missing = sorted(set(pairs) - present)
        if missing:
            raise MeshInputError(
                f"no tet has region {missing[0]} (the regions are "
                f"{', '.join(map(str, sorted(present)))})"
            )
        old = np.array(sorted(pairs), np.int64)
        at = np.searchsorted(old, self.region)
        hit = (at < len(old)) & (old[np.minimum(at, len(old) - 1)] == self.region)
        new = np.array([pairs[o] for o in old.tolist()], np.int64)
        region = np.where(hit, new[np.minimum(at, len(old) - 1)], self.region)
        names = {k: v for k, v in self.label_names.items() if k[0] != 3 or k[1] not in pairs}
        for (dim, label), name in self.label_names.items():
            if dim == 3 and label in pairs:
                names.setdefault((3, pairs[label]), name)
        return self.replace(region=region, label_names=names)

    @staticmethod
    def _labels(region, m: int, what: str = "region labels", item: str = "tet") -> np.ndarray:
        if region is None:
            return np.zeros(m, np.int64)
        r = np.asarray(region).reshape(-1)
        if np.issubdtype(r.dtype, np.integer) or np.issubdtype(r.dtype, np.bool_):
            return r.astype(np.int64)
        if np.issubdtype(r.dtype, np.floating):
            whole = np.isfinite(r) & (r == np.round(r))
            if not whole.all():
                t = int(np.flatnonzero(~whole)[0])
                raise MeshInputError(f"{what} must be integers; {item} {t} has {float(r[t])!r}")
            return r.astype(np.int64)
        raise MeshInputError(f"{what} must be integers, got dtype {r.dtype}")

    @staticmethod
    def _entity_array(a, k: int, name: str, n_points: int, return_index: bool = False):
        """Sorted, distinct vertex tuples (j, k) of ``a``; with ``return_index`` also the
        index in ``a`` of each one's first listing (j,)."""
        if a is None or np.asarray(a).size == 0:
            empty = np.zeros((0, k), np.int64)
            return (empty, np.zeros(0, np.int64)) if return_index else empty
        a = np.asarray(a)
        if a.ndim != 2 or a.shape[1] != k or not np.issubdtype(a.dtype, np.integer):
            raise MeshInputError(
                f"{name} must be an integer array of shape (n, {k}), got {a.shape}"
            )
        if ((a < 0) | (a >= n_points)).any():
            raise MeshInputError(f"{name} holds vertex indices out of range [0, {n_points})")
        a = np.sort(a.astype(np.int64), axis=1)
        rep = (a[:, 1:] == a[:, :-1]).any(axis=1)
        if rep.any():
            raise MeshInputError(f"{name} entry {a[rep][0].tolist()} repeats a vertex")
        return np.unique(a, axis=0, return_index=return_index)

    @classmethod
    def _labelled(cls, rows, labels, what: str, n_points: int) -> tuple[np.ndarray, np.ndarray]:
        """Protected faces / edges / vertices (``what``: one of ``PROTECTED``) as sorted,
        distinct vertex rows (k, 3) / (k, 2) / ids (k,), and their labels (k,) (0 unless
        given); an entity listed twice keeps the label it is first listed with."""
        name, label_name, j = PROTECTED[what]
        if rows is None or np.asarray(rows).size == 0:
            if labels is not None and np.asarray(labels).size:
                raise MeshInputError(f"{label_name} given without {name}")
            return np.zeros((0, j) if j > 1 else 0, np.int64), np.zeros(0, np.int64)
        raw = np.asarray(rows)
        if j == 1:  # vertex ids: a 1-D array
            if raw.ndim != 1 or not np.issubdtype(raw.dtype, np.integer):
                raise MeshInputError(
                    f"{name} must be a 1-D integer array of vertex ids, got shape "
                    f"{raw.shape} of {raw.dtype}"
                )
            raw = raw.reshape(-1, 1)
        unique, first = cls._entity_array(raw, j, name, n_points, return_index=True)
        if j == 1:
            unique = unique[:, 0]
        if labels is None:
            return unique, np.zeros(len(unique), np.int64)
        lab = np.asarray(labels).reshape(-1)
        if lab.shape != (len(raw),):
            raise MeshInputError(
                f"{label_name} must have one label per protected {what} "
                f"({len(raw)}), got {np.shape(labels)}"
            )
        return unique, cls._labels(lab, len(raw), f"protected {what} labels", f"protected {what}")[
            first
        ]

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_arrays(
        cls,
        points,
        tets,
        region=None,
        protected_faces=None,
        protected_edges=None,
        protected_face_labels=None,
        protected_vertices=None,
        protected_edge_labels=None,
        protected_vertex_labels=None,
        *,
        label_names=None,
        periodic=None,
        protected_tets=None,
        node_sets=None,
        point_data=None,
        cell_data=None,
        curved_edges=None,
        source: str = "input",
    ) -> TetMesh:
        """Build a mesh from user arrays, fixing a globally reversed orientation.

        If every non-degenerate tet is negatively oriented the whole mesh is reoriented
        (with a warning). If both orientations occur and the tets' vertex orders are
        inconsistent (two tets sharing a face induce the same orientation on it), but
        reordering every negative tet makes them consistent, those tets were listed inside
        out (e.g. raw ``scipy.spatial.Delaunay`` simplices) and are reordered, with a
        warning. Otherwise a mesh mixing both orientations is kept as it is: its negative
        tets are truly inverted (reported by ``is_valid()``; edge removal can repair some).
        """
        mesh = cls(
            points, tets, region, protected_faces, protected_edges, protected_face_labels,
            protected_vertices, protected_edge_labels, protected_vertex_labels, label_names,
            periodic, protected_tets, node_sets, point_data, cell_data, curved_edges,
        )  # fmt: skip
        vol = _orient_volumes6(mesh.points, mesh.tets)
        neg, pos = int((vol < 0).sum()), int((vol > 0).sum())
        if neg and not pos:
            warnings.warn(
                f"{source}: all {neg} tets are negatively oriented; reoriented to jtet's "
                "(VTK) convention of positive volume",
                stacklevel=2,
            )
            t = mesh.tets[:, [1, 0, 2, 3]]
            mesh = mesh.replace(tets=t)
        elif neg and len(face_conflicts(mesh.tets, mesh.n_points)[1]):
            # Mixed orientation with inconsistent vertex orders (e.g. the simplices of
            # scipy.spatial.Delaunay): if listing every negative tet the other way round
            # makes the orders consistent, the tets were just listed inside out.
            t = mesh.tets.copy()
            t[vol < 0] = t[vol < 0][:, [1, 0, 2, 3]]
            mis = face_conflicts(t, mesh.n_points)[1]
            for _ in range(8):  # flat tets have no sign: follow their neighbours' order
                flat = vol[mis] == 0
                flip = np.unique(mis[flat & ~flat[:, ::-1]])
                if len(mis) == 0 or len(flip) == 0:
                    break
                t[flip] = t[flip][:, [1, 0, 2, 3]]
                mis = face_conflicts(t, mesh.n_points)[1]
            if len(mis) == 0:
                warnings.warn(
                    f"{source}: {neg} of {len(vol)} tets were listed in the opposite vertex "
                    "order to their neighbours (negative volume); reordered to jtet's (VTK) "
                    "convention of positive volume",
                    stacklevel=2,
                )
                mesh = mesh.replace(tets=t)
            else:
                warnings.warn(
                    f"{source}: the tets' vertex orders are inconsistent (tets sharing a face "
                    "on the same side of it) and reordering the negative ones does not fix "
                    "it; jtet.improve will refuse this mesh",
                    stacklevel=2,
                )
        elif neg:
            warnings.warn(
                f"{source}: {neg} of {len(vol)} tets are inverted (negative volume); "
                "jtet keeps them and tries to repair them by edge removal",
                stacklevel=2,
            )
        return mesh

    @classmethod
    def from_pyvista(cls, grid, *, source: str = "pyvista grid") -> TetMesh:
        """Build a mesh from a ``pyvista.UnstructuredGrid`` of tetra cells.

        Reads a ``region`` cell array when present (also ``gmsh:physical``,
        ``medit:ref``, ``CellEntityIds`` as written by meshio / VTK readers).
        """
        from ._io import grid_extras, grid_to_arrays, unstructured_grid

        grid = unstructured_grid(grid, source)
        arrays = grid_to_arrays(grid, source)
        return cls.from_arrays(*arrays, **grid_extras(grid, source), source=source)

    def replace(self, **changes) -> TetMesh:
        """A copy with some fields replaced; the constructor's checks run on the replaced
        fields (and on whatever depends on them: the tets again for new points of another
        count, the labels for tets of another count)."""
        return self._derive(**changes)

    # ------------------------------------------------------------------ properties
    @property
    def has_curved_edges(self) -> bool:
        """Whether the mesh holds mid-edge nodes off their edges' midpoints
        (``curved_edges``)."""
        return len(self.curved_edges.edges) > 0

    @property
    def n_points(self) -> int:
        return len(self.points)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    @functools.cached_property
    def volumes(self) -> np.ndarray:
        """(m,) signed volumes."""
        return _orient_volumes6(self.points, self.tets) / 6.0

    # Degrees: two subfacets of one surface bent by more than this meet at a subsegment
    # (``Topology.build``). Not a field: ``improve`` sets it on its working copy of the
    # mesh (``_with_feature_angle``), and every mesh derived from that copy (flip steps,
    # smoothing) keeps it, so their topologies, full or incremental, agree.
    _feature_angle = 0.0

    def _with_feature_angle(self, feature_angle: float) -> TetMesh:
        """This mesh if its topology is built with ``feature_angle``, else a copy (same
        read-only arrays, no cached topology) whose topology will be."""
        if float(feature_angle) == self._feature_angle:
            return self
        out = self._derive()
        object.__setattr__(out, "_feature_angle", float(feature_angle))
        return out

    @functools.cached_property
    def topology(self):
        """Vectorized adjacency: faces, edges, rings, boundary, protection (cached)."""
        from ._topology import Topology

        return Topology.build(self, self._feature_angle)

    def _part(self, sel: np.ndarray) -> tuple[TetMesh, np.ndarray, np.ndarray]:
        """The tets where ``sel`` (m,) is True as a mesh of their own (same feature
        angle), with the protected faces, edges and vertices that are faces, edges and
        vertices of those tets, and the curved edges between their vertices. Returns
        (submesh, verts, faces_in): ``verts`` (v,) maps the submesh's vertex ids to this
        mesh's (sorted), ``faces_in`` (k,) marks the protected faces taken."""
        from ._topology import TET_EDGES, TET_FACES, match_rows

        tets = self.tets[sel]
        verts = np.unique(tets)
        local = np.full(self.n_points, -1, np.int64)
        local[verts] = np.arange(len(verts))
        n = self.n_points
        faces = np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1)
        edges = np.sort(tets[:, TET_EDGES].reshape(-1, 2), axis=1)
        faces_in = match_rows(faces, self.protected_faces, n) >= 0
        edges_in = match_rows(edges, self.protected_edges, n) >= 0
        pv_local = local[self.protected_vertices]
        pv_in = pv_local >= 0
        protected = tets[self.protected_tet_mask()[sel]] if len(self.protected_tets) else tets[:0]
        curved = self.curved_edges
        curved_in = (local[curved.edges] >= 0).all(axis=1)
        sub = TetMesh(
            self.points[verts],
            local[tets],
            self.region[sel],
            protected_faces=local[self.protected_faces[faces_in]],
            protected_edges=local[self.protected_edges[edges_in]],
            protected_face_labels=self.protected_face_labels[faces_in],
            protected_vertices=pv_local[pv_in],
            protected_edge_labels=self.protected_edge_labels[edges_in],
            protected_vertex_labels=self.protected_vertex_labels[pv_in],
            label_names=self.label_names,
            protected_tets=local[protected],
            curved_edges=(local[curved.edges[curved_in]], curved.points[curved_in]),
        )
        return sub._with_feature_angle(self._feature_angle), verts, faces_in

    def protected_tet_mask(self) -> np.ndarray:
        """(m,) bool: the tets listed in ``protected_tets``. ``MeshInputError`` when one
        of those is no tet of this mesh."""
        from ._topology import match_rows

        mask = np.zeros(self.n_tets, bool)
        if not len(self.protected_tets):
            return mask
        at = match_rows(self.tets, self.protected_tets, self.n_points)
        if (at < 0).any():
            bad = self.protected_tets[at < 0]
            raise MeshInputError(
                f"{len(bad)} protected tet(s) are no tets of the mesh (first: {bad[0].tolist()})"
            )
        mask[at] = True
        return mask

    def _with_pinned(self, edges: np.ndarray, vertices: np.ndarray, **changes) -> TetMesh:
        """This mesh with ``edges`` (k, 2) and ``vertices`` (j,) protected too (label
        ``PIN_LABEL``; an entity protected already keeps its own), and ``changes``: a run
        then removes none of these edges and moves none of these vertices. Runs pin what
        must come back exactly (a submesh's cut, periodic surfaces) and give the result
        its own protected entities back."""
        # listed after the mesh's own: an entity listed twice keeps its first label
        return self.replace(
            protected_edges=np.concatenate([self.protected_edges, edges]),
            protected_edge_labels=np.concatenate(
                [self.protected_edge_labels, np.full(len(edges), PIN_LABEL)]
            ),
            protected_vertices=np.concatenate([self.protected_vertices, vertices]),
            protected_vertex_labels=np.concatenate(
                [self.protected_vertex_labels, np.full(len(vertices), PIN_LABEL)]
            ),
            **changes,
        )

    def vertex_kinds(self, vids: np.ndarray) -> np.ndarray:
        """(v,) int8 kinds (``_topology`` FREE, SURFACE, SEGMENT, CORNER) of the vertices
        ``vids`` (v,), equal to ``topology.vertex_kind[vids]``. Without a cached topology,
        from the topology of their stars alone: a vertex's kind depends only on the faces
        and edges at it, and every tet holding one of those is in its star (a whole-mesh
        build costs ~35 ms at 33k tets, ~2 s at 1M)."""
        from ._topology import corner_counts

        vids = np.asarray(vids, np.int64)
        if "topology" in self.__dict__:
            return self.topology.vertex_kind[vids]
        want = np.zeros(self.n_points, bool)
        want[vids] = True
        stars = corner_counts(want, self.tets) > 0
        kinds = np.zeros(len(vids), np.int8)  # FREE: a vertex in no tet is in no face
        if stars.any():
            sub, verts, _ = self._part(stars)
            pos = np.minimum(np.searchsorted(verts, vids), len(verts) - 1)
            found = verts[pos] == vids
            kinds[found] = sub.topology.vertex_kind[pos[found]]
        return kinds

    def quality(self, measure: str = "min_sine") -> np.ndarray:
        """(m,) quality of every tet under ``measure`` (see ``jtet.MEASURES``)."""
        from ._quality import tet_quality

        return tet_quality(self.points, self.tets, measure)

    def is_valid(self):
        """Full (expensive) validity check; returns a ``ValidityReport``."""
        from ._validity import check_validity

        return check_validity(self)

    def to_pyvista(self, cell_data: dict | None = None):
        """A ``pyvista.UnstructuredGrid`` with a ``region`` cell array (plus ``cell_data``)."""
        from ._io import mesh_to_grid

        return mesh_to_grid(self, cell_data)

    def __repr__(self) -> str:
        nreg = len(np.unique(self.region))
        pv = len(self.protected_vertices)
        return (
            f"TetMesh({self.n_points} points, {self.n_tets} tets, {nreg} region(s), "
            f"{len(self.protected_faces)} protected faces, {len(self.protected_edges)} protected edges"
            + (f", {pv} protected vertices" if pv else "")
            + (f", {len(self.protected_tets)} protected tets" if len(self.protected_tets) else "")
            + (f", {len(self.periodic)} periodic links" if self.periodic else "")
            + (f", {len(self.node_sets)} node set(s)" if self.node_sets else "")
            + (f", point data {', '.join(self.point_data)}" if self.point_data else "")
            + (f", cell data {', '.join(self.cell_data)}" if self.cell_data else "")
            + (f", {len(self.curved_edges.edges)} curved edges" if self.has_curved_edges else "")
            + ")"
        )
