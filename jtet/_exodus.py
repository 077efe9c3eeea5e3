"""Exodus II meshes (``.exo``, ``.e``; Cubit, SEACAS, MOOSE, ParaView), read and written
here: element blocks are regions, side sets labelled protected faces, node sets node
sets, with their names.

An Exodus file is a netCDF file: the classic ones (CDF1, CDF2 "64-bit offset") are read
and written with ``scipy.io.netcdf_file``, the netCDF-4 ones (HDF5 inside) read with
``h5py``; both are dependencies already. Variables (``_Reader``):

    coordx, coordy, coordz (or coord)    node coordinates
    elem_num_map                         element numbers (jtet's: its tet order)
    connect<b> + elem_type attribute     element block b's nodes (1-based), its type
    eb_prop1, eb_names                   block ids (-> region labels) and names
    elem_ss<s>, side_ss<s>               side set s: element (1-based, over the blocks in
                                         their order) and side (1-4) of each face
    ss_prop1, ss_names                   side set ids (-> face labels) and names
    node_ns<s>, ns_prop1, ns_names       node sets (1-based nodes), ids and names

Sides of a tet (the Exodus manual, TETRA): 1 = nodes 1 2 4, 2 = 2 3 4, 3 = 1 4 3,
4 = 1 3 2. Blocks of triangles (shells), bars and spheres become candidate protected
faces, edges and vertices labelled by their block id; blocks of other solids are refused.

A node set that is the nodes of the side set with its id is read as derived from it and
written again from it: ``write_exo`` gives each side set a node set of its id and name
(Cubit's and Gmsh's habit; MOOSE makes the same ones). jtet's protected vertices are
node sets too, whose ids the file's ``jtet_point_sets`` attribute lists. Every other
node set is one of ``TetMesh.node_sets``, kept as it is (overlaps included).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ._errors import MeshFileError, MeshInputError

#: global attribute of jtet's files: the ids of the node sets that are protected vertices
POINT_SETS_ATTR = "jtet_point_sets"

#: local vertices of each Exodus tet side (1-4), 0-based
SIDES = np.array([[0, 1, 3], [1, 2, 3], [0, 3, 2], [0, 2, 1]])

# element types by family (Exodus names, upper case, without their node count)
_TETS = ("TETRA", "TET", "TETRAHEDRON")
_TRIANGLES = ("TRI", "TRIANGLE", "TRISHELL", "SHELL")  # a 3-node shell is a triangle
_BARS = ("BAR", "BEAM", "TRUSS", "EDGE")
_POINTS = ("SPHERE", "CIRCLE", "POINT", "NODE")
# nodes of a quadratic cell of each kind (TETRA10, TRI6, BAR3), corners first
_QUADRATIC = {"tet": 10, "triangle": 6, "bar": 3}


def _family_kind(family: str) -> str | None:
    """The kind of cell ("tet", "triangle", "bar") of an element type's family, or None."""
    return (
        "tet" if family in _TETS else "triangle" if family in _TRIANGLES
        else "bar" if family in _BARS else None
    )  # fmt: skip


