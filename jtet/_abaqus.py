"""Abaqus / CalculiX input files (``.inp``): the mesh part of a flat input file.

``write_inp`` writes the nodes, the tets as ``C3D4`` elements in one ``*ELEMENT`` block
per region (its element set named after the region: a Gmsh physical name, else
``REGION<label>``), a set ``EALL`` of every element (CalculiX decks' habit), and each
label of the protected faces as an element-face ``*SURFACE`` (what ``*DSLOAD`` /
``*DLOAD`` pressure loads and contact use) with a node set ``<surface>_NODES`` of its
vertices (what ``*BOUNDARY`` uses). Each region and surface also has a node set of its
own name, as Gmsh's export writes them (``Mesh.SaveGroupsOfNodes``), each label of the
protected vertices a node set (``POINT<label>`` when unnamed), and each of
``TetMesh.node_sets`` its own. Element ``i + 1`` is tet ``i``, node ``j + 1`` point
``j``. Comment lines ``** jtet region <label> <set>``, ``** jtet surface <label>
<name>`` and ``** jtet point <label> <set>`` keep the labels for the way back.

``read_inp`` reads such files and those of Gmsh, meshio and CalculiX's pre-processor:
``*NODE``, ``*ELEMENT`` (tets; triangles and lines as candidate protected faces and
edges), ``*ELSET`` / ``*NSET`` (ids, ``GENERATE`` ranges, other sets' names) and
element-face ``*SURFACE``. Node sets that are not the nodes of a region, surface or
curve become ``TetMesh.node_sets`` (``_point_sets``): the nodes a deck's loads and
boundary conditions name stay where they are, and the output writes each set again
under its name. Regions come from the element sets holding tets (without the
comments: the sets named by ``*ELSET`` first, then those of ``*ELEMENT`` lines, a tet
in several taking the first; a set holding every tet is no region when there are
others). Material, step and load sections are skipped. Parts, instances and
``*INCLUDE`` are refused: an assembly's node ids are local to its parts.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from ._errors import MeshFileError, MeshInputError
from ._io import format_rows

# Abaqus numbers a C3D4's faces S1 (nodes 1 2 3), S2 (1 4 2), S3 (2 4 3), S4 (3 4 1);
# by the local vertex each face leaves out (jtet's TET_FACES order): 3 -> S1, 2 -> S2,
# 0 -> S3, 1 -> S4
FACE_NODES = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]])
_S_OF_OPPOSITE = np.array([3, 4, 2, 1])  # S number of the face opposite local vertex j

# element types by the cells they are (Abaqus and CalculiX names; a trailing H, T, R,
# ... of the linear ones is a formulation, not a shape)
_TETS = re.compile(r"^C3D4[A-Z]*$")
_TRIANGLES = re.compile(r"^(S3|S3R|STRI3|CPS3|CPE3|CAX3|M3D3|SFM3D3|R3D3|DS3|F3D3)[A-Z]*$")
_LINES = re.compile(r"^(T3D2|B31|B21|T2D2|R3D2|SPRINGA|DCOUP3D)[A-Z]*$")
_OTHER_SOLIDS = re.compile(r"^(C3D|DC3D|AC3D)(\d+)")
# numbers in a row of a linear cell: the element id and its nodes
_ROW_WIDTH = {"tet": 5, "triangle": 4, "line": 3}
# quadratic cells, read as their corners with ``jtet.load(path, linear=True)``: (kind,
# numbers a row: the element id and its nodes, corners first)
_QUADRATIC = (
    (re.compile(r"^(C3D10|DC3D10|AC3D10)[A-Z]*$"), "tet", 11),
    (re.compile(r"^(STRI65|S6|CPS6|CPE6|CAX6|M3D6|DS6|SFM3D6|R3D6)[A-Z]*$"), "triangle", 7),
    (re.compile(r"^(T3D3|B32|T2D3|B22)[A-Z]*$"), "line", 4),
)


def _set_name(name: str, taken: set) -> str:
    """An Abaqus name of ``name``: letters, digits and underscores, starting with a
    letter, at most 80 characters, not in ``taken``."""
    clean = re.sub(r"[^A-Za-z0-9_]", "_", name)
    if not clean[:1].isalpha():
        clean = "S_" + clean
    clean = clean[:72]
    out, k = clean, 1
    while out.upper() in taken:
        k += 1
        out = f"{clean}_{k}"
    taken.add(out.upper())
    return out


def _nodes_of(cells: np.ndarray, n: int) -> np.ndarray:
    """Sorted distinct node indices of ``cells`` (any shape) among ``n`` nodes: a mask,
    not a sort (a region's 4M corner ids)."""
    used = np.zeros(n, bool)
    used[np.ravel(cells)] = True
    return np.flatnonzero(used)


def _id_lines(ids: np.ndarray) -> str:
    """1-based ids, 16 to a line (Abaqus reads at most 16 per data line)."""
    ids = np.asarray(ids, np.int64)
    full = len(ids) // 16 * 16
    text = format_rows(ids[:full].reshape(-1, 16), ", ".join(["%d"] * 16) + "\n")
    if full < len(ids):
        text += ", ".join(map(str, ids[full:].tolist())) + "\n"
    return text


def write_inp(mesh, path: Path, quad=None) -> None:
    """Write ``mesh`` as the Abaqus / CalculiX input file ``path`` (see the module); with
    ``quad`` (``_quadratic.quadratic_mesh(mesh)``) as ``C3D10`` elements over its nodes
    (Abaqus lists a C3D10's nodes in VTK's order), the node sets with their mid-edge
    nodes."""
    from . import __version__

    nodes, tets, node_sets_of_mesh, kind = mesh.points, mesh.tets, mesh.node_sets, "C3D4"
    faces = mesh.protected_faces
    if quad is not None:
        nodes, tets, node_sets_of_mesh, kind = quad.points, quad.tets, quad.node_sets, "C3D10"
        faces = quad.cells(mesh.protected_faces)
    n_nodes = len(nodes)

    taken: set = set()
    names = mesh.label_names
    regions = np.unique(mesh.region)
    region_sets = {
        int(r): _set_name(names.get((3, int(r)), f"REGION{r}".replace("-", "M")), taken)
        for r in regions
    }
    face_labels = np.unique(mesh.protected_face_labels)
    surfaces = {
        int(k): _set_name(names.get((2, int(k)), f"SURFACE{k}".replace("-", "M")), taken)
        for k in face_labels
    }
    # node sets have names of their own (Abaqus keeps element and node sets apart)
    node_taken: set = set()
    # the mesh's node sets keep their names first: a deck names them (the sets jtet
    # derives from regions and surfaces take a suffix where a name is taken)
    own_sets = [
        (_set_name(ns.name or f"NSET{ns.label}".replace("-", "M"), node_taken), ns.ids)
        for ns in node_sets_of_mesh
    ]
    point_labels = np.unique(mesh.protected_vertex_labels)
    points = {
        int(k): _set_name(names.get((0, int(k)), f"POINT{k}".replace("-", "M")), node_taken)
        for k in point_labels
    }
    out = [f"** written by jtet {__version__}\n"]
    out += [f"** jtet region {r} {s}\n" for r, s in region_sets.items()]
    out += [f"** jtet surface {k} {s}\n" for k, s in surfaces.items()]
    out += [f"** jtet point {k} {s}\n" for k, s in points.items()]
    out.append(f"*HEADING\njtet mesh: {n_nodes} nodes, {mesh.n_tets} {kind} elements\n")
    ids = np.arange(1, n_nodes + 1, dtype=np.float64)[:, None]
    out.append("*NODE\n")
    # 16 significant digits, as Gmsh writes them: CalculiX refuses a number of 17 digits
    # with an exponent ("1.3601257419226798e-06"), and 16 keep each coordinate to within
    # a relative 1e-16 (an ulp or two)
    out.append(format_rows(np.hstack([ids, nodes]), "%d, %.16g, %.16g, %.16g\n"))
    table = np.column_stack([np.arange(1, mesh.n_tets + 1), tets + 1])
    row = ", ".join(["%d"] * table.shape[1]) + "\n"
    for r, name in region_sets.items():
        out.append(f"*ELEMENT, TYPE={kind}, ELSET={name}\n")
        out.append(format_rows(table[mesh.region == r], row))
    if "EALL" not in taken:
        # every element: CalculiX decks (cgx's, PrePoMax's) put their sections on Eall,
        # which a read of such a deck's mesh keeps as no region when there are others
        out.append(f"*ELSET, ELSET=EALL, GENERATE\n1, {mesh.n_tets}, 1\n")
    # a node set of each region and surface under its own name, as Gmsh's export writes
    # them (Mesh.SaveGroupsOfNodes): decks written for Gmsh's files (*BOUNDARY on a
    # physical group's name) run on jtet's
    surface_nodes = {
        k: _nodes_of(faces[mesh.protected_face_labels == k], n_nodes) for k in surfaces
    }  # also the <surface>_NODES sets below
    node_sets = [
        (name, _nodes_of(tets[mesh.region == r], n_nodes)) for r, name in region_sets.items()
    ]
    node_sets += [(name, surface_nodes[k]) for k, name in surfaces.items()]
    for name, nodes in node_sets:
        out.append(f"*NSET, NSET={_set_name(name, node_taken)}\n" + _id_lines(nodes + 1))
    for k, name in points.items():
        out.append(f"*NSET, NSET={name}\n")
        out.append(_id_lines(mesh.protected_vertices[mesh.protected_vertex_labels == k] + 1))
    for name, ids in own_sets:
        out.append(f"*NSET, NSET={name}\n" + _id_lines(ids + 1))
    if len(mesh.protected_faces):
        tet, opposite = _face_owners(mesh)
        side = _S_OF_OPPOSITE[opposite]
        for k, name in surfaces.items():
            mine = mesh.protected_face_labels == k
            lines = []
            for s in range(1, 5):
                elements = tet[mine & (side == s)] + 1
                if len(elements):
                    out.append(f"*ELSET, ELSET={name}_S{s}\n" + _id_lines(elements))
                    lines.append(f"{name}_S{s}, S{s}\n")
            out.append(f"*SURFACE, NAME={name}, TYPE=ELEMENT\n" + "".join(lines))
            out.append(f"*NSET, NSET={_set_name(name + '_NODES', node_taken)}\n")
            out.append(_id_lines(surface_nodes[k] + 1))
    path.write_text("".join(out))


def _face_owners(mesh) -> tuple[np.ndarray, np.ndarray]:
    """For each protected face, a tet that has it and the local vertex it leaves out."""
    from ._topology import TET_FACES, match_rows

    faces = mesh.tets[:, TET_FACES].reshape(-1, 3)  # face j of tet t: row 4 t + j
    at = match_rows(faces, mesh.protected_faces, mesh.n_points)
    if (at < 0).any():  # TetMesh checks its protected faces: cannot happen
        raise MeshInputError("a protected face is no face of a tet")
    return at // 4, at % 4


# ---------------------------------------------------------------------------------------
# reading


def _sections(text: str, source: str):
    """(keyword, {parameter: value}, data block) of each keyword line of the file, and
    the ``** jtet`` comments. Regular expressions find the lines (C-level: a 1M-tet
    file has millions), a data block is the text up to the next keyword."""
    first = re.search(r"(?mi)^\*NODE", text)  # jtet writes its comments before the nodes
    top = text if first is None else text[: first.start()]
    comments = re.findall(r"(?m)^\*\* jtet (region|surface|point) (-?\d+) (\S+)[ \t]*\r?$", top)
    body = re.sub(r"(?m)^(\*\*.*|[ \t\r]*)(\n|$)", "", text)  # comment and blank lines
    keywords = list(re.finditer(r"(?m)^\*.*$", body))
    lead = body[: keywords[0].start()] if keywords else body
    if lead.strip():
        raise MeshFileError(f"{source}: not a readable Abaqus input file (data before any keyword)")
    out = []
    for k, m in enumerate(keywords):
        parts = [p.strip() for p in m.group()[1:].split(",")]
        params = {}
        for p in parts[1:]:
            key, _, value = p.partition("=")
            params[key.strip().upper()] = value.strip()
        stop = keywords[k + 1].start() if k + 1 < len(keywords) else len(body)
        out.append((parts[0].upper(), params, body[m.end() + 1 : stop]))
    return out, comments


def _line_count(block: str) -> int:
    return block.count("\n") + (1 if block and not block.endswith("\n") else 0)


def _numbers(block: str, width: int, what: str, source: str, kind=np.float64):
    """The data block's numbers as a (k, width) array (commas or blanks between)."""
    tokens = block.replace(",", " ").split()
    try:
        values = np.array(tokens, dtype=np.float64)
    except ValueError:
        raise MeshFileError(f"{source}: {what}: data that are not numbers") from None
    lines = _line_count(block)
    if len(values) % width or len(values) // width != lines:
        raise MeshFileError(
            f"{source}: {what}: {len(values)} numbers on {lines} lines, not {width} a line"
        )
    values = values.reshape(-1, width)
    if kind is np.int64:
        if not (np.isfinite(values).all() and (values == np.round(values)).all()):
            raise MeshFileError(f"{source}: {what}: ids that are not integers")
        return values.astype(np.int64)
    return values


def _set_ids(block: str, generate: bool, sets: dict, what: str, source: str) -> np.ndarray:
    """The ids of a set's data block: ids, ``GENERATE`` triples, or names of sets."""
    tokens = block.replace(",", " ").split()
    if generate:
        try:
            triples = np.array(tokens, dtype=np.int64).reshape(-1, 3)
        except ValueError:
            raise MeshFileError(f"{source}: {what}: GENERATE needs start, end, step") from None
        if (triples[:, 2] <= 0).any() or (triples[:, 1] - triples[:, 0] > 10**9).any():
            raise MeshFileError(f"{source}: {what}: bad GENERATE range")
        return np.concatenate([np.arange(a, b + 1, s) for a, b, s in triples.tolist()] or [[]])
    try:  # ids only: one C-level conversion
        return np.array(tokens, dtype=np.int64)
    except ValueError:
        pass
    tokens = np.array(tokens)
    numeric = np.char.isdigit(np.char.lstrip(tokens, "-"))
    out = [tokens[numeric].astype(np.int64)]
    for name in tokens[~numeric].tolist():
        if name.upper() not in sets:
            raise MeshInputError(f"{source}: {what} names the unknown set {name!r}")
        out.append(sets[name.upper()][1])
    return np.concatenate(out).astype(np.int64)


def read_inp(path: Path, source: str):
    """The arrays of ``TetMesh.from_arrays`` (and label names) of the Abaqus input file
    ``path``: (points, tets, region, faces, face labels, edges, edge labels, names)
    with faces / edges as candidate rows for ``_mesh_cells``."""
    from ._io import _non_tet_message, note_mid_nodes, noted_mid_nodes, reading_linear
    from ._quadratic import MID_EDGES

    try:
        text = path.read_text(errors="replace")
    except OSError as e:
        raise MeshFileError(f"{source}: cannot read the file ({e.strerror or e})") from None
    sections, comments = _sections(text, source)
    heads = {h for h, _, _ in sections}
    for bad in ("PART", "INSTANCE", "ASSEMBLY", "INCLUDE"):
        if bad in heads:
            raise MeshInputError(
                f"{source}: *{bad} is not supported: jtet reads flat input files (export "
                "the mesh without parts and assemblies, or with its includes merged)"
            )
    node_blocks, elements = [], {"tet": [], "triangle": [], "line": []}
    mid_nodes: list = []  # node ids of quadratic cells' mid-edge nodes (and their edges')
    others: dict[str, int] = {}
    sets: dict[str, tuple[str, np.ndarray, int]] = {}  # NAME -> (name, element ids, order)
    node_sets: dict[str, tuple[str, np.ndarray, int]] = {}  # the same, of node ids
    surfaces: list[tuple[str, list[str]]] = []
    order = 0
    for head, params, data in sections:
        if head in ("NODE", "ELEMENT", "ELSET", "NSET") and "INPUT" in params:
            raise MeshInputError(
                f"{source}: *{head} with INPUT= (data in another file) is not supported"
            )
        if head == "NODE" and params.get("SYSTEM", "R").upper() != "R":
            # cylindrical / spherical coordinates would be read as x, y, z
            raise MeshInputError(
                f"{source}: *NODE, SYSTEM={params['SYSTEM']} is not supported (rectangular "
                "coordinates only)"
            )
        if head == "NODE" and data.strip():
            node_blocks.append(data)
        elif head == "ELEMENT" and data.strip():
            etype = params.get("TYPE", "").upper()
            kind = (
                "tet" if _TETS.match(etype) else "triangle" if _TRIANGLES.match(etype)
                else "line" if _LINES.match(etype) else None
            )  # fmt: skip
            width = _ROW_WIDTH.get(kind)
            quadratic = reading_linear() and kind is None
            if quadratic:
                kind, width = next(((k, w) for p, k, w in _QUADRATIC if p.match(etype)), (None, 0))
            if kind is None:
                if _OTHER_SOLIDS.match(etype):
                    others[etype] = others.get(etype, 0) + _line_count(data)
                continue
            rows = _numbers(data, width, f"*ELEMENT, TYPE={etype}", source, np.int64)
            if quadratic:  # the element id and the corners; the mid-edge nodes noted
                # (a C3D10's in VTK's order, with their edges: ``quadratic_corners``)
                ends = rows[:, 1:5][:, MID_EDGES[4]] if kind == "tet" else None
                mid_nodes.append((rows[:, _ROW_WIDTH[kind] :], ends))
                rows = rows[:, : _ROW_WIDTH[kind]]
            elements[kind].append(rows)
            if params.get("ELSET"):
                name = params["ELSET"]
                # an *ELEMENT set ranks after every *ELSET (10**9 + order)
                prev = sets.get(name.upper(), (name, np.zeros(0, np.int64), 10**9 + order))
                sets[name.upper()] = (name, np.concatenate([prev[1], rows[:, 0]]), prev[2])
                order += 1
        elif head == "ELSET" and params.get("ELSET"):
            name = params["ELSET"]
            ids = _set_ids(data, "GENERATE" in params, sets, f"*ELSET {name}", source)
            prev = sets.get(name.upper(), (name, np.zeros(0, np.int64), order))
            sets[name.upper()] = (name, np.concatenate([prev[1], ids]), prev[2])
            order += 1
        elif head == "NSET" and params.get("NSET"):
            name = params["NSET"]
            ids = _set_ids(data, "GENERATE" in params, node_sets, f"*NSET {name}", source)
            prev = node_sets.get(name.upper(), (name, np.zeros(0, np.int64), len(node_sets)))
            node_sets[name.upper()] = (name, np.concatenate([prev[1], ids]), prev[2])
        elif head == "SURFACE" and params.get("TYPE", "ELEMENT").upper() == "ELEMENT":
            surfaces.append((params.get("NAME", f"SURFACE{len(surfaces) + 1}"), data))
    if others:
        raise MeshInputError(
            _non_tet_message(
                source, list(others), list(others.values()), any("10" in t for t in others)
            )
        )
    if not node_blocks:
        raise MeshInputError(f"{source}: the file has no *NODE section")
    widths = {len(b.split("\n", 1)[0].replace(",", " ").split()) for b in node_blocks}
    if widths == {3}:
        raise MeshInputError(f"{source}: the points are 2-D; jtet needs a 3-D tet mesh")
    nodes = np.concatenate([_numbers(b, 4, "*NODE", source) for b in node_blocks])
    node_ids = nodes[:, 0]
    if not (node_ids == np.round(node_ids)).all():
        raise MeshFileError(f"{source}: *NODE: ids that are not integers")
    node_ids = node_ids.astype(np.int64)
    order_ids = np.argsort(node_ids, kind="stable")
    sorted_ids = node_ids[order_ids]
    if len(sorted_ids) > 1 and (np.diff(sorted_ids) == 0).any():
        dup = int(sorted_ids[np.flatnonzero(np.diff(sorted_ids) == 0)[0]])
        raise MeshInputError(f"{source}: node {dup} is defined twice")

    numbered = sorted_ids[0] == 1 and sorted_ids[-1] == len(sorted_ids)  # 1..n: no search

    def index_of(ids: np.ndarray, what: str) -> np.ndarray:
        if numbered and len(ids) and ids.min() >= 1 and ids.max() <= len(sorted_ids):
            return order_ids[ids - 1]
        at = np.minimum(np.searchsorted(sorted_ids, ids), len(sorted_ids) - 1)
        bad = sorted_ids[at] != ids
        if bad.any():
            raise MeshInputError(
                f"{source}: {what} names node {int(ids[bad][0])}, which no *NODE defines"
            )
        return order_ids[at]

    tet_rows = np.concatenate(elements["tet"] or [np.zeros((0, 5), np.int64)])
    if not len(tet_rows):
        found = {k: sum(len(r) for r in v) for k, v in elements.items() if v}
        only = ", ".join(f"{k} x {n}" for k, n in found.items()) or "no elements"
        raise MeshInputError(f"{source}: the mesh has no tetrahedra (only {only})")
    # tets in element-id order (jtet's files: element i + 1 is tet i, whatever the blocks)
    tet_rows = tet_rows[np.argsort(tet_rows[:, 0], kind="stable")]
    if len(tet_rows) > 1 and (np.diff(tet_rows[:, 0]) == 0).any():
        dup = int(tet_rows[np.flatnonzero(np.diff(tet_rows[:, 0]) == 0)[0], 0])
        raise MeshInputError(f"{source}: element {dup} is defined twice")
    tets = index_of(tet_rows[:, 1:], "a C3D4 element")
    for ids, ends in mid_nodes:  # their indices, for ``load`` to leave out
        ends = None if ends is None else index_of(ends.reshape(-1), "a quadratic element")
        note_mid_nodes(index_of(ids.reshape(-1), "a quadratic element"), ends)
    is_mid = np.zeros(len(nodes), bool)  # a node set's mid-edge nodes are no corners
    is_mid[noted_mid_nodes()] = True
    region, names = _regions(tet_rows[:, 0], sets, comments, source)
    faces, face_labels = _surfaces(tet_rows, tets, surfaces, sets, comments, names, source)
    start = int(face_labels.max(initial=0))
    extra_faces, extra_labels = _element_cells(
        elements["triangle"], sets, index_of, names, 2, start
    )
    lines, line_labels = _element_cells(elements["line"], sets, index_of, names, 1, 0)
    faces = np.concatenate([faces, extra_faces])
    face_labels = np.concatenate([face_labels, extra_labels])
    entities = [(3, tets, region), (2, faces, face_labels), (1, lines, line_labels)]
    pins, pin_labels, kept = _point_sets(node_sets, index_of, entities, names, comments, is_mid)
    return (nodes[:, 1:], tets, region, faces, face_labels, lines, line_labels, pins,
            pin_labels, {"label_names": names, "node_sets": kept})  # fmt: skip


def _point_sets(node_sets, index_of, entities, names, comments, is_mid: np.ndarray):
    """Protected vertices (k,), their labels (k,) and ``TetMesh.node_sets`` from the
    node sets of the file: those jtet wrote for its protected vertices (``** jtet point``
    comments) are protected vertices again; those that are the nodes of a named region,
    surface or curve (Gmsh's ``SaveGroupsOfNodes`` sets and jtet's ``<surface>_NODES``;
    their mid-edge nodes, ``is_mid`` (n,) bool, aside) are written again from those;
    every other one (what a deck's boundary conditions and loads name) is a node set,
    kept as it is (``names`` gains the protected vertices' names)."""
    n = len(is_mid)
    derived = {}
    default = {3: "REGION", 2: "SURFACE", 1: "CURVE"}  # write_inp's names of unnamed labels
    for dim, cells, labels in entities:
        for label in np.unique(labels).tolist():
            name = names.get((dim, label), f"{default[dim]}{label}".replace("-", "M"))
            nodes = _nodes_of(cells[labels == label], n).tobytes()
            derived[name.upper()] = nodes
            derived[name.upper() + "_NODES"] = nodes
    given = {name.upper(): int(label) for kind, label, name in comments if kind == "point"}
    pins, pin_labels, kept = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], []
    for key, (name, ids, _) in sorted(node_sets.items(), key=lambda s: s[1][2]):
        nodes = _nodes_of(index_of(ids, f"*NSET {name}"), n)
        label = given.get(key)
        if label is not None:  # jtet's protected vertices of this label
            if not re.fullmatch(r"POINT-?M?\d+", name):
                names[(0, label)] = name
            pins.append(nodes)
            pin_labels.append(np.full(len(nodes), label, np.int64))
        elif derived.get(key) != nodes[~is_mid[nodes]].tobytes():
            kept.append((name, nodes))
    return np.concatenate(pins), np.concatenate(pin_labels), kept


