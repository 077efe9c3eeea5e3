"""Netgen / NGSolve meshes (``.vol``, and ``.vol.gz`` for reading): what
``ngsolve.Mesh("x.vol")`` loads and ``mesh.ngmesh.Save`` writes.

``read_vol`` reads the mesh part of the file (up to ``endmesh``; the geometry Netgen may
append after it is not read): ``points``; ``volumeelements`` (tets, their material
number -> region); ``surfaceelements`` (also the ``gi`` / ``uv`` variants of STL and OCC
geometries: triangles with their boundary-condition number -> labelled protected faces);
``edgesegments`` (``gi2`` / ``gi3`` too: the geometry's edges -> protected edges
labelled with their edge number); ``pointelements`` -> protected vertices; the names of
``materials``, ``bcnames``, ``cd2names`` and ``cd3names`` -> ``TetMesh.label_names``; periodic
``identifications`` -> ``TetMesh.periodic`` links, which ``improve`` keeps (their
vertices and the surface edges between them stay), written back as identifications. Netgen orients tets the other way
round from VTK: they are read and written with two vertices swapped. With
``load(..., linear=True)`` a second-order file (``Mesh.SecondOrder``: 10-node tets,
6-node surface elements) reads as its corners, and the nodes of its curved edges (in
Netgen's order, ``_MID_EDGES``) become ``TetMesh.curved_edges``.

``write_vol`` writes points, tets with their region as material number, and as surface
elements every boundary face, every face between two regions and every protected face,
each with a boundary-condition number (the face's label; unlabelled boundary and
interface faces share one more number, named ``default``), the regions on its two sides
(``domin`` behind its normal, ``domout`` in front, 0 outside) and the names.

Both work on whole arrays: a section's numbers are parsed in one call, never a Python
loop over its lines.
"""

from __future__ import annotations

import gzip
import re
import warnings
from pathlib import Path

import numpy as np

from ._errors import MeshFileError, MeshInputError
from ._quadratic import vtk_edge_columns

# Netgen's vertex order of a tet is VTK's with the second and third swapped
_SWAP = [0, 2, 1, 3]
# corner pairs (in Netgen's order) of the edge nodes of its 10-node tets, in the file's
# order (checked on Netgen's own second-order file in the tests: every node off its
# edge's midpoint lies on the curved surface)
_MID_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
# those edges of a tet in VTK's order (``_SWAP`` undone) as columns of VTK's edge nodes
_VTK_COLUMNS = vtk_edge_columns(np.array(_SWAP)[_MID_EDGES])
# sections whose numbers jtet reads, with the number of leading columns before the
# vertex count ("surfaceelements": surfnr bcnr domin domout np p1 p2 p3 [geometry info])
_SURFACE = ("surfaceelements", "surfaceelementsgi", "surfaceelementsuv")
_EDGES = ("edgesegments", "edgesegmentsgi", "edgesegmentsgi2", "edgesegmentsgi3")
# sections of "<count>" then count lines (skipped unless read above)
_COUNTED = (
    "facedescriptors",
    "volumeelements",
    "points",
    "pointelements",
    "materials",
    "bcnames",
    "cd2names",
    "cd3names",
    "edgedescriptors",
    "identifications",
    "identificationnames",
    "singular_points",
    "singular_edge_left",
    "singular_edge_right",
    "singular_face_inside",
    "singular_face_outside",
    "face_colours",
    "face_transparencies",
    *_SURFACE,
    *_EDGES,
)
_NAMES = {"materials": 3, "bcnames": 2, "cd2names": 1, "cd3names": 0}