class _Reader:
    """Variables and attributes of a netCDF file, classic or netCDF-4 (HDF5)."""

    def __init__(self, path: Path, source: str):
        self.source = source
        with open(path, "rb") as f:
            magic = f.read(4)
        try:
            if magic[:3] == b"CDF" and magic[3:4] in (b"\x01", b"\x02"):
                from scipy.io import netcdf_file

                self._nc = netcdf_file(str(path), "r", mmap=False)
                self._vars = self._nc.variables
                self._attrs = self._nc._attributes
            elif magic == b"\x89HDF":
                import h5py

                self._nc = h5py.File(path, "r")
                self._vars = self._nc
                self._attrs = self._nc.attrs
            else:
                why = (
                    "netCDF 64-bit data (CDF5): write it as netCDF-4 or classic"
                    if (magic == b"CDF\x05")
                    else "not a netCDF file"
                )
                raise MeshFileError(f"{source}: not a readable Exodus file ({why})")
        except MeshFileError:
            raise
        except Exception as e:  # noqa: BLE001 - any failure of the netCDF readers
            raise MeshFileError(f"{source}: not a readable Exodus file ({e})") from None

    def close(self):
        self._nc.close()

    def array(self, name: str):
        """Variable ``name`` as a NumPy array (None when the file has none)."""
        if name not in self._vars:
            return None
        var = self._vars[name]
        try:
            return np.array(var.data if hasattr(var, "data") and not hasattr(var, "attrs")
                            else var[()])  # fmt: skip
        except Exception as e:  # noqa: BLE001
            raise MeshFileError(f"{self.source}: unreadable variable {name} ({e})") from None

    def ints(self, name: str, default=None) -> np.ndarray | None:
        a = self.array(name)
        if a is None:
            return default
        if not np.issubdtype(a.dtype, np.number):
            raise MeshFileError(f"{self.source}: variable {name} holds no numbers")
        return a.astype(np.int64).reshape(-1) if a.ndim <= 1 else a.astype(np.int64)

    def names(self, name: str, count: int) -> list[str]:
        """The ``count`` names of a char variable (k, len_name); "" where none."""
        a = self.array(name)
        if a is None or a.ndim != 2 or len(a) < count:
            return [""] * count
        rows = a.astype("S1").view(f"S{a.shape[1]}").reshape(-1)
        return [r.split(b"\0")[0].decode("utf-8", "replace").strip() for r in rows[:count]]

    def global_attr(self, name: str, default=None):
        """The file's attribute ``name`` (``default`` without it)."""
        return self._attrs.get(name, default)

    def all_names(self, name: str) -> list[str]:
        """Every name of a char variable (k, len_name); [] without it."""
        a = self.array(name)
        return self.names(name, len(a)) if a is not None and a.ndim == 2 else []

    def attr(self, var: str, name: str) -> str:
        v = self._vars[var]
        value = (v.attrs if hasattr(v, "attrs") else v._attributes).get(name, b"")
        if isinstance(value, np.ndarray):
            value = value.tobytes() if value.dtype.kind == "S" else str(value)
        return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)

    def count(self, prop: str, prefix: str) -> int:
        """How many blocks / sets: the length of their id variable, else how many
        ``<prefix><i>`` variables there are."""
        ids = self.array(prop)
        if ids is not None:
            return int(np.size(ids))
        k = 0
        while f"{prefix}{k + 1}" in self._vars:
            k += 1
        return k


def read_exo(path: Path, source: str):
    """(points, tets, region, faces, face labels, lines, line labels, pins, pin labels,
    names) of the Exodus file ``path`` (faces / lines / pins: candidate rows for
    ``_io._mesh_cells`` / ``_mesh_vertices``)."""
    reader = _Reader(path, source)
    try:
        return _read(reader, source)
    except (MeshFileError, MeshInputError):
        raise
    except Exception as e:  # noqa: BLE001 - a damaged file fails inside netCDF / HDF5
        raise MeshFileError(
            f"{source}: not a readable Exodus file ({type(e).__name__}: {e})"
        ) from None
    finally:
        reader.close()