def _regions(tet_ids, sets, comments, source):
    """Region label of each tet and the names of the labels (see the module)."""
    region = np.zeros(len(tet_ids), np.int64)
    names: dict = {}
    labelled = [(int(label), name) for kind, label, name in comments if kind == "region"]
    if labelled:
        for label, name in labelled:
            if name.upper() in sets:
                region[np.isin(tet_ids, sets[name.upper()][1])] = label
                if not re.fullmatch(r"REGION-?M?\d+", name):
                    names[(3, label)] = name
        return region, names
    held = [
        (rank, name, mask)
        for name, ids, rank in sets.values()
        if (mask := np.isin(tet_ids, ids)).any()
    ]
    if len(held) > 1:  # a set of every tet ("EALL") says nothing of regions
        # (unless every set holds every tet: then the first in the file's order, a
        # Gmsh physical volume's *ELSET before its elementary volume's *ELEMENT set)
        held = [h for h in held if not h[2].all()] or [min(held, key=lambda h: h[0])]
    done = np.zeros(len(tet_ids), bool)
    label = 0
    for _, name, mask in sorted(held, key=lambda h: h[0]):
        if (mask & ~done).any():  # a set whose tets all went to earlier sets is no region
            label += 1
            region[mask & ~done] = label
            names[(3, label)] = name
            done |= mask
    return region, names