def read_vol(path: Path, source: str):
    """``(points, tets, region, faces, face labels, edges, edge labels, vertices,
    vertex labels, {"label_names": names, "periodic": links})`` of the Netgen mesh file
    ``path``: faces / edges / vertices as candidate rows for ``_io._mesh_cells`` /
    ``_mesh_vertices``, names as ``TetMesh.label_names``, the identifications as
    ``TetMesh.periodic`` links (one per identification number, no affine map)."""
    try:
        data = path.read_bytes()
        if path.name.lower().endswith(".gz"):
            data = gzip.decompress(data)
    except (OSError, EOFError, gzip.BadGzipFile) as e:
        raise MeshFileError(f"{source}: cannot read the file ({e})") from None
    text = data.decode("latin-1")
    end = re.search(r"^\s*endmesh\s*$", text, re.M)
    text = re.sub(r"#[^\n]*", "", text[: end.start()] if end else text)
    lines = text.split("\n")
    if next((ln.strip() for ln in lines if ln.strip()), "") != "mesh3d":
        raise MeshFileError(f"{source}: not a Netgen mesh file (no 'mesh3d' first)")
    sections = _sections(lines, source)
    dimension = int(_numbers(sections.get("dimension", ["3"]), 1, "dimension", source)[0, 0])
    if dimension != 3:
        raise MeshInputError(f"{source}: a {dimension}-D Netgen mesh; jtet needs a 3-D tet mesh")
    if "points" not in sections or "volumeelements" not in sections:
        raise MeshInputError(f"{source}: the file has no points or no volume elements")
    points = _numbers(sections["points"], 3, "points", source)
    tets, region = _volume_elements(sections["volumeelements"], source)
    faces, face_labels = _surface_elements(sections, source)
    edges, edge_labels = _edge_segments(sections, source)
    vertices = np.zeros(0, np.int64)
    vertex_labels = np.zeros(0, np.int64)
    if "pointelements" in sections:
        table = _numbers(sections["pointelements"], 2, "pointelements", source, np.int64)
        vertices, vertex_labels = table[:, 0] - 1, table[:, 1]
    periodic = []
    if "identifications" in sections:  # periodic pairs: p1 p2 identification number
        pairs = _numbers(sections["identifications"], 3, "identifications", source, np.int64)
        for number in np.unique(pairs[:, 2]):
            link = pairs[pairs[:, 2] == number, :2] - 1
            periodic.append((2, (int(number), int(number)), None, link))
    names = {}
    for section, dim in _NAMES.items():
        for line in sections.get(section, []):
            number, name = (line.split(None, 1) + ["", ""])[:2]
            name = name.strip()
            if number.lstrip("-").isdigit() and name and name != "default":
                names[(dim, int(number))] = name
    return (
        points,
        tets,
        region,
        faces,
        face_labels,
        edges,
        edge_labels,
        vertices,
        vertex_labels,
        {"label_names": names, "periodic": periodic},
    )


def _sections(lines: list[str], source: str) -> dict[str, list[str]]:
    """{keyword: its data lines} of the file's ``lines`` (comments removed). Netgen
    writes a keyword line, a count line and that many lines (``dimension`` and
    ``geomtype``: one value); the data lines of a section hold no blank line."""
    out: dict[str, list[str]] = {}
    i, n = 0, len(lines)
    while i < n:
        word = lines[i].strip()
        i += 1
        if not word or word == "mesh3d":
            continue
        word = word.split()[0]
        if word in ("dimension", "geomtype"):
            while i < n and not lines[i].strip():
                i += 1
            if i >= n:
                raise MeshFileError(f"{source}: the Netgen section {word} has no value")
            out[word] = lines[i : i + 1]
            i += 1
            continue
        if word == "curvedelements":  # Netgen's high-order geometry, last before endmesh
            break
        if word not in _COUNTED and word != "identificationtypes":
            raise MeshFileError(f"{source}: unknown Netgen mesh section {word[:40]!r}")
        while i < n and not lines[i].strip():
            i += 1
        try:
            count = int(lines[i].split()[0]) if i < n else -1
        except (ValueError, IndexError):
            count = -1
        if count < 0:
            raise MeshFileError(f"{source}: the Netgen section {word} has no count")
        i += 1
        if word == "identificationtypes":  # one line of ``count`` numbers
            count = 1 if count else 0
        named = word in _NAMES or word in ("identificationnames", "edgedescriptors")
        if named:  # names: blank lines between them are skipped
            rows = []
            while i < n and len(rows) < count:
                if lines[i].strip():
                    rows.append(lines[i])
                i += 1
        else:
            rows = lines[i : i + count]
            i += count
        # a numbers row never starts with a letter: that is the next section's keyword
        cut = any(not r.strip() or (r.strip()[0].isalpha() and not named) for r in rows)
        if len(rows) < count or cut:
            raise MeshFileError(
                f"{source}: the Netgen section {word} announces {count} lines; fewer follow"
            )
        out[word] = rows
    return out


def _numbers(rows: list[str], width: int | None, what: str, source: str, kind=np.float64):
    """The numbers of ``rows`` as a (len(rows), width) array (``width`` None: the
    rows' common width), parsed in one call; ``MeshFileError`` when they are not that."""
    if not rows:
        return np.zeros((0, width or 0), kind)
    joined = " ".join(rows)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a word among the numbers: unreadable
            values = np.fromstring(joined, dtype=np.float64, sep=" ")
    except (ValueError, DeprecationWarning) as e:
        raise MeshFileError(
            f"{source}: unreadable numbers in Netgen section {what} ({e})"
        ) from None
    if width is None:
        if len(values) % len(rows):
            raise ValueError("rows of different lengths")
        width = len(values) // len(rows)
    if len(values) != width * len(rows) or not np.isfinite(values).all():
        raise MeshFileError(
            f"{source}: Netgen section {what}: {len(values)} numbers for {len(rows)} rows "
            f"of {width}, or a number that is not finite"
        )
    table = values.reshape(len(rows), width)
    if kind is not np.float64:
        if (table != np.round(table)).any() or np.abs(table).max(initial=0) >= 2**62:
            raise MeshFileError(f"{source}: Netgen section {what} holds a non-integral id")
        table = table.astype(kind)
    return table