def _read(r: _Reader, source: str):
    from ._io import _non_tet_message, quadratic_corners, reading_linear

    coords = [r.array(f"coord{c}") for c in "xyz"]
    stacked = r.array("coord") if coords[0] is None else None  # the older layout
    if stacked is not None:
        coords = list(np.atleast_2d(stacked))
    coords = [c for c in coords if c is not None]
    if not coords:
        raise MeshInputError(f"{source}: the file has no node coordinates")
    if len(coords) != 3:
        raise MeshInputError(f"{source}: the points are {len(coords)}-D; jtet needs a 3-D mesh")
    try:
        points = np.column_stack([np.asarray(c, np.float64).reshape(-1) for c in coords])
    except ValueError:
        raise MeshFileError(f"{source}: coordinate arrays of different lengths") from None
    n = len(points)
    n_blocks = r.count("eb_prop1", "connect")
    block_ids = r.ints("eb_prop1", np.arange(1, n_blocks + 1))[:n_blocks]
    block_names = r.names("eb_names", n_blocks)
    names: dict = {}
    tets, region = [], []
    cells = {2: ([], []), 1: ([], []), 0: ([], [])}  # dim -> rows, labels (tets apart)
    others: dict[str, int] = {}
    tet_of_element = []  # per element of the file: its tet index, or -1
    tet_blocks = []  # (block index, its first tet, its tets)
    n_tets = 0
    for b in range(n_blocks):
        conn = r.ints(f"connect{b + 1}")
        if conn is None:  # an empty block has no connectivity variable
            continue
        kind = r.attr(f"connect{b + 1}", "elem_type").upper()
        family = kind.rstrip("0123456789")
        conn = conn.reshape(len(conn), -1) - 1
        width = conn.shape[1]
        if reading_linear() and _QUADRATIC.get(_family_kind(family)) == width:
            # a quadratic block as its corners (``jtet.load(path, linear=True)``)
            width = {10: 4, 6: 3, 3: 2}[width]
            conn = quadratic_corners(conn, width)
        dim = (
            3 if family in _TETS and width == 4 else 2 if family in _TRIANGLES and width == 3
            else 1 if family in _BARS and width == 2 else 0 if family in _POINTS and width == 1
            else None
        )  # fmt: skip
        label = int(block_ids[b])
        if dim is None:
            if family in _TETS or family in ("HEX", "HEXAHEDRON", "WEDGE", "PYRAMID", "PYRA"):
                others[f"{kind or 'unknown'} ({width} nodes)"] = len(conn)
            tet_of_element.append(np.full(len(conn), -1))
            continue
        if block_names[b]:
            names[(dim, label)] = block_names[b]
        if dim == 3:
            tets.append(conn)
            region.append(np.full(len(conn), label, np.int64))
            tet_of_element.append(np.arange(n_tets, n_tets + len(conn)))
            tet_blocks.append((b, n_tets, len(conn)))
            n_tets += len(conn)
        else:
            cells[dim][0].append(conn)
            cells[dim][1].append(np.full(len(conn), label, np.int64))
            tet_of_element.append(np.full(len(conn), -1))
    # a solver's results on the mesh (MOOSE's nodal and element variables)
    point_data = _nodal_variables(r, n, source)
    cell_data = _element_variables(r, tet_blocks, n_tets, source)
    if others:
        raise MeshInputError(
            _non_tet_message(
                source, list(others), list(others.values()), any("TET" in k for k in others)
            )
        )
    if not tets:
        raise MeshInputError(f"{source}: the mesh has no tetrahedra (no TETRA4 block)")
    tets = np.concatenate(tets)
    region = np.concatenate(region)
    tet_of_element = np.concatenate(tet_of_element)

    faces, face_labels, side_nodes = _side_sets(r, tets, tet_of_element, names, source)
    pins, pin_labels, node_sets = _node_sets(r, n, side_nodes, names, source)
    # jtet's files number the tets in ``elem_num_map`` (their order before they were
    # grouped into blocks): back in that order, when it is one of every tet (after the
    # side sets, which name elements in the blocks' order)
    numbers = r.ints("elem_num_map")
    if numbers is not None and len(numbers) == len(tet_of_element):
        numbers = numbers[tet_of_element >= 0]
        if np.array_equal(np.sort(numbers), np.arange(1, len(tets) + 1)):
            order = np.argsort(numbers)
            tets, region = tets[order], region[order]
            cell_data = {name: a[order] for name, a in cell_data.items()}

    def joined(dim, k):
        rows, labels = cells[dim]
        return (np.concatenate([np.zeros((0, k), np.int64), *rows]),
                np.concatenate([np.zeros(0, np.int64), *labels]))  # fmt: skip

    tri, tri_labels = joined(2, 3)
    lines, line_labels = joined(1, 2)
    spheres, sphere_labels = joined(0, 1)
    faces = np.concatenate([faces, tri])
    face_labels = np.concatenate([face_labels, tri_labels])
    pins = np.concatenate([pins, spheres.reshape(-1)])
    pin_labels = np.concatenate([pin_labels, sphere_labels])
    return (points, tets, region, faces, face_labels, lines, line_labels, pins, pin_labels,
            {"label_names": names, "node_sets": node_sets, "point_data": point_data,
             "cell_data": cell_data})  # fmt: skip


