"""XDMF mesh files (``.xdmf`` with its heavy data in ``.h5``): what dolfinx and ParaView read.

``write_xdmf`` writes the layout of dolfinx's own ``XDMFFile.write_mesh`` and
``write_meshtags``: a grid ``mesh`` (tets and points; the ``region`` and the per-tet arrays
as cell attributes, for ParaView), then one grid per kind of tag holding the entities and
their labels as dolfinx meshtags: ``cell_tags`` (every tet, its region), ``facet_tags``
(the protected faces), ``edge_tags`` and ``vertex_tags`` (the protected edges and
vertices). Every grid points at the same geometry dataset, and ``cell_tags`` at the same
topology dataset, so the file holds the points and tets once. The names of Gmsh physical
groups go to an ``Information`` element, the protected tets to a ``protected`` attribute.

``read_xdmf`` reads that layout, dolfinx's (``tests/data/dolfinx_cube.xdmf`` was written by
dolfinx 0.5.2: its tag grids list cells in their own order, matched to the mesh's by
their vertices), meshio's and VTK's (one grid, ``Mixed`` topology when it has several
cell types), with heavy data inline (``XML``), in HDF5 files (``HDF``) or raw
(``Binary``). Temporal collections give their first time step. It runs in a forked child
on Linux (``_forked``) whose memory is capped: a crash of the HDF5 library on a damaged
file, or a header claiming terabytes, becomes an error.
"""

from __future__ import annotations

import json
import math
import re
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ._errors import MeshFileError, MeshInputError

#: the heavy data of ``path.xdmf`` goes to ``path.h5``
HEAVY_SUFFIX = ".h5"
#: names of the tag grids, by dimension of their entities
TAG_GRIDS = {3: "cell_tags", 2: "facet_tags", 1: "edge_tags", 0: "vertex_tags"}
LABEL_NAMES_INFO = "jtet:label_names"
PROTECTED_ATTRIBUTE = "protected"

# XDMF topology names (lower case; XDMF 2 and 3 spellings) -> meshio cell type
_TOPOLOGIES = {
    "polyvertex": "vertex",
    "polyline": "line",
    "triangle": "triangle",
    "quadrilateral": "quad",
    "tetrahedron": "tetra",
    "pyramid": "pyramid",
    "wedge": "wedge",
    "hexahedron": "hexahedron",
    "edge_3": "line3",
    "triangle_6": "triangle6",
    "tri_6": "triangle6",
    "quadrilateral_8": "quad8",
    "quad_8": "quad8",
    "quadrilateral_9": "quad9",
    "quad_9": "quad9",
    "tetrahedron_10": "tetra10",
    "tet_10": "tetra10",
    "pyramid_13": "pyramid13",
    "wedge_15": "wedge15",
    "wedge_18": "wedge18",
    "hexahedron_20": "hexahedron20",
    "hex_20": "hexahedron20",
    "hexahedron_24": "hexahedron24",
    "hex_24": "hexahedron24",
    "hexahedron_27": "hexahedron27",
    "hex_27": "hexahedron27",
}
# cell type ids of a Mixed topology (the XDMF specification's) -> (meshio type, nodes);
# nodes None: the id is followed by the cell's node count (poly-vertex, poly-line)
_MIXED = {
    1: ("vertex", None),
    2: ("line", None),
    4: ("triangle", 3),
    5: ("quad", 4),
    6: ("tetra", 4),
    7: ("pyramid", 5),
    8: ("wedge", 6),
    9: ("hexahedron", 8),
    34: ("line3", 3),
    35: ("quad9", 9),
    36: ("triangle6", 6),
    37: ("quad8", 8),
    38: ("tetra10", 10),
    39: ("pyramid13", 13),
    40: ("wedge15", 15),
    41: ("wedge18", 18),
    48: ("hexahedron20", 20),
    49: ("hexahedron24", 24),
    50: ("hexahedron27", 27),
}
_NODES = {
    "vertex": 1,
    "line": 2,
    "triangle": 3,
    "quad": 4,
    "tetra": 4,
    "pyramid": 5,
    "wedge": 6,
    "hexahedron": 8,
}
_NODES.update({t: k for t, k in _MIXED.values() if k is not None})
_DIMENSION = {"vertex": 0, "line": 1, "line3": 1, "triangle": 2, "triangle6": 2}
_DIMENSION.update({t: 2 for t in ("quad", "quad8", "quad9")})
_NUMBER_TYPES = {"float": "f", "int": "i", "uint": "u", "char": "i", "uchar": "u"}