def _volume_elements(rows: list[str], source: str) -> tuple[np.ndarray, np.ndarray]:
    """(tets (m, 4) 0-based in VTK's order, material numbers (m,)) of ``volumeelements``
    (rows: matnr np p1 .. pnp); ``MeshInputError`` naming other elements."""
    from ._io import note_mid_nodes, reading_linear

    counts = np.array([ln.split()[1] if len(ln.split()) > 1 else "0" for ln in rows[:1]])
    table = None
    if reading_linear() and len(counts) and counts[0] == "10":
        # second-order tets as their corners (``jtet.load(path, linear=True)``)
        try:
            table = _numbers(rows, 12, "volumeelements", source, np.int64)
        except MeshFileError:
            table = None
        if table is not None and (table[:, 1] == 10).all():
            nodes = table[:, 2:] - 1
            note_mid_nodes(nodes[:, 4:], nodes[:, _MID_EDGES])  # curved ones are kept
            return nodes[:, :4][:, _SWAP], table[:, 0]
        table = None
    if len(counts) and counts[0] == "4":
        try:
            table = _numbers(rows, 6, "volumeelements", source, np.int64)
        except MeshFileError:
            table = None
    if table is None or (table[:, 1] != 4).any():
        from ._io import _non_tet_message

        sizes = np.array([len(ln.split()) - 2 for ln in rows])
        kinds = {4: "tetra", 5: "pyramid", 6: "wedge", 8: "hexahedron", 10: "tetra10"}
        found, number = np.unique(sizes, return_counts=True)
        bad = [
            (kinds.get(int(k), f"{k}-node element"), int(c))
            for k, c in zip(found, number, strict=True)
            if k != 4
        ]
        if not bad:
            raise MeshFileError(f"{source}: unreadable Netgen volume elements")
        raise MeshInputError(
            _non_tet_message(source, [b[0] for b in bad], [b[1] for b in bad], True)
        )
    return table[:, 2:6][:, _SWAP] - 1, table[:, 0]


def _section_table(sections: dict, names: tuple, source: str):
    """(the first of the sections ``names`` the file has, its rows' numbers; None when
    the rows differ in length), or (None, None) when it has none of them."""
    found = next((name for name in names if sections.get(name)), None)
    if found is None:
        return None, None
    try:
        return found, _numbers(sections[found], None, found, source)
    except ValueError:
        return found, None


def _ids(table: np.ndarray, columns: list, what: str, source: str) -> np.ndarray:
    """``table``'s ``columns`` as int64; ``MeshFileError`` for a non-integral one."""
    ids = table[:, columns]
    if (ids != np.round(ids)).any():
        raise MeshFileError(f"{source}: Netgen {what} hold a non-integral id")
    return ids.astype(np.int64)


def _surface_elements(sections: dict, source: str) -> tuple[np.ndarray, np.ndarray]:
    """(triangles (k, 3) 0-based, boundary-condition numbers (k,)) of the surface
    elements (rows: surfnr bcnr domin domout np p1 p2 p3 [geometry info per point]);
    with ``load(..., linear=True)``, second-order ones (np 6: the nodes of their edges
    after the corners) as their corners."""
    from ._io import note_mid_nodes, reading_linear

    found, table = _section_table(sections, _SURFACE, source)
    if found is None:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    sizes = (3, 6) if reading_linear() else (3,)
    if (
        table is None
        or table.shape[1] < 8
        or (table[:, 4] != table[0, 4]).any()
        or table[0, 4] not in sizes
        or table.shape[1] < 5 + table[0, 4]
    ):
        warnings.warn(
            f"{source}: Netgen surface elements other than triangles (or of mixed kinds); "
            "none of them is kept as a protected face",
            stacklevel=4,
        )
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    ids = _ids(table, [1, 5, 6, 7], "surface elements", source)
    if table[0, 4] == 6:  # the edge nodes: the tets' (their curved ones come from there)
        note_mid_nodes(_ids(table, [8, 9, 10], "surface elements", source) - 1)
    return ids[:, 1:] - 1, ids[:, 0]