def _nodal_variables(r: _Reader, n: int, source: str) -> dict:
    """The nodal variables of the file at its last time step (a solver's final
    solution; a warning says so when there are several), as ``TetMesh.point_data``:
    {name: (n,) float64}, runs ``name[0]``, ``name[1]``, ... joined into (n, k) arrays.
    Both layouts: one variable per nodal variable (``vals_nod_var1``, ...) and the
    older single (time, variable, node) array ``vals_nod_var``."""
    from ._point_data import joined_columns

    names = r.all_names("name_nod_var")
    if not names:
        return {}
    stacked = r.array("vals_nod_var")
    columns, steps = {}, 0
    for k, name in enumerate(names):
        a = r.array(f"vals_nod_var{k + 1}")
        if a is None and stacked is not None and stacked.ndim == 3 and k < stacked.shape[1]:
            a = stacked[:, k, :]
        if a is None or a.dtype.kind not in "biuf" or a.size == 0 or a.shape[-1] != n:
            raise MeshInputError(
                f"{source}: nodal variable {name or k + 1!r} does not hold one value per node"
            )
        a = np.asarray(a, np.float64).reshape(-1, n)
        steps = max(steps, len(a))
        columns[name or f"nod_var{k + 1}"] = a[-1]
    _last_step_warning("nodal variables", steps, r, source)
    return joined_columns(columns)


def _last_step_warning(what: str, steps: int, r: _Reader, source: str) -> None:
    if steps > 1:
        times = r.array("time_whole")
        when = f" (time {float(times[-1]):g})" if times is not None and len(times) else ""
        warnings.warn(
            f"{source}: the {what} are read at the last of {steps} time steps{when}",
            stacklevel=5,
        )


def _element_variables(r: _Reader, tet_blocks: list, n_tets: int, source: str) -> dict:
    """The element variables of the file's tet blocks at its last time step, as
    ``TetMesh.cell_data``: {name: (n_tets,) float64} in the blocks' order (NaN in a
    block the truth table leaves out), runs ``name[0]``, ``name[1]``, ... joined into
    (n_tets, k) arrays. jtet's own quality arrays are left out: every output gets fresh
    ones."""
    from ._io import _carried_array_name
    from ._point_data import joined_columns

    names = r.all_names("name_elem_var")
    columns, steps = {}, 0
    for v, name in enumerate(names):
        name = name or f"elem_var{v + 1}"
        if not _carried_array_name(name):
            continue
        out = np.full(n_tets, np.nan)
        for b, first, count in tet_blocks:
            a = r.array(f"vals_elem_var{v + 1}eb{b + 1}")
            if a is None:
                continue
            if a.dtype.kind not in "biuf" or a.size == 0 or a.shape[-1] != count:
                raise MeshInputError(
                    f"{source}: element variable {name!r} does not hold one value per "
                    f"element of block {b + 1}"
                )
            a = np.asarray(a, np.float64).reshape(-1, count)
            steps = max(steps, len(a))
            out[first : first + count] = a[-1]
        columns[name] = out
    _last_step_warning("element variables", steps, r, source)
    return joined_columns(columns)