def _dimension(cell_type: str) -> int:
    return _DIMENSION.get(cell_type, 3)


# ---------------------------------------------------------------------------------------
# writing


def _number_type(a: np.ndarray) -> dict:
    kind = {"f": "Float", "i": "Int", "u": "UInt"}[a.dtype.kind]
    if a.dtype.itemsize == 1 and kind in ("Int", "UInt"):
        kind = "Char" if kind == "Int" else "UChar"
    return {"NumberType": kind, "Precision": str(a.dtype.itemsize)}


def write_xdmf(mesh, xdmf: Path, heavy: Path, heavy_name: str, cell_data: dict, quad=None) -> None:
    """Write ``mesh`` as the XDMF file ``xdmf`` whose heavy data goes to the HDF5 file
    ``heavy``, which ``xdmf`` names ``heavy_name`` (relative to its directory: the final
    name, while both are written under temporary names). ``cell_data``: name -> (m, ...)
    per-tet arrays, written as cell attributes of the ``mesh`` grid.

    With ``quad`` (``_quadratic.quadratic_mesh(mesh)``) the cells are quadratic:
    ``Tetrahedron_10`` over all the nodes, the facet tags' ``Triangle_6`` and the edge
    tags' ``Edge_3``, in VTK's node order (XDMF's), and point data on every node."""
    import h5py

    points, tets, point_data = mesh.points, mesh.tets, mesh.point_data
    if quad is not None:
        points, tets, point_data = quad.points, quad.tets, quad.point_data
    tet_topology = ("Tetrahedron", 4) if quad is None else ("Tetrahedron_10", 10)
    datasets: dict[str, np.ndarray] = {
        "Mesh/mesh/geometry": np.asarray(points, np.float64),
        "Mesh/mesh/topology": np.asarray(tets, np.int64),
        "Mesh/mesh/region": np.asarray(mesh.region, np.int64),
    }
    root = ET.Element("Xdmf", {"Version": "3.0"})
    domain = ET.SubElement(root, "Domain")

    def item(parent, key: str) -> None:
        a = datasets[key]
        attrs = {"Dimensions": " ".join(map(str, a.shape)), **_number_type(a), "Format": "HDF"}
        ET.SubElement(parent, "DataItem", attrs).text = f"{heavy_name}:/{key}"

    def grid(name: str, topology: str, nodes: int, cells_key: str) -> ET.Element:
        g = ET.SubElement(domain, "Grid", {"Name": name, "GridType": "Uniform"})
        count = len(datasets[cells_key])
        topo = ET.SubElement(
            g,
            "Topology",
            {
                "TopologyType": topology,
                "NumberOfElements": str(count),
                "NodesPerElement": str(nodes),
            },
        )
        item(topo, cells_key)
        item(ET.SubElement(g, "Geometry", {"GeometryType": "XYZ"}), "Mesh/mesh/geometry")
        return g

    def attribute(g: ET.Element, name: str, key: str, center: str = "Cell") -> None:
        a = datasets[key]
        kind = "Scalar" if a.ndim == 1 else "Vector" if a.shape[1:] == (3,) else "Matrix"
        attrs = {"Name": name, "AttributeType": kind, "Center": center}
        item(ET.SubElement(g, "Attribute", attrs), key)

    main = grid("mesh", *tet_topology, "Mesh/mesh/topology")
    attribute(main, "region", "Mesh/mesh/region")
    mask = mesh.protected_tet_mask()
    if mask.any():
        datasets["Mesh/mesh/protected"] = mask.astype(np.uint8)
        attribute(main, PROTECTED_ATTRIBUTE, "Mesh/mesh/protected")
    # dataset names by position: an array's name may hold "/"; jtet's quality arrays win
    for i, (name, values) in enumerate({**mesh.cell_data, **cell_data}.items()):
        a = np.asarray(values)
        a = a.astype(np.uint8) if a.dtype == bool else a  # HDF5 has no bool type
        datasets[f"Mesh/mesh/cell_data/{i}"] = a.reshape(len(a), -1) if a.ndim > 2 else a
        attribute(main, name, f"Mesh/mesh/cell_data/{i}")
    for i, (name, values) in enumerate(point_data.items()):
        datasets[f"Mesh/mesh/point_data/{i}"] = np.asarray(values)
        attribute(main, name, f"Mesh/mesh/point_data/{i}", "Node")
    cell_tags = grid(TAG_GRIDS[3], *tet_topology, "Mesh/mesh/topology")
    attribute(cell_tags, TAG_GRIDS[3], "Mesh/mesh/region")
    faces, edges = mesh.protected_faces, mesh.protected_edges
    face_topology, edge_topology = "Triangle", "Polyline"
    if quad is not None:
        faces, edges = quad.cells(faces), quad.cells(edges)
        face_topology, edge_topology = "Triangle_6", "Edge_3"
    for dim, cells, labels, topology in (
        (2, faces, mesh.protected_face_labels, face_topology),
        (1, edges, mesh.protected_edge_labels, edge_topology),
        (
            0,
            np.asarray(mesh.protected_vertices).reshape(-1, 1),
            mesh.protected_vertex_labels,
            "Polyvertex",
        ),
    ):
        if not len(cells):
            continue
        name = TAG_GRIDS[dim]
        datasets[f"MeshTags/{name}/topology"] = np.asarray(cells, np.int64)
        datasets[f"MeshTags/{name}/Values"] = np.asarray(labels, np.int64)
        g = grid(name, topology, cells.shape[1], f"MeshTags/{name}/topology")
        attribute(g, name, f"MeshTags/{name}/Values")
    if len(mesh.label_names):
        names = [[dim, label, name] for (dim, label), name in sorted(mesh.label_names.items())]
        ET.SubElement(domain, "Information", {"Name": LABEL_NAMES_INFO, "Value": json.dumps(names)})
    with h5py.File(heavy, "w") as f:
        for key, a in datasets.items():
            f.create_dataset(key, data=a)
    ET.indent(root, space="  ")
    text = '<?xml version="1.0"?>\n<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>\n'
    text += ET.tostring(root, encoding="unicode") + "\n"
    xdmf.write_text(text, encoding="utf-8")