# a surface's data line: an element id or an element set, then the face S1-S4
_SURFACE_LINE = re.compile(r"(?m)^[ \t]*([^,\s]+)[ \t]*,[ \t]*[Ss]([1-4])[ \t]*(?:,.*)?\r?$")


def _surfaces(tet_rows, tets, surfaces, sets, comments, names, source):
    """Faces (k, 3) and labels (k,) of the element-face surfaces. ``tet_rows`` are in
    element-id order. A surface may list every face's element (CalculiX's do): its lines
    are matched by one regular expression and looked up together."""
    labels = {name.upper(): int(label) for kind, label, name in comments if kind == "surface"}
    next_label = max([0, *labels.values()]) + 1
    all_faces, all_labels = [np.zeros((0, 3), np.int64)], [np.zeros(0, np.int64)]
    element_ids = tet_rows[:, 0]
    for name, data in surfaces:
        label = labels.get(name.upper())
        if label is None:
            label, next_label = next_label, next_label + 1
        if not re.fullmatch(r"SURFACE-?M?\d+", name):
            names[(2, label)] = name
        pairs = _SURFACE_LINE.findall(data)
        skipped = _line_count(data) - len(pairs)
        if skipped:
            warnings.warn(
                f"{source}: *SURFACE {name}: {skipped} line(s) that are no 'element or set, "
                "S1-S4' skipped",
                stacklevel=4,
            )
        if not pairs:
            continue
        refs, sides = np.array(pairs).T
        numeric = np.char.isdigit(np.char.lstrip(refs, "-"))
        ids = [refs[numeric].astype(np.int64)]
        faces = [sides[numeric].astype(np.int64) - 1]
        for ref, side in zip(refs[~numeric].tolist(), sides[~numeric].tolist(), strict=True):
            if ref.upper() not in sets:
                raise MeshInputError(f"{source}: *SURFACE {name} names the unknown set {ref!r}")
            members = sets[ref.upper()][1]
            ids.append(members)
            faces.append(np.full(len(members), int(side) - 1, np.int64))
        ids, faces = np.concatenate(ids), np.concatenate(faces)
        at = np.minimum(np.searchsorted(element_ids, ids), len(element_ids) - 1)
        hit = element_ids[at] == ids
        rows = tets[at[hit]]
        all_faces.append(np.take_along_axis(rows, FACE_NODES[faces[hit]], axis=1))
        all_labels.append(np.full(int(hit.sum()), label, np.int64))
    return np.concatenate(all_faces), np.concatenate(all_labels)


def _element_cells(blocks, sets, index_of, names, dim, start):
    """Triangle / line elements (k, 3 or 2) with labels from the first set holding them,
    numbered from ``start`` + 1 (after the surfaces' labels)."""
    width = dim + 1
    if not blocks:
        return np.zeros((0, width), np.int64), np.zeros(0, np.int64)
    rows = np.concatenate(blocks)
    cells = index_of(rows[:, 1:], "an element")
    labels = np.zeros(len(rows), np.int64)
    label = start
    done = np.zeros(len(rows), bool)
    for name, ids, _ in sorted(sets.values(), key=lambda s: s[2]):
        mask = np.isin(rows[:, 0], ids) & ~done
        if mask.any():
            label += 1
            labels[mask] = label
            names[(dim, label)] = name
            done |= mask
    return cells, labels