def _side_sets(r: _Reader, tets, tet_of_element, names, source):
    """Faces (k, 3) and labels (k,) of the side sets on tets, and {set id: bytes of its
    sorted nodes} (for the node sets derived from them)."""
    count = r.count("ss_prop1", "elem_ss")
    ids = r.ints("ss_prop1", np.arange(1, count + 1))[:count]
    set_names = r.names("ss_names", count)
    faces, labels, nodes = [np.zeros((0, 3), np.int64)], [np.zeros(0, np.int64)], {}
    for s in range(count):
        elements, sides = r.ints(f"elem_ss{s + 1}"), r.ints(f"side_ss{s + 1}")
        if elements is None or sides is None:
            continue
        if len(elements) != len(sides):
            raise MeshFileError(f"{source}: side set {int(ids[s])}: elements and sides differ")
        bad = (elements < 1) | (elements > len(tet_of_element)) | (sides < 1) | (sides > 6)
        if bad.any():
            raise MeshInputError(
                f"{source}: side set {int(ids[s])} names element {int(elements[bad][0])} "
                f"side {int(sides[bad][0])}, which the file does not have"
            )
        tet = tet_of_element[elements - 1]
        on_tet = (tet >= 0) & (sides <= 4)  # sides of shells and other elements: skipped
        rows = np.take_along_axis(tets[tet[on_tet]], SIDES[sides[on_tet] - 1], axis=1)
        label = int(ids[s])
        faces.append(rows)
        labels.append(np.full(len(rows), label, np.int64))
        nodes[label] = np.unique(rows).tobytes()
        if set_names[s]:
            names[(2, label)] = set_names[s]
    return np.concatenate(faces), np.concatenate(labels), nodes


def _node_sets(r: _Reader, n: int, side_nodes: dict, names, source):
    """(protected vertices, their labels, ``TetMesh.node_sets``) of the file's node
    sets: those jtet wrote for protected vertices (the ids its ``jtet_point_sets``
    attribute lists) are protected vertices again; a side set's own (its id, its nodes)
    is written again from the side set (its faces' mid-edge nodes aside, for a
    quadratic file read as linear); every other one is a node set, kept as it is."""
    from ._io import noted_mid_nodes

    mid = noted_mid_nodes()
    count = r.count("ns_prop1", "node_ns")
    ids = r.ints("ns_prop1", np.arange(1, count + 1))[:count]
    set_names = r.names("ns_names", count)
    points = set(np.ravel(r.global_attr(POINT_SETS_ATTR, [])).astype(np.int64).tolist())
    pins, labels, kept = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], []
    for s in range(count):
        members = r.ints(f"node_ns{s + 1}")
        if members is None:
            members = np.zeros(0, np.int64)
        if len(members) and (members.min() < 1 or members.max() > n):
            raise MeshInputError(
                f"{source}: node set {int(ids[s])} names node "
                f"{int(members[(members < 1) | (members > n)][0])} of {n}"
            )
        nodes = np.unique(members - 1)
        label = int(ids[s])
        if label in points:
            if set_names[s]:
                names.setdefault((0, label), set_names[s])
            pins.append(nodes)
            labels.append(np.full(len(nodes), label, np.int64))
        elif side_nodes.get(label) != nodes[~np.isin(nodes, mid)].tobytes():
            kept.append((set_names[s], nodes, label))
    return np.concatenate(pins), np.concatenate(labels), kept


def _chars(names: list[str], width: int) -> np.ndarray:
    """(k, width) netCDF char array of ``names``, NUL-padded."""
    raw = b"".join(s.encode()[: width - 1].ljust(width, b"\0") for s in names)
    return np.frombuffer(raw, "S1").reshape(len(names), width)


