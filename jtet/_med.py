"""MED meshes (``.med``): the HDF5 format of Salome, code_aster and MEDCoupling, read and
written here with ``h5py`` (a dependency already): element groups are regions and
labelled protected faces, node groups node sets, with their names.

The layout (MED 3.0 / 4.x; what ``read_med`` reads, what ``write_med`` writes)::

    ENS_MAA/<mesh>/<step>/NOE/COO        coordinates, column-major (x of every node, then y, z)
    ENS_MAA/<mesh>/<step>/NOE/FAM        the family of each node (> 0; 0: none)
    ENS_MAA/<mesh>/<step>/MAI/<type>/NOD connectivity of the cells of a type (TE4, TR3,
                                         SE2, PO1, ...), 1-based, column-major
    ENS_MAA/<mesh>/<step>/MAI/<type>/FAM the family of each cell (< 0; 0: none)
    FAS/<mesh>/ELEME/<family>            a cell family: attribute NUM, GRO/NOM its groups'
    FAS/<mesh>/NOEUD/<family>            names (80 bytes each); the same for node families
    CHA/<field>/<step>/NOE, MAI.TE4      field values at the nodes / on the tets

A group is what a MED user names and works with (Salome's groups, code_aster's
``GROUP_MA`` / ``GROUP_NO``); a family is how the file stores them: one number per cell,
for the set of groups the cell is in. So groups may overlap. ``read_med`` gives the cells
of each set of groups one label: tets a region, triangles a protected face label,
segments a protected edge label, point cells (PO1) a protected vertex label, named after
their groups ("inlet", or "inlet+wall" for the cells in both). Families of the same
groups share the label of the first (Gmsh writes a family per geometric entity); a
label is a family's number without its sign, and cells of no family get 0. Node groups
become ``TetMesh.node_sets`` (overlaps kept), which ``improve`` never moves.

``write_med`` writes the reverse: a family per region and per face, edge and vertex
label (its number the label's negative where that is free; groups: the label's name
split at "+", else ``region_<label>``, ``surface_<label>``, ``edge_<label>``,
``vertex_<label>``; region 0 without a name: no family), the protected faces as TR3, edges as
SE2, vertices as PO1 cells, node families for the node sets, and the point data and
cell arrays as fields (float64, one step).

MED orders a tet's vertices the other way round from VTK and jtet (Gmsh's
``med2mshNodeIndex``: the second and third swapped); triangles are as they are.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from ._errors import MeshFileError, MeshInputError

# MED's tet vertex order is VTK's with the second and third swapped (an involution)
_SWAP = [0, 2, 1, 3]
# cell types jtet reads: (jtet's role, vertices per cell)
_READ = {"TE4": ("tet", 4), "TR3": ("face", 3), "SE2": ("edge", 2), "PO1": ("vertex", 1)}
_VERTICES_OF_ROLE = dict(_READ.values())
# quadratic cells, read as their corners with ``jtet.load(path, linear=True)``
# (role, corners, nodes), the corners listed first
# a 10-node tet in VTK's order (``_quadratic``) as a MED T10: MED lists the corners the
# other way round (``_SWAP``), then the nodes on its edges 01, 12, 20, 03, 13, 23
_T10_FROM_VTK = [0, 2, 1, 3, 6, 5, 4, 7, 9, 8]
_QUADRATIC = {"T10": ("tet", 4, 10), "TR6": ("face", 3, 6), "SE3": ("edge", 2, 3)}
# solids jtet refuses, with the names its messages give them; T10 gets the quadratic hint
_SOLIDS = {
    "T10": "TETRA10",
    "HE8": "HEXA8",
    "H20": "HEXA20",
    "H27": "HEXA27",
    "PE6": "PENTA6",
    "P15": "PENTA15",
    "P18": "PENTA18",
    "PY5": "PYRA5",
    "P13": "PYRA13",
    "POE": "POLYHEDRON",
}
_NAME_BYTES = 80  # a group name
_DEFAULT_GROUP = {3: "region", 2: "surface", 1: "edge", 0: "vertex"}
_NO_PROFILE = "MED_NO_PROFILE_INTERNAL"


def _text(value) -> str:
    """An HDF5 attribute or a row of bytes as a string, without trailing NULs / blanks."""
    if isinstance(value, np.ndarray):
        value = value.astype(np.uint8).tobytes()
    if isinstance(value, bytes | np.bytes_):
        value = bytes(value).split(b"\0")[0].decode("utf-8", errors="replace")
    return str(value).rstrip()


def read_med(path: Path, source: str):
    """(points, tets, region, faces, face labels, edges, edge labels, vertices, vertex
    labels, extras) of the MED file ``path``: faces / edges / vertices as candidate rows
    for ``_io._mesh_cells`` / ``_mesh_vertices``; extras: ``label_names``,
    ``node_sets``, ``point_data``, ``cell_data``."""
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise MeshFileError(f"{source}: not a readable MED file (not HDF5: {e})") from None
    try:
        with f:
            return _read(f, source)
    except (MeshFileError, MeshInputError):
        raise
    except Exception as e:  # noqa: BLE001 - a damaged file fails anywhere inside HDF5
        raise MeshFileError(
            f"{source}: not a readable MED file ({type(e).__name__}: {e})"
        ) from None


def _last(group, what: str, source: str):
    """The last of the computing steps in ``group`` (by their NDT, NOR attributes)."""
    import h5py

    steps = [group[k] for k in group if isinstance(group[k], h5py.Group)]
    if not steps:
        raise MeshFileError(f"{source}: the {what} has no computing step")
    key = [(int(s.attrs.get("NDT", -1)), int(s.attrs.get("NOR", -1))) for s in steps]
    return steps[int(max(range(len(steps)), key=key.__getitem__))], len(steps)


def _read(f, source: str):
    from ._io import _non_tet_message, quadratic_corners, reading_linear

    if "ENS_MAA" not in f:
        raise MeshFileError(f"{source}: not a MED file (an HDF5 file without ENS_MAA)")
    meshes = list(f["ENS_MAA"])
    if len(meshes) != 1:
        listing = ", ".join(repr(m) for m in meshes[:5]) or "none"
        raise MeshInputError(
            f"{source}: the file holds {len(meshes)} meshes ({listing}); jtet reads a MED "
            "file of one mesh"
        )
    mesh_name = meshes[0]
    med_mesh = f["ENS_MAA"][mesh_name]
    if int(med_mesh.attrs.get("TYP", 0)) != 0:
        raise MeshInputError(f"{source}: a structured MED mesh; jtet reads unstructured ones")
    dim = int(med_mesh.attrs.get("ESP", 3))
    if dim != 3:
        raise MeshInputError(f"{source}: the points are {dim}-D; jtet needs a 3-D tet mesh")
    # MED 2 files hold the nodes and cells in the mesh's group itself
    step, n_steps = (med_mesh, 1) if "NOE" in med_mesh else _last(med_mesh, "mesh", source)
    if n_steps > 1:
        warnings.warn(
            f"{source}: the mesh is read at the last of its {n_steps} computing steps",
            stacklevel=4,
        )
    coords = step["NOE"]["COO"]
    n = int(coords.attrs["NBR"])
    points = np.asarray(coords[()], np.float64).reshape(3, n).T
    node_families = _families(step["NOE"], n, source)

    linear = reading_linear()
    blocks: dict[str, list] = {}  # role -> [(ids, family numbers or None), ...]
    bad, skipped = {}, {}
    for kind, group in step.get("MAI", {}).items():
        quadratic = linear and kind in _QUADRATIC
        if kind in _SOLIDS and not quadratic:
            bad[_SOLIDS[kind]] = _cell_count(group)
            continue
        if kind not in _READ and not quadratic:
            skipped[kind] = _cell_count(group)
            continue
        role, k, width = _QUADRATIC[kind] if quadratic else (*_READ[kind], _READ[kind][1])
        nod = group["NOD"]
        count = int(nod.attrs["NBR"])
        ids = np.asarray(nod[()], np.int64).reshape(width, count).T - 1
        if quadratic:  # corners first, in the order of the linear cell
            ids = quadratic_corners(ids, k)
        blocks.setdefault(role, []).append((ids, _families(group, count, source)))
    cells = {role: _joined_blocks(found) for role, found in blocks.items()}
    if bad:
        quadratic = _SOLIDS["T10"] in bad
        raise MeshInputError(_non_tet_message(source, list(bad), list(bad.values()), quadratic))
    if "tet" not in cells:
        only = ", ".join(f"{k} x {c}" for k, c in skipped.items()) or "no cells"
        raise MeshInputError(f"{source}: the mesh has no tetrahedra (TE4; only {only})")
    if skipped:
        listing = ", ".join(f"{k} x {c}" for k, c in skipped.items())
        warnings.warn(f"{source}: cells jtet does not read were left out: {listing}", stacklevel=4)

    fas = None
    if "FAS" in f and mesh_name in f["FAS"]:
        fas = f["FAS"][mesh_name]
    elif "FAS" in med_mesh:  # MED 2
        fas = med_mesh["FAS"]
    cell_groups = _family_groups(fas, "ELEME")
    names: dict[tuple[int, int], str] = {}
    labelled = {}
    for role, dim_of in (("tet", 3), ("face", 2), ("edge", 1), ("vertex", 0)):
        ids, fam = cells.get(role, (np.zeros((0, _VERTICES_OF_ROLE[role]), np.int64), None))
        labels = (
            np.zeros(len(ids), np.int64)
            if fam is None
            else _labels(fam, cell_groups, dim_of, names)
        )
        labelled[role] = (ids, labels)
    tets = labelled["tet"][0][:, _SWAP]
    node_sets = _node_sets(node_families, _family_groups(fas, "NOEUD"))
    # cell fields of a quadratic mesh read as linear (``--linear``) lie on its T10 cells
    kinds = set(step.get("MAI", {}))
    tet_support = "MAI.T10" if linear and "T10" in kinds and "TE4" not in kinds else "MAI.TE4"
    point_data, cell_data = _fields(f, mesh_name, n, len(tets), source, tet_support)
    vertices, vertex_labels = labelled["vertex"]
    return (
        points,
        tets,
        labelled["tet"][1],
        *labelled["face"],
        *labelled["edge"],
        vertices.reshape(-1),
        vertex_labels,
        {
            "label_names": names,
            "node_sets": node_sets,
            "point_data": point_data,
            "cell_data": cell_data,
        },
    )


def _joined_blocks(found: list) -> tuple[np.ndarray, np.ndarray | None]:
    """(ids, family numbers or None) of the cells of one role from several types (TE4
    and T10 read as linear ones)."""
    if len(found) == 1:
        return found[0]
    ids = np.concatenate([i for i, _ in found])
    if all(f is None for _, f in found):
        return ids, None
    fam = [np.zeros(len(i), np.int64) if f is None else f for i, f in found]
    return ids, np.concatenate(fam)


def _cell_count(group) -> int:
    """The number of cells of a cell type's group (polygons and polyhedra count theirs in
    FAM or NUM, the others in NOD too)."""
    for key in ("FAM", "NUM", "NOD"):
        if key in group and "NBR" in group[key].attrs:
            return int(group[key].attrs["NBR"])
    return 0


def _families(group, count: int, source: str) -> np.ndarray | None:
    """The (count,) family numbers of a node or cell group (None: it has none)."""
    if "FAM" not in group:
        return None
    fam = np.asarray(group["FAM"][()], np.int64).reshape(-1)
    if len(fam) != count:
        raise MeshInputError(f"{source}: {len(fam)} family numbers for {count} entities")
    return fam


def _family_groups(fas, kind: str) -> dict[int, tuple[str, ...]]:
    """{family number: its groups' names} of the cell (``ELEME``) or node (``NOEUD``)
    families in the file's ``FAS/<mesh>`` group."""
    out: dict[int, tuple[str, ...]] = {}
    if fas is None or kind not in fas:
        return out
    for family in fas[kind].values():
        groups: tuple[str, ...] = ()
        if "GRO" in family and "NOM" in family["GRO"]:
            rows = np.asarray(family["GRO"]["NOM"][()]).reshape(-1, _NAME_BYTES)
            groups = tuple(t for t in (_text(r) for r in rows) if t)
        out[int(family.attrs["NUM"])] = groups
    return out


def _labels(fam: np.ndarray, groups: dict, dim: int, names: dict) -> np.ndarray:
    """Labels of cells of family numbers ``fam``: a family's number without its sign,
    families of the same groups the first one's; their names into ``names``."""
    used = np.unique(fam)
    label_of = {}
    first_of_groups: dict[tuple[str, ...], int] = {}
    for number in used.tolist():
        found = groups.get(number, ())
        label = abs(number)
        if found:
            label = first_of_groups.setdefault(tuple(sorted(found)), label)
            names[(dim, label)] = "+".join(found)
        label_of[number] = label
    table = np.array([label_of[u] for u in used.tolist()], np.int64)
    return table[np.searchsorted(used, fam)]


def _node_sets(families: np.ndarray | None, groups: dict) -> list:
    """``TetMesh.node_sets`` items (name, vertex ids) of the node groups, in the order of
    the families (by number) they first appear in."""
    if families is None:
        return []
    members: dict[str, list[int]] = {}
    for number in sorted(groups):
        for name in groups[number]:
            members.setdefault(name, []).append(number)
    return [(name, np.flatnonzero(np.isin(families, nums))) for name, nums in members.items()]


def _fields(
    f, mesh_name: str, n_points: int, n_tets: int, source: str, tet_support: str = "MAI.TE4"
):
    """(point_data, cell_data): the file's fields on every node (``NOE``) and on every
    tet (``tet_support``: ``MAI.TE4``, or ``MAI.T10`` for a file of 10-node tets read as
    linear; one value per tet) at their last step; others left out with a warning.
    jtet's own per-tet arrays (region, quality) are not read: every output gets fresh
    ones."""
    from ._io import _carried_array_name

    point_data: dict = {}
    cell_data: dict = {}
    if "CHA" not in f:
        return point_data, cell_data
    left, last_of = [], []
    for name, field in f["CHA"].items():
        if _text(field.attrs.get("MAI", mesh_name)) not in ("", _text(mesh_name)):
            continue
        step, n_steps = _last(field, f"field {name!r}", source)
        if n_steps > 1:
            last_of.append(name)
        n_comp = int(field.attrs.get("NCO", 1))
        for support, values in step.items():
            profile = _text(values.attrs.get("PFL", _NO_PROFILE))
            data = values.get(profile)
            target, count = {"NOE": (point_data, n_points), tet_support: (cell_data, n_tets)}.get(
                support, (None, 0)
            )
            gauss = int(data.attrs.get("NGA", 1)) if data is not None else 0
            if target is cell_data and not _carried_array_name(name):
                continue
            if target is None or profile != _NO_PROFILE or data is None or gauss != 1:
                left.append(f"{name} ({support})")
                continue
            co = np.asarray(data["CO"][()])
            if co.size != count * n_comp:
                raise MeshInputError(
                    f"{source}: field {name!r} has {co.size} values on {support}, not "
                    f"{count} x {n_comp}"
                )
            a = co.reshape(n_comp, count).T
            target[name] = a[:, 0] if n_comp == 1 else a
    if last_of:
        warnings.warn(
            f"{source}: fields read at their last step: {', '.join(last_of[:3])}"
            f"{', ...' if len(last_of) > 3 else ''}",
            stacklevel=5,
        )
    if left:
        warnings.warn(
            f"{source}: fields left out (jtet reads values at every node or one per tet): "
            f"{', '.join(left[:3])}{', ...' if len(left) > 3 else ''}",
            stacklevel=5,
        )
    return point_data, cell_data


# ---------------------------------------------------------------------------------------
# writing


def _family_numbers(labels_by_dim: dict[int, np.ndarray], names) -> dict[tuple[int, int], int]:
    """{(dim, label): cell family number (< 0; 0: none)}: a label's negative where no
    other (dim, label) took it (dims 3, 2, 1, 0 in turn), else the next number below all
    wanted ones; region 0 without a name is in no family."""
    wanted = [-int(v) for a in labels_by_dim.values() for v in np.unique(a) if v > 0]
    free = min([0, *wanted]) - 1
    taken: set[int] = set()
    out = {}
    for dim in (3, 2, 1, 0):
        for label in np.unique(labels_by_dim.get(dim, np.zeros(0, np.int64))).tolist():
            if dim == 3 and label == 0 and (3, 0) not in names:
                out[(dim, label)] = 0
                continue
            number = -label if label > 0 and -label not in taken else None
            if number is None:
                number, free = free, free - 1
            taken.add(number)
            out[(dim, label)] = number
    return out


def _group_names(dim: int, label: int, names) -> list[str]:
    name = names.get((dim, label))
    if not name:
        return [f"{_DEFAULT_GROUP[dim]}_{label}"]
    return [g for g in name.split("+") if g] or [name]


def _write_family(parent, number: int, groups: list[str], source: str) -> None:
    """A family group ``FAM_<number>_...`` with its groups' names (80 bytes each)."""
    rows = np.zeros((len(groups), _NAME_BYTES), np.int8)
    for i, g in enumerate(groups):
        raw = g.encode()
        if len(raw) > _NAME_BYTES:
            warnings.warn(
                f"{source}: group name {g!r} cut to MED's {_NAME_BYTES} bytes", stacklevel=4
            )
            raw = raw[:_NAME_BYTES]
        rows[i, : len(raw)] = np.frombuffer(raw, np.uint8).view(np.int8)
    key = re.sub(r"[^A-Za-z0-9_.-]", "_", "_".join(groups))[:40]
    family = parent.create_group(f"FAM_{number}_{key}")
    family.attrs.create("NUM", number, dtype=np.int64)
    gro = family.create_group("GRO")
    gro.attrs.create("NBR", len(groups), dtype=np.int64)
    # one (80,) int8 element per group, as MED's own library writes them
    gro.create_dataset("NOM", (len(groups),), dtype=np.dtype(("i1", (_NAME_BYTES,))))[...] = rows


def _node_families(node_sets, n: int) -> tuple[np.ndarray, list[tuple[int, list[str]]]]:
    """(n,) node family numbers (1, 2, ...; 0: in no node set) and [(number, the names
    of its node sets)]: one family per distinct set of node sets a node is in, the
    families of the first node set's nodes first (so that ``read_med``, which lists the
    groups in the order of the families they first appear in, gives the sets back in
    their order when they are disjoint or nested)."""
    if not node_sets:
        return np.zeros(n, np.int64), []
    k = len(node_sets)
    member = np.zeros((n, k), bool)
    for j, ns in enumerate(node_sets):
        member[ns.ids, j] = True
    rows, inverse = np.unique(np.packbits(member, axis=1), axis=0, return_inverse=True)
    bits = np.unpackbits(rows, axis=1)[:, :k].astype(bool)
    # rows in set 0 first, then by set 1, ... (np.lexsort: the last key is the primary)
    order = np.lexsort([~bits[:, j] for j in reversed(range(k))])
    order = order[bits[order].any(axis=1)]  # the empty row is family 0
    number = np.zeros(len(rows), np.int64)
    number[order] = np.arange(1, len(order) + 1)
    set_names = [ns.name or f"nodes_{j}" for j, ns in enumerate(node_sets)]
    families = [(int(number[r]), [set_names[j] for j in np.flatnonzero(bits[r])]) for r in order]
    return number[inverse.reshape(-1)], families


def _mesh_name(path: Path) -> str:
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", path.stem.split(".")[0])[:64]
    return name or "mesh"


def write_med(
    mesh, path: Path, cell_data: dict | None = None, name_from: Path | None = None, quad=None
) -> None:
    """Write ``mesh`` as a MED 3.0 file (what Salome, code_aster and Gmsh read): tets
    (TE4) with a family per region, protected faces (TR3), edges (SE2) and vertices (PO1)
    with a family per label, node families for ``mesh.node_sets``, and
    ``mesh.point_data`` and ``mesh.cell_data`` with ``cell_data`` (jtet's quality
    arrays, which win) as float64 fields at one step. The mesh is named after the stem of
    ``name_from`` (default: ``path``), as Salome names a mesh after its file. With
    ``quad`` (``_quadratic.quadratic_mesh(mesh)``) the cells are quadratic (T10, TR6,
    SE3) over its nodes, with its point data and node sets."""
    import h5py

    source = str(path)
    names = mesh.label_names
    labels_by_dim = {
        3: mesh.region,
        2: mesh.protected_face_labels,
        1: mesh.protected_edge_labels,
        0: mesh.protected_vertex_labels,
    }
    numbers = _family_numbers(labels_by_dim, names)
    mesh_name = _mesh_name(Path(name_from or path))
    blocks = [
        ("TE4", 304, mesh.tets[:, _SWAP], mesh.region, 3),
        ("TR3", 203, mesh.protected_faces, mesh.protected_face_labels, 2),
        ("SE2", 102, mesh.protected_edges, mesh.protected_edge_labels, 1),
        ("PO1", 1, mesh.protected_vertices.reshape(-1, 1), mesh.protected_vertex_labels, 0),
    ]
    points, node_sets, point_data, tet_kind = mesh.points, mesh.node_sets, mesh.point_data, "TE4"
    if quad is not None:
        tet_kind = "T10"
        blocks[:3] = [
            ("T10", 310, quad.tets[:, _T10_FROM_VTK], mesh.region, 3),
            ("TR6", 206, quad.cells(mesh.protected_faces), mesh.protected_face_labels, 2),
            ("SE3", 103, quad.cells(mesh.protected_edges), mesh.protected_edge_labels, 1),
        ]
        points, node_sets, point_data = quad.points, quad.node_sets, quad.point_data
    node_fam, node_families = _node_families(node_sets, len(points))
    with h5py.File(path, "w") as f:
        info = f.create_group("INFOS_GENERALES")
        for key, value in (("MAJ", 3), ("MIN", 0), ("REL", 0)):
            info.attrs.create(key, value, dtype=np.int64)
        m = f.create_group("ENS_MAA").create_group(mesh_name)
        for key, value in (("DIM", 3), ("ESP", 3), ("REP", 0), ("SRT", 0), ("TYP", 0)):
            m.attrs.create(key, value, dtype=np.int64)
        m.attrs.create("NOM", np.bytes_("".join(f"{c:<16}" for c in "XYZ")))
        m.attrs.create("UNI", np.bytes_(" " * 48))
        m.attrs.create("UNT", np.bytes_(""))
        m.attrs.create("DES", np.bytes_("written by jtet"))
        step = m.create_group("-0000000000000000001-0000000000000000001")
        for key, value in (("CGT", 1), ("NDT", -1), ("NOR", -1)):
            step.attrs.create(key, value, dtype=np.int64)
        step.attrs.create("PDT", -1.0)

        def dataset(group, key, data, count):
            d = group.create_dataset(key, data=data)
            d.attrs.create("CGT", 1, dtype=np.int64)
            d.attrs.create("NBR", count, dtype=np.int64)

        noe = step.create_group("NOE")
        noe.attrs.create("CGT", 1, dtype=np.int64)
        noe.attrs.create("CGS", 1, dtype=np.int64)
        noe.attrs.create("PFL", np.bytes_(_NO_PROFILE))
        dataset(noe, "COO", np.ascontiguousarray(points.T).reshape(-1), len(points))
        dataset(noe, "FAM", node_fam, len(points))
        mai = step.create_group("MAI")
        mai.attrs.create("CGT", 1, dtype=np.int64)
        for kind, geo, ids, labels, dim in blocks:
            if not len(ids):
                continue
            g = mai.create_group(kind)
            for key, value in (("CGT", 1), ("CGS", 1), ("GEO", geo)):
                g.attrs.create(key, value, dtype=np.int64)
            g.attrs.create("PFL", np.bytes_(_NO_PROFILE))
            dataset(g, "NOD", np.ascontiguousarray(ids.T, np.int64).reshape(-1) + 1, len(ids))
            lut_labels = np.unique(labels)
            lut = np.array([numbers[(dim, int(v))] for v in lut_labels], np.int64)
            dataset(g, "FAM", lut[np.searchsorted(lut_labels, labels)], len(ids))

        fas = f.create_group("FAS").create_group(mesh_name)
        fas.create_group("FAMILLE_ZERO").attrs.create("NUM", 0, dtype=np.int64)
        written = {k: v for k, v in numbers.items() if v != 0}
        if written:
            eleme = fas.create_group("ELEME")
            for (dim, label), number in written.items():
                _write_family(eleme, number, _group_names(dim, label, names), source)
        if node_families:
            noeud = fas.create_group("NOEUD")
            for number, groups in node_families:
                _write_family(noeud, number, groups, source)

        fields = {
            **{k: ("NOE", a) for k, a in point_data.items()},
            **{
                k: (f"MAI.{tet_kind}", a)
                for k, a in {**mesh.cell_data, **dict(cell_data or {})}.items()
            },
        }
        if fields:
            # creation order kept, so that the arrays come back in their order (HDF5 lists
            # a group's members by name otherwise)
            cha = f.create_group("CHA", track_order=True)
            for field_name, (support, values) in fields.items():
                _write_field(cha, field_name, mesh_name, support, np.asarray(values, np.float64))


def _write_field(cha, name: str, mesh_name: str, support: str, values: np.ndarray) -> None:
    """One float64 field ``name`` at one step (NDT 1, NOR 1, time 0) on the nodes
    (``support`` "NOE") or the tets ("MAI.TE4"), without a profile."""
    values = values.reshape(len(values), -1)
    count, n_comp = values.shape
    field = cha.create_group(name[:64])
    field.attrs.create("MAI", np.bytes_(mesh_name))
    field.attrs.create("TYP", 6, dtype=np.int64)  # MED_FLOAT64
    field.attrs.create("NCO", n_comp, dtype=np.int64)
    field.attrs.create("NOM", np.bytes_("".join(f"{f'c{i}':<16}" for i in range(n_comp))))
    field.attrs.create("UNI", np.bytes_(" " * 16 * n_comp))
    field.attrs.create("UNT", np.bytes_(""))
    step = field.create_group("0000000000000000000100000000000000000001")
    for key, value in (("NDT", 1), ("NOR", 1), ("RDT", -1), ("ROR", -1)):
        step.attrs.create(key, value, dtype=np.int64)
    step.attrs.create("PDT", 0.0)
    where = step.create_group(support)
    where.attrs.create("GAU", np.bytes_(""))
    where.attrs.create("PFL", np.bytes_(_NO_PROFILE))
    data = where.create_group(_NO_PROFILE)
    data.attrs.create("NBR", count, dtype=np.int64)
    data.attrs.create("NGA", 1, dtype=np.int64)
    data.attrs.create("GAU", np.bytes_(""))
    data.create_dataset("CO", data=np.ascontiguousarray(values.T).reshape(-1))