# ---------------------------------------------------------------------------------------
# reading


def _parse(path: Path, source: str) -> ET.Element:
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise MeshFileError(f"{source}: not a readable XDMF file (XML: {e})") from None
    except OSError as e:
        raise MeshFileError(f"{source}: cannot read the file ({e.strerror or e})") from None
    if root.tag != "Xdmf" or root.find("Domain") is None:
        raise MeshFileError(f"{source}: not a readable XDMF file (no Xdmf / Domain element)")
    return root


def _uniform_grids(parent: ET.Element):
    """The uniform grids under ``parent``, in document order: the children of spatial
    collections and trees, the first time step of a temporal collection."""
    for g in parent.findall("Grid"):
        kind = (g.get("GridType") or "Uniform").lower()
        if kind == "uniform":
            yield g
        elif kind in ("collection", "tree"):
            if (g.get("CollectionType") or "").lower() == "temporal":
                first = next(_uniform_grids(g), None)
                if first is not None:
                    yield first
            else:
                yield from _uniform_grids(g)


def _part(g: ET.Element, tag: str, domain: ET.Element) -> ET.Element | None:
    """The ``Topology`` / ``Geometry`` element of grid ``g``: its own, or the one an
    XInclude in it points at: meshio's time steps name the grid that holds them
    (``xpointer(//Grid[@Name="mesh"]/*[self::Topology or self::Geometry])``), dolfinx's
    tag grids take the geometry of the first grid (``xpointer(/Xdmf/Domain/Grid/Geometry)``).
    Other XPointer expressions are not followed."""
    own = g.find(tag)
    if own is not None:
        return own
    for inc in g:
        if not (isinstance(inc.tag, str) and inc.tag.endswith("}include")):
            continue
        pointer = inc.get("xpointer") or ""
        if tag not in pointer and "self::" not in pointer:
            continue
        named = re.search(r"@Name=[\"']([^\"']*)[\"']", pointer)
        for other in domain.iter("Grid"):
            if other is g or (named and other.get("Name") != named.group(1)):
                continue
            if other.find(tag) is not None:
                return other.find(tag)
    return None