def write_exo(mesh, path: Path, cell_data: dict | None = None, quad=None) -> None:
    """Write ``mesh`` as a classic (64-bit offset) Exodus II file: one TETRA4 block per
    region (id = label, name from ``label_names``), one side set per protected face
    label with a node set of the same id and name, one node set per protected vertex
    label (listed in the ``jtet_point_sets`` attribute) and per ``node_sets`` entry
    (each keeps its id unless one before took it: the next free id), and ``cell_data`` (name -> (m,)
    per-tet values) as element variables at one time step (0.0), which ParaView colours
    by. With ``quad`` (``_quadratic.quadratic_mesh(mesh)``) the blocks are TETRA10 (in
    VTK's node order, Exodus's too) over its nodes, with its node sets and point data,
    and a side set's node set has the nodes of its faces' edges."""
    from scipy.io import netcdf_file

    from ._abaqus import _face_owners

    nodes, tets, kind, own_sets = mesh.points, mesh.tets, "TETRA4", mesh.node_sets
    face_nodes, point_data = mesh.protected_faces, mesh.point_data
    if quad is not None:
        nodes, tets, kind, own_sets = quad.points, quad.tets, "TETRA10", quad.node_sets
        face_nodes, point_data = quad.cells(mesh.protected_faces), quad.point_data

    names = mesh.label_names
    regions = np.unique(mesh.region)
    order = np.argsort(mesh.region, kind="stable")  # elements block by block
    face_labels = np.unique(mesh.protected_face_labels)
    vertex_labels = np.unique(mesh.protected_vertex_labels)
    all_names = [names.get((3, int(r)), "") for r in regions]
    all_names += [names.get((2, int(k)), "") for k in face_labels]
    all_names += [names.get((0, int(k)), "") for k in vertex_labels]
    all_names += [ns.name for ns in own_sets]
    from ._point_data import scalar_columns

    # the mesh's cell data and jtet's quality arrays (which win), as scalar columns
    cell_data = scalar_columns({**mesh.cell_data, **dict(cell_data or {})})
    all_names += list(cell_data)

    nodal = scalar_columns(point_data)  # an (n, k) array: k variables name[i]
    all_names += list(nodal)
    width = min(max([33] + [len(s.encode()) + 1 for s in all_names]), 256)

    f = netcdf_file(str(path), "w", version=2)
    try:
        f.api_version = np.float32(8.11)
        f.version = np.float32(8.11)
        f.floating_point_word_size = np.int32(8)
        f.file_size = np.int32(1)
        f.maximum_name_length = np.int32(width - 1)
        f.int64_status = np.int32(0)
        f.title = "written by jtet"
        f.createDimension("time_step", None)  # scipy: the record dimension comes first
        f.createDimension("len_string", 33)
        f.createDimension("len_line", 81)
        f.createDimension("four", 4)
        f.createDimension("len_name", width)
        f.createDimension("num_dim", 3)
        f.createDimension("num_nodes", len(nodes))
        f.createDimension("num_elem", mesh.n_tets)
        f.createDimension("num_el_blk", len(regions))
        f.createVariable("time_whole", "f8", ("time_step",))
        for c, axis in enumerate("xyz"):
            f.createVariable(f"coord{axis}", "f8", ("num_nodes",))[:] = nodes[:, c]
        f.createVariable("coor_names", "c", ("num_dim", "len_name"))[:] = _chars(
            ["x", "y", "z"], width
        )

        def ids_variable(name, dim, values):
            var = f.createVariable(name, "i4", (dim,))
            var[:] = np.asarray(values, np.int32)
            if name.endswith("prop1"):
                var.name = "ID"

        ids_variable("eb_status", "num_el_blk", np.ones(len(regions)))
        ids_variable("eb_prop1", "num_el_blk", regions)
        f.createVariable("eb_names", "c", ("num_el_blk", "len_name"))[:] = _chars(
            all_names[: len(regions)], width
        )
        # the elements' numbers: the tets' order (blocks group them by region)
        f.createVariable("elem_num_map", "i4", ("num_elem",))[:] = (order + 1).astype(np.int32)
        counts = np.bincount(np.searchsorted(regions, mesh.region), minlength=len(regions))
        for b, k in enumerate(counts.tolist()):
            f.createDimension(f"num_el_in_blk{b + 1}", k)
            f.createDimension(f"num_nod_per_el{b + 1}", tets.shape[1])
        start = np.concatenate([[0], np.cumsum(counts)])
        for b in range(len(regions)):
            var = f.createVariable(
                f"connect{b + 1}", "i4", (f"num_el_in_blk{b + 1}", f"num_nod_per_el{b + 1}")
            )
            var[:] = (tets[order[start[b] : start[b + 1]]] + 1).astype(np.int32)
            var.elem_type = kind

        side_sets = []
        if len(mesh.protected_faces):
            tet, opposite = _face_owners(mesh)
            element = np.empty(mesh.n_tets, np.int64)
            element[order] = np.arange(1, mesh.n_tets + 1)  # file element of each tet
            side = _SIDE_OF_OPPOSITE[opposite]
            for k in face_labels.tolist():
                mine = mesh.protected_face_labels == k
                side_sets.append((k, element[tet[mine]], side[mine]))
        node_sets = [
            (k, np.unique(face_nodes[mesh.protected_face_labels == k]) + 1,
             names.get((2, k), ""))
            for k, _, _ in side_sets
        ]  # fmt: skip
        used = {k for k, _, _ in side_sets}
        own = [ns.label for ns in own_sets if ns.label is not None]
        spare = max([0, *used, *vertex_labels.tolist(), *own]) + 1
        point_sets = []

        def free(label):  # the id itself, or the next unused one
            nonlocal spare
            if label is None or label in used:
                label, spare = spare, spare + 1
            used.add(label)
            return label

        for k in vertex_labels.tolist():
            mine = mesh.protected_vertices[mesh.protected_vertex_labels == k] + 1
            point_sets.append(free(k))
            node_sets.append((point_sets[-1], mine, names.get((0, k), "")))
        node_sets += [(free(ns.label), ns.ids + 1, ns.name) for ns in own_sets]
        if point_sets:
            setattr(f, POINT_SETS_ATTR, np.array(point_sets, np.int32))
        if side_sets:
            f.createDimension("num_side_sets", len(side_sets))
            ids_variable("ss_status", "num_side_sets", np.ones(len(side_sets)))
            ids_variable("ss_prop1", "num_side_sets", [k for k, _, _ in side_sets])
            f.createVariable("ss_names", "c", ("num_side_sets", "len_name"))[:] = _chars(
                [names.get((2, k), "") for k, _, _ in side_sets], width
            )
            for s, (_, elements, sides) in enumerate(side_sets):
                f.createDimension(f"num_side_ss{s + 1}", len(elements))
                ids_variable(f"elem_ss{s + 1}", f"num_side_ss{s + 1}", elements)
                ids_variable(f"side_ss{s + 1}", f"num_side_ss{s + 1}", sides)
        if node_sets:
            f.createDimension("num_node_sets", len(node_sets))
            ids_variable("ns_status", "num_node_sets", np.ones(len(node_sets)))
            ids_variable("ns_prop1", "num_node_sets", [k for k, _, _ in node_sets])
            f.createVariable("ns_names", "c", ("num_node_sets", "len_name"))[:] = _chars(
                [name for _, _, name in node_sets], width
            )
            for s, (_, nodes, _) in enumerate(node_sets):
                f.createDimension(f"num_nod_ns{s + 1}", len(nodes))
                ids_variable(f"node_ns{s + 1}", f"num_nod_ns{s + 1}", nodes)
        if nodal:
            f.createDimension("num_nod_var", len(nodal))
            f.createVariable("name_nod_var", "c", ("num_nod_var", "len_name"))[:] = _chars(
                list(nodal), width
            )
            f.variables["time_whole"][0] = 0.0
            for v, values in enumerate(nodal.values()):
                var = f.createVariable(f"vals_nod_var{v + 1}", "f8", ("time_step", "num_nodes"))
                var[0, :] = values
        if cell_data:
            f.createDimension("num_elem_var", len(cell_data))
            f.createVariable("name_elem_var", "c", ("num_elem_var", "len_name"))[:] = _chars(
                list(cell_data), width
            )
            table = f.createVariable("elem_var_tab", "i4", ("num_el_blk", "num_elem_var"))
            table[:] = np.ones((len(regions), len(cell_data)), np.int32)
            f.variables["time_whole"][0] = 0.0
            for v, values in enumerate(cell_data.values()):
                values = np.asarray(values, np.float64)[order]
                for b in range(len(regions)):
                    var = f.createVariable(
                        f"vals_elem_var{v + 1}eb{b + 1}",
                        "f8",
                        ("time_step", f"num_el_in_blk{b + 1}"),
                    )
                    var[0, :] = values[start[b] : start[b + 1]]
    finally:
        f.close()


# Exodus side (1-4) of the face opposite local vertex j: the side of ``SIDES`` without j
_SIDE_OF_OPPOSITE = 1 + np.argmin((SIDES[None, :, :] == np.arange(4)[:, None, None]).any(2), 1)