def _edge_segments(sections: dict, source: str) -> tuple[np.ndarray, np.ndarray]:
    """(edges (k, 2) 0-based, edge numbers (k,)) of the edge segments: ``gi3`` rows
    "p1 p2 trignum1 trignum2 dist1 dist2 edgenr-1", the older ones "si 0 p1 p2 ...";
    an unreadable section is ignored with a warning (the edges are the geometry's)."""
    try:
        found, table = _section_table(sections, _EDGES, source)
    except MeshFileError:
        found, table = next(name for name in _EDGES if sections.get(name)), None
    if found is None:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    # gi3: p1 p2 ... edgenr - 1 (numbered from 0); older: si 0 p1 p2 ...
    cols, shift = ([0, 1, 6], 1) if found == "edgesegmentsgi3" else ([2, 3, 0], 0)
    if table is None or table.shape[1] <= max(cols):
        warnings.warn(f"{source}: unreadable Netgen {found}; its edges are not kept", stacklevel=4)
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    ids = _ids(table, cols, found, source)
    return ids[:, :2] - 1, ids[:, 2] + shift


# ---------------------------------------------------------------------------------------
# writing


def write_vol(mesh, path: Path, quad=None) -> None:
    """``mesh`` as a Netgen ``.vol`` file at ``path`` (see the module's docstring); with
    ``quad`` (``_quadratic.quadratic_mesh(mesh)``) its tets and surface elements are
    second order, as Netgen's ``Mesh.SecondOrder`` writes them: 10-node tets (edge
    nodes in ``_MID_EDGES``' order) and 6-node triangles (the nodes of the edges
    opposite their first, second and third corner)."""
    from ._io import format_rows
    from ._topology import TET_FACES, _group, match_rows, row_keys

    def edge_nodes(cells: np.ndarray, pairs: np.ndarray) -> np.ndarray:
        """The node of each edge ``pairs`` (local corner pairs) of ``cells``."""
        ends = cells[:, pairs].reshape(-1, 2)
        return quad.cells(ends)[:, 2].reshape(len(cells), len(pairs))

    points = np.asarray(mesh.points if quad is None else quad.points, np.float64)
    tets = np.asarray(mesh.tets, np.int64)
    region = np.asarray(mesh.region, np.int64)
    n, m = mesh.n_points, len(tets)
    materials, matnr = np.unique(region, return_inverse=True)
    matnr = matnr + 1 if (materials < 1).any() else region
    # the tet faces (row 4 t + j: face j of tet t) grouped by face of the mesh, each
    # group listing its one or two rows
    sides = np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1)
    perm, ptr, group = _group(row_keys(sides, n))
    count = np.diff(ptr)
    one = perm[ptr[:-1]]
    other = np.where(count == 2, perm[np.minimum(ptr[:-1] + 1, 4 * m - 1)], -1)
    labels = np.asarray(mesh.protected_face_labels, np.int64)
    default = int(max(labels.max(initial=0), 0)) + 1  # the bc number of unlabelled faces
    bc = np.full(len(count), default)
    at = group[match_rows(sides, mesh.protected_faces, n)]  # TetMesh: they are tet faces
    bc[at] = np.where(labels > 0, labels, default)
    # an interface face belongs to the tet of the lower material number (domin), so that
    # all its faces' normals point one way, into the higher one, as Netgen's do
    swap = (other >= 0) & (matnr[np.maximum(other, 0) // 4] < matnr[one // 4])
    one, other = np.where(swap, other, one), np.where(swap, one, other)
    t0, t1 = one // 4, np.where(other >= 0, other // 4, -1)
    r0 = matnr[t0]
    r1 = np.where(t1 >= 0, matnr[np.maximum(t1, 0)], 0)
    keep = (t1 < 0) | (r0 != r1)
    keep[at] = True
    # the face as tet t0 has it, turned so that its normal points out of t0: t0 is behind
    rows = np.flatnonzero(keep)
    tet, local = one[rows] // 4, one[rows] % 4
    tri = tets[tet[:, None], TET_FACES[local]]
    p = points[tri]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    apex = points[tets[tet, local]] - p[:, 0]
    inward = np.einsum("ij,ij->i", normal, apex) > 0
    tri[inward] = tri[inward][:, [0, 2, 1]]
    domin, domout, bcnr = r0[rows], r1[rows], bc[rows]
    _, surfnr = np.unique(np.stack([bcnr, domin, domout], axis=1), axis=0, return_inverse=True)
    corners = tets[:, _SWAP]
    if quad is not None:
        tri = np.concatenate([tri, edge_nodes(tri, np.array([[1, 2], [0, 2], [0, 1]]))], axis=1)
        # the tets' edge nodes by column, not looked up (672k tets: 1 s less)
        corners = np.concatenate([corners, quad.tets[:, 4 + _VTK_COLUMNS]], axis=1)
    surface = np.column_stack(
        [surfnr.reshape(-1) + 1, bcnr, domin, domout, np.full(len(rows), tri.shape[1]), tri + 1]
    )
    volume = np.column_stack([matnr, np.full(m, corners.shape[1]), corners + 1])
    names = mesh.label_names
    material_names = {
        int(k): names.get((3, int(r)), f"region{int(r)}") for k, r in zip(*_first(matnr, region))
    }
    bc_names = {
        int(b): names.get((2, int(b)), f"surface{int(b)}") for b in np.unique(bcnr) if b != default
    }
    if (bcnr == default).any():
        bc_names[default] = "default"
    with open(path, "w") as f:
        f.write("# Generated by jtet\nmesh3d\ndimension\n3\ngeomtype\n0\n\n")
        f.write("# surfnr    bcnr   domin  domout      np      p1      p2      p3\n")
        f.write(f"surfaceelements\n{len(surface)}\n")
        f.write(format_rows(surface, "%d" + " %d" * (surface.shape[1] - 1) + "\n"))
        f.write("\n#  matnr      np      p1      p2      p3      p4\n")
        f.write(f"volumeelements\n{m}\n")
        f.write(format_rows(volume, "%d" + " %d" * (volume.shape[1] - 1) + "\n"))
        edges = np.asarray(mesh.protected_edges, np.int64).reshape(-1, 2)
        edge_numbers = np.maximum(np.asarray(mesh.protected_edge_labels, np.int64), 1)
        segments = np.column_stack(
            [edges + 1, np.full((len(edges), 2), -1), np.zeros((len(edges), 2)), edge_numbers - 1]
        )
        f.write("\n# p1   p2   trignum1   trignum2   dist1   dist2   edsi\n")
        f.write(f"edgesegmentsgi3\n{len(edges)}\n")
        f.write(format_rows(segments, "%d %d %d %d %d %d %d\n"))
        f.write(f"\n#          X             Y             Z\npoints\n{len(points)}\n")
        f.write(format_rows(points, "%.17g %.17g %.17g\n"))
        pins = np.asarray(mesh.protected_vertices, np.int64)
        pin_numbers = np.maximum(np.asarray(mesh.protected_vertex_labels, np.int64), 1)
        f.write(f"\n#          pnum             index\npointelements\n{len(pins)}\n")
        f.write(format_rows(np.column_stack([pins + 1, pin_numbers]), "%d %d\n"))
        if mesh.periodic:  # Netgen's identifications, each of type 2 (periodic)
            pairs = np.concatenate(
                [
                    np.column_stack([lk.pairs + 1, np.full(len(lk.pairs), k + 1)])
                    for k, lk in enumerate(mesh.periodic)
                ]
            )
            f.write(f"\nidentifications\n{len(pairs)}\n")
            f.write(format_rows(pairs, "%d %d %d\n"))
            f.write(f"identificationtypes\n{len(mesh.periodic)}\n")
            f.write(" ".join(["2"] * len(mesh.periodic)) + "\n")
        f.write(f"\nmaterials\n{len(material_names)}\n")
        f.write("".join(f"{k} {_name(v)}\n" for k, v in sorted(material_names.items())))
        width = max(bc_names, default=0)
        f.write(f"\nbcnames\n{width}\n")
        f.write("".join(f"{k} {_name(bc_names.get(k, 'default'))}\n" for k in range(1, width + 1)))
        for section, dim in (("cd2names", 1), ("cd3names", 0)):  # edge and point names
            named = {label: name for (d, label), name in names.items() if d == dim and label >= 1}
            if named:
                width = max(named)
                f.write(f"\n{section}\n{width}\n")
                f.write(
                    "".join(f"{k} {_name(named.get(k, 'default'))}\n" for k in range(1, width + 1))
                )
        f.write("\nendmesh\n")


def _first(numbers: np.ndarray, labels: np.ndarray):
    """(each distinct value of ``numbers``, the label of its first tet)."""
    values, first = np.unique(numbers, return_index=True)
    return values, labels[first]


def _name(name: str) -> str:
    """A name as Netgen reads it: one word (it reads a name up to the line's end, but
    spaces would make other readers split it)."""
    return re.sub(r"\s+", "_", name.strip()) or "default"