def _hdf_parts(text: str) -> tuple[str, str] | None:
    """(file, /dataset) of an HDF data item's text ``FILE:/DATASET``, or None."""
    at = text.find(":/")
    return None if at < 0 else (text[:at], text[at + 1 :])


def heavy_files(path: Path) -> list[Path]:
    """The files holding the heavy data of the XDMF file ``path`` (HDF5 and raw binary
    files its data items name), as paths; [] when it cannot be parsed."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError):
        return []
    out = []
    for item in root.iter("DataItem"):
        fmt = (item.get("Format") or "XML").upper()
        if fmt in ("HDF", "BINARY") and item.text:
            name = item.text.strip()
            if fmt == "HDF":
                name = (_hdf_parts(name) or (name, ""))[0]
            p = path.parent / name
            if p not in out:
                out.append(p)
    return out


class _Data:
    """Reads data items, keeping each HDF5 file open once and each dataset read once
    (jtet's and dolfinx's tag grids point at the mesh's geometry and topology)."""

    def __init__(self, base: Path, source: str):
        self.base, self.source = base, source
        self.files: dict[Path, object] = {}
        self.read_before: dict[tuple[Path, str], np.ndarray] = {}

    def close(self) -> None:
        for f in self.files.values():
            f.close()

    def fail(self, msg: str) -> MeshFileError:
        return MeshFileError(f"{self.source}: {msg}")

    def read(self, item: ET.Element | None, what: str) -> np.ndarray:
        if item is None:
            raise self.fail(f"{what} has no DataItem")
        if (
            item.get("Reference") is not None
            or (item.get("ItemType") or "Uniform").lower() != "uniform"
        ):
            kind = item.get("ItemType") or "Reference"
            raise self.fail(f"{what}: data items of type {kind} are not supported")
        try:
            dims = tuple(int(v) for v in (item.get("Dimensions") or "").split())
        except ValueError:
            raise self.fail(f"{what}: bad Dimensions {item.get('Dimensions')!r}") from None
        if any(d < 0 for d in dims):
            raise self.fail(f"{what}: bad Dimensions {item.get('Dimensions')!r}")
        fmt = (item.get("Format") or "XML").upper()
        number = (item.get("NumberType") or item.get("DataType") or "Float").lower()
        if number not in _NUMBER_TYPES:
            raise self.fail(f"{what}: unknown NumberType {number!r}")
        precision = item.get("Precision") or ("1" if "char" in number else "4")
        if precision not in ("1", "2", "4", "8"):
            raise self.fail(f"{what}: bad Precision {precision!r}")
        if number == "float" and precision == "1":
            raise self.fail(f"{what}: bad Precision 1 for Float numbers")
        dtype = np.dtype(f"{_NUMBER_TYPES[number]}{precision}")
        text = (item.text or "").strip()
        if fmt == "XML":
            try:
                a = np.array(text.split(), dtype=np.float64 if dtype.kind == "f" else np.int64)
            except ValueError:
                raise self.fail(f"{what}: inline data that are not numbers") from None
        elif fmt == "HDF":
            a = self._hdf(text, what, dims)
        elif fmt == "BINARY":
            a = self._binary(item, text, dtype, dims, what)
        else:
            raise self.fail(f"{what}: data format {fmt!r} is not supported (XML, HDF, Binary)")
        if dims and a.size != math.prod(dims):
            raise self.fail(f"{what}: {a.size} values for Dimensions {' '.join(map(str, dims))}")
        return a.reshape(dims) if dims else a.reshape(-1)

    def _hdf(self, text: str, what: str, dims: tuple) -> np.ndarray:
        import h5py

        parts = _hdf_parts(text)
        if parts is None:
            raise self.fail(f"{what}: HDF data item {text!r} is not FILE:/DATASET")
        name, dataset = parts
        path = self.base / name
        if path not in self.files:
            if not path.is_file():
                raise self.fail(f"{what}: the HDF5 file {name} is missing")
            try:
                # no HDF5 file lock: reading needs none, and taking one fails on
                # file systems without locks (NFS, some containers)
                self.files[path] = h5py.File(path, "r", locking=False)
            except OSError as e:
                raise self.fail(f"{name}: not a readable HDF5 file ({e})") from None
        if (path, dataset) in self.read_before:
            return self.read_before[path, dataset]
        f = self.files[path]
        try:
            data = f[dataset]
            if not isinstance(data, h5py.Dataset):
                raise KeyError(dataset)
            # the size the file claims is checked before anything is read: a damaged
            # header may claim terabytes
            if dims and data.size != math.prod(dims):
                raise self.fail(
                    f"{what}: dataset {dataset} of {name} holds {data.size} values for "
                    f"Dimensions {' '.join(map(str, dims))}"
                )
            a = data[()]
        except MeshFileError:
            raise
        except KeyError:
            raise self.fail(f"{what}: no dataset {dataset} in {name}") from None
        except MemoryError:
            raise self.fail(f"{what}: dataset {dataset} of {name} is too large to read") from None
        except (OSError, ValueError, TypeError) as e:
            raise self.fail(f"{what}: dataset {dataset} of {name} is unreadable ({e})") from None
        a = np.asarray(a)
        if a.dtype.kind not in "fiub":
            raise self.fail(f"{what}: dataset {dataset} of {name} holds no numbers")
        a.flags.writeable = False  # shared by every data item naming it
        self.read_before[path, dataset] = a
        return a

    def _binary(self, item, text: str, dtype, dims, what: str) -> np.ndarray:
        path = self.base / text
        if not path.is_file():
            raise self.fail(f"{what}: the binary data file {text} is missing")
        endian = (item.get("Endian") or "Native").lower()
        if endian in ("big", "little"):
            dtype = dtype.newbyteorder(">" if endian == "big" else "<")
        count = math.prod(dims) if dims else -1
        try:
            seek = int(item.get("Seek") or 0)
            a = np.fromfile(path, dtype=dtype, count=count, offset=seek)
        except (ValueError, OSError) as e:
            raise self.fail(f"{what}: binary data file {text} is unreadable ({e})") from None
        return a.astype(dtype.newbyteorder("="))


def _mixed_cells(flat: np.ndarray, what: str, fail) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Split a ``Mixed`` topology (per cell: type id, [node count,] nodes) into
    (meshio type, (k, nodes) cells, (k,) positions of those cells in the grid) per run
    of cells of one type and size. A run is found by checking its stride's type ids in
    chunks that double, so a file of a few long runs costs a few NumPy passes."""
    flat = np.asarray(flat, np.int64).reshape(-1)
    out, pos, index, n = [], 0, 0, len(flat)
    while pos < n:
        kind = int(flat[pos])
        if kind not in _MIXED:
            raise fail(f"{what}: unknown cell type {kind} in a Mixed topology")
        cell_type, nodes = _MIXED[kind]
        head = 1
        if nodes is None:
            if pos + 1 >= n:
                raise fail(f"{what}: a Mixed topology cut short")
            nodes, head = int(flat[pos + 1]), 2
            if nodes != (1 if kind == 1 else 2):
                raise fail(f"{what}: a poly-{'vertex' if kind == 1 else 'line'} of {nodes} nodes")
        stride = head + nodes
        count, chunk = 0, 64
        while True:
            starts = pos + (count + np.arange(chunk)) * stride
            starts = starts[starts < n]
            ok = flat[starts] == kind
            if head == 2:
                ok &= (starts + 1 < n) & (flat[np.minimum(starts + 1, n - 1)] == nodes)
            run = len(ok) if ok.all() else int(np.argmin(ok))
            count += run
            if run < chunk or not len(starts):
                break
            chunk *= 2
        end = pos + count * stride
        if end > n:
            raise fail(f"{what}: a Mixed topology cut short")
        block = flat[pos:end].reshape(count, stride)[:, head:]
        out.append((cell_type, block, index + np.arange(count)))
        pos, index = end, index + count
    return out


def _grid_cells(g: ET.Element, data: _Data, what: str, domain: ET.Element):
    """The cells of one uniform grid: [(meshio type, (k, nodes) ids, (k,) positions)]."""
    topo = _part(g, "Topology", domain)
    if topo is None:
        raise data.fail(f"{what} has no Topology")
    name = (topo.get("TopologyType") or topo.get("Type") or "").lower()
    flat = data.read(topo.find("DataItem"), f"{what} topology")
    if flat.dtype.kind == "f" and not (np.isfinite(flat).all() and (flat == np.round(flat)).all()):
        raise MeshInputError(f"{data.source}: {what} holds node ids that are not integers")
    if name == "mixed":
        return _mixed_cells(flat, what, data.fail)
    cell_type = _TOPOLOGIES.get(name)
    if cell_type is None:
        raise data.fail(f"{what}: topology {name or '(none)'!r} is not supported")
    nodes = _NODES[cell_type]
    per = topo.get("NodesPerElement")
    if cell_type in ("vertex", "line") and per is not None:
        if not per.strip().isdigit():
            raise data.fail(f"{what}: bad NodesPerElement {per!r}")
        nodes = int(per)
        if nodes != _NODES[cell_type]:
            return []  # poly-lines / poly-vertices of several nodes: no edges / vertices
    if flat.size % nodes:
        raise data.fail(f"{what}: {flat.size} node ids are no whole number of {name} cells")
    cells = np.asarray(flat).reshape(-1, nodes)
    return [(cell_type, cells.astype(np.int64), np.arange(len(cells)))]


def _points(g: ET.Element, data: _Data, what: str, domain: ET.Element) -> np.ndarray | None:
    geo = _part(g, "Geometry", domain)
    if geo is None:
        return None
    kind = (geo.get("GeometryType") or geo.get("Type") or "XYZ").upper()
    items = geo.findall("DataItem")
    if kind == "XYZ":
        pts = data.read(items[0] if items else None, f"{what} geometry")
        if pts.size % 3:
            raise MeshInputError(f"{data.source}: {what}: {pts.size} coordinates for XYZ points")
        return np.asarray(pts, np.float64).reshape(-1, 3)
    if kind == "X_Y_Z" and len(items) == 3:
        cols = [np.asarray(data.read(i, f"{what} geometry"), np.float64).reshape(-1) for i in items]
        if len({len(c) for c in cols}) != 1:
            raise MeshInputError(f"{data.source}: {what}: X, Y and Z of different lengths")
        return np.column_stack(cols)
    if kind in ("XY", "X_Y"):
        raise MeshInputError(f"{data.source}: the points are 2-D; jtet needs a 3-D tet mesh")
    raise data.fail(f"{what}: geometry type {kind!r} is not supported (XYZ, X_Y_Z)")


def _attributes(g: ET.Element, data: _Data, what: str, n_cells: int) -> dict:
    """Cell attributes of a grid with one value per cell: name -> (n_cells,) array."""
    out = {}
    for a in g.findall("Attribute"):
        if (a.get("Center") or "Node").lower() != "cell":
            continue
        name = a.get("Name") or ""
        values = np.asarray(data.read(a.find("DataItem"), f"{what} attribute {name!r}"))
        if values.ndim == 2 and values.shape[1] == 1:
            values = values[:, 0]
        if values.ndim == 1 and len(values) == n_cells and name not in out:
            out[name] = values
    return out


def _node_attributes(g: ET.Element, data: _Data, what: str, n: int, center: str = "node") -> dict:
    """Node (or, ``center`` "cell", cell) attributes of a grid of numbers, one value or
    one row of values per point (cell): name -> (n,) or (n, k) array
    (``TetMesh.point_data``, ``TetMesh.cell_data``)."""
    out = {}
    for a in g.findall("Attribute"):
        name = a.get("Name") or ""
        if (a.get("Center") or "Node").lower() != center or not name or name in out:
            continue
        values = np.asarray(data.read(a.find("DataItem"), f"{what} attribute {name!r}"))
        if values.dtype.kind not in "biuf" or values.size % max(n, 1):
            continue
        values = values.reshape(n, -1)
        out[name] = values[:, 0] if values.shape[1] == 1 else values
    return out


def _read_xdmf_arrays(path: Path, source: str) -> dict:
    """Everything ``load`` needs of an XDMF file, as plain arrays (picklable: the work of
    the forked child): points, cell blocks [(type, ids, labels or None)], protected-tet
    mask or None, label names [[dim, label, name]]."""
    from ._io import REGION_ARRAYS, _carried_array_name, _labels

    root = _parse(path, source)
    domain = root.find("Domain")
    grids = list(_uniform_grids(domain))
    if not grids:
        raise MeshInputError(f"{source}: the file has no grid")
    data = _Data(path.parent, source)
    try:
        parsed = []
        for i, g in enumerate(grids):
            what = f"grid {g.get('Name') or i + 1!r}"
            cells = _grid_cells(g, data, what, domain)
            n_cells = sum(len(c[1]) for c in cells)
            parsed.append((g, what, cells, n_cells))
        main = next((p for p in parsed if any(_dimension(c[0]) == 3 for c in p[2])), None)
        if main is None:
            found = ", ".join(f"{c[0]} x {len(c[1])}" for p in parsed for c in p[2]) or "no cells"
            raise MeshInputError(f"{source}: the mesh has no tetrahedra (only {found})")
        g, what, main_cells, n_main = main
        points = _points(g, data, what, domain)
        if points is None:
            raise data.fail(f"{what} has no Geometry")
        attrs = _attributes(g, data, what, n_main)
        point_data = _node_attributes(g, data, what, len(points))
        cell_attrs = _node_attributes(g, data, what, n_main, "cell")
        region_name = next((a for a in (*REGION_ARRAYS, TAG_GRIDS[3]) if a in attrs), None)
        labels = None if region_name is None else _labels(attrs[region_name], region_name, source)
        # the tets of the main grid as one block (a Mixed topology may hold several runs):
        # linear ones, or else 10-node ones (dolfinx's second-order geometry, which
        # ``load(linear=True)`` reads as their corners)
        types = {t for t, _, _ in main_cells}
        tet_type = "tetra" if "tetra" in types or "tetra10" not in types else "tetra10"
        tet_pos = np.concatenate(
            [pos for t, _, pos in main_cells if t == tet_type] or [np.zeros(0, np.int64)]
        )
        tets = np.concatenate(
            [c for t, c, _ in main_cells if t == tet_type] or [np.zeros((0, 4), np.int64)]
        )
        region = None if labels is None else labels[tet_pos]
        blocks = [
            (t, c, None if labels is None else labels[pos])
            for t, c, pos in main_cells
            if t != tet_type
        ]
        cell_data = {
            name: a[tet_pos]
            for name, a in cell_attrs.items()
            if name not in (region_name, PROTECTED_ATTRIBUTE) and _carried_array_name(name)
        }
        protected = None
        if PROTECTED_ATTRIBUTE in attrs:
            protected = np.asarray(attrs[PROTECTED_ATTRIBUTE])[tet_pos] != 0
        for g2, what2, cells2, n2 in parsed:
            if g2 is g or not n2:
                continue
            pts2 = _points(g2, data, what2, domain)
            if pts2 is not None and not (
                pts2.shape == points.shape and np.array_equal(pts2, points)
            ):
                warnings.warn(f"{source}: {what2} has points of its own; ignored", stacklevel=2)
                continue
            attrs2 = _attributes(g2, data, what2, n2)
            labels2 = next(iter(attrs2.values()), None)
            name2 = next(iter(attrs2), "")
            labels2 = None if labels2 is None else _labels(labels2, name2, source)
            for t, c, pos in cells2:
                lab = None if labels2 is None else labels2[pos]
                if t != tet_type:
                    blocks.append((t, c, lab))
                elif lab is not None and region is None:  # dolfinx's cell tags
                    # (a 10-node tet is known by its corners, which come first)
                    region = _tag_region(tets[:, :4], c[:, :4], lab, len(points), source, what2)
    finally:
        data.close()
    blocks.insert(0, (tet_type, tets, region))
    names = []
    for info in domain.findall("Information"):
        if info.get("Name") == LABEL_NAMES_INFO:
            try:
                names = json.loads(info.get("Value") or info.text or "[]")
            except ValueError:
                raise MeshInputError(f"{source}: damaged {LABEL_NAMES_INFO} information") from None
    return {
        "points": points,
        "blocks": blocks,
        "protected": protected,
        "names": names,
        "point_data": point_data,
        "cell_data": cell_data,
    }


def _tag_region(
    tets: np.ndarray, tagged: np.ndarray, labels: np.ndarray, n_points: int, source, what
):
    """Region of each tet from a cell-tags grid (dolfinx meshtags: the tagged tets by
    their vertices, in any order and vertex order): its label, 0 for untagged tets;
    None when the tets hold ids out of range (``from_arrays`` reports them)."""
    from ._topology import match_rows

    if len(tets) and (tets.min() < 0 or tets.max() >= n_points):
        return None
    inside = (tagged.min(axis=1) >= 0) & (tagged.max(axis=1) < n_points)
    tagged, labels = tagged[inside], labels[inside]
    at = match_rows(tagged, tets, n_points)
    region = np.where(at >= 0, labels[np.maximum(at, 0)] if len(labels) else 0, 0)
    stray = int((~inside).sum()) + int((match_rows(tets, tagged, n_points) < 0).sum())
    if stray:
        warnings.warn(
            f"{source}: {stray} tet(s) of {what} are not tets of the mesh; ignored", stacklevel=3
        )
    return region.astype(np.int64)


def read_xdmf(path: Path, source: str) -> dict:
    """``_read_xdmf_arrays`` in a forked child where that is safe (``_forked``)."""
    from ._forked import call_in_child, can_fork

    if not can_fork():
        return _read_xdmf_arrays(path, source)
    import h5py  # noqa: F401  (imported once here, not in every child)

    from ._io import _limit_child_memory

    def read() -> dict:
        # a damaged HDF5 header may claim terabytes: the cap makes that a quick failure
        _limit_child_memory(path, *heavy_files(path))
        return _read_xdmf_arrays(path, source)

    def crashed(how: str) -> MeshFileError:
        return MeshFileError(f"{source}: not a readable XDMF file (the reader {how}: damaged data)")

    return call_in_child(read, crashed)


def xdmf_to_meshio(found: dict):
    """The meshio mesh of ``read_xdmf``'s arrays (cell blocks with a ``region`` array)."""
    import meshio

    blocks = [meshio.CellBlock(t, c) for t, c, _ in found["blocks"]]
    labels = [np.zeros(len(c), np.int64) if lab is None else lab for _, c, lab in found["blocks"]]
    has = any(lab is not None for _, _, lab in found["blocks"])
    return meshio.Mesh(found["points"], blocks, cell_data={"region": labels} if has else {})


def companion(path: Path) -> Path:
    """The HDF5 file ``write_xdmf`` writes beside ``path``."""
    return path.with_suffix(HEAVY_SUFFIX)
