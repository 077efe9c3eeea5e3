"""Netgen / NGSolve ``.vol`` meshes (``jtet._netgen``), against a file Netgen wrote.

``tests/data/netgen_ball.vol.gz`` was written by Netgen 6.2.2608 (``experiments/
ngsolve_vol.py --write-fixture``): a unit cube holding a ball of radius 0.25, materials
"matrix" and "inclusion", boundaries "left" (x = 0), "right" (x = 1), "wall" (the four
other sides) and "interface". ``netgen_ball.json`` holds what NGSolve integrates on it.
"""

import gzip
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from helpers import delaunay_mesh, gmsh_region_volumes

import jtet
from jtet._errors import MeshFileError, MeshInputError
from jtet._topology import TET_FACES
from jtet.cli import main

DATA = Path(__file__).parent / "data"
FIXTURE = DATA / "netgen_ball.vol.gz"
NGSOLVE = json.loads((DATA / "netgen_ball.json").read_text())


def _areas(mesh, label: int) -> float:
    p = np.asarray(mesh.points)[mesh.protected_faces[mesh.protected_face_labels == label]]
    return float(np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum() / 2)


def _labels_named(mesh, dim: int, name: str) -> list[int]:
    return [label for (d, label), n in mesh.label_names.items() if d == dim and n == name]


def test_netgen_file_reads_with_its_materials_and_boundaries():
    """Regions and their volumes as NGSolve integrates them, boundary areas by closed
    form (the cube's sides) and by NGSolve (the interface), tets positive with no
    warning (Netgen's vertex order is the mirror of VTK's)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = jtet.load(FIXTURE)
    assert mesh.n_tets == NGSOLVE["tets"] and (mesh.volumes > 0).all()
    assert mesh.is_valid().ok
    for name, volume in NGSOLVE["volume"].items():
        (label,) = _labels_named(mesh, 3, name)
        assert mesh.volumes[mesh.region == label].sum() == pytest.approx(volume, rel=1e-12)
    closed_form = {"left": 1.0, "right": 1.0, "wall": 4.0}
    for name, area in NGSOLVE["area"].items():
        labels = _labels_named(mesh, 2, name)
        total = sum(_areas(mesh, label) for label in labels)
        assert total == pytest.approx(closed_form.get(name, area), rel=1e-12)
    # the cube's 12 edges and the ball's seam are the geometry's edges; its corners
    assert len(mesh.protected_edges) > 12 and len(mesh.protected_vertices) >= 8


def test_gzipped_and_plain_files_read_the_same(tmp_path):
    plain = tmp_path / "ball.vol"
    plain.write_bytes(gzip.decompress(FIXTURE.read_bytes()))
    a, b = jtet.load(FIXTURE), jtet.load(plain)
    np.testing.assert_array_equal(a.tets, b.tets)
    np.testing.assert_array_equal(a.points, b.points)
    assert a.label_names == b.label_names


def test_round_trip_keeps_everything_netgen_holds(tmp_path):
    mesh = jtet.load(FIXTURE)
    jtet.save(mesh, tmp_path / "out.vol")
    back = jtet.load(tmp_path / "out.vol")
    np.testing.assert_array_equal(back.points, mesh.points)  # 17 digits: exact
    np.testing.assert_array_equal(back.tets, mesh.tets)
    np.testing.assert_array_equal(back.region, mesh.region)
    for name in ("protected_faces", "protected_face_labels", "protected_edges"):
        np.testing.assert_array_equal(getattr(back, name), getattr(mesh, name))
    np.testing.assert_array_equal(back.protected_vertices, mesh.protected_vertices)
    assert back.label_names == mesh.label_names


def test_names_of_every_dimension_round_trip(tmp_path):
    """Material, boundary, edge and point names (Netgen's materials, bcnames, cd2names
    and cd3names) come back from a written file."""
    mesh = jtet.load(FIXTURE)
    edge, vertex = int(mesh.protected_edge_labels[0]), int(mesh.protected_vertex_labels[0])
    names = {**mesh.label_names, (1, edge): "seam", (0, vertex): "corner"}
    jtet.save(mesh.replace(label_names=names), tmp_path / "named.vol")
    assert jtet.load(tmp_path / "named.vol").label_names == names


def _written_surface(path: Path) -> np.ndarray:
    """The (k, 8) rows of a written file's surfaceelements section."""
    lines = path.read_text().splitlines()
    start = lines.index("surfaceelements")
    count = int(lines[start + 1])
    return np.array([ln.split() for ln in lines[start + 2 : start + 2 + count]], np.int64)


def test_surface_elements_point_from_domin_to_domout(tmp_path):
    """Every boundary and interface face is a surface element, its normal (right-hand
    rule) pointing out of the tet of material ``domin`` and into the one of ``domout``
    (0: none), as Netgen's own: checked against the tets by NumPy. Regions 0 and -3,
    which Netgen's materials (from 1) cannot be, become materials 2 and 1, named."""
    base = delaunay_mesh(150, seed=2)
    c = np.asarray(base.points)[base.tets].mean(axis=1)
    mesh = base.replace(region=np.where(c[:, 0] < 0.5, 0, -3))
    with pytest.warns(UserWarning, match="Netgen numbers materials from 1"):
        jtet.save(mesh, tmp_path / "m.vol")
    rows = _written_surface(tmp_path / "m.vol")
    tri, domin, domout = rows[:, 5:8] - 1, rows[:, 2], rows[:, 3]
    material = np.where(mesh.region == -3, 1, 2)
    faces = np.sort(mesh.tets[:, TET_FACES], axis=2).reshape(-1, 3)
    keys, counts = np.unique(faces, axis=0, return_counts=True)
    owners = {tuple(f): [] for f in keys.tolist()}
    for i, f in enumerate(faces.tolist()):
        owners[tuple(f)].append(i // 4)
    expect = {f for f, ts in owners.items() if len(ts) == 1 or len(set(material[ts])) == 2}
    assert {tuple(f) for f in np.sort(tri, axis=1).tolist()} == expect
    points = np.asarray(mesh.points)
    p = points[tri]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    for k, f in enumerate(np.sort(tri, axis=1).tolist()):
        for t in owners[tuple(f)]:
            apex = points[np.setdiff1d(mesh.tets[t], f)[0]] - p[k, 0]
            side = domin[k] if normal[k] @ apex < 0 else domout[k]
            assert side == material[t]
    back = jtet.load(tmp_path / "m.vol")
    assert back.label_names[(3, 1)] == "region-3" and back.label_names[(3, 2)] == "region0"
    np.testing.assert_array_equal(back.region, material)


def test_improve_cli_reads_and_writes_netgen(tmp_path):
    out = tmp_path / "out.vol"
    args = ["improve", str(FIXTURE), str(out), "-q", "--max-passes", "2", "--perturb", "0"]
    assert main(args) == 0
    mesh, back = jtet.load(FIXTURE), jtet.load(out)
    assert back.is_valid().ok and back.label_names == mesh.label_names
    assert jtet.stats(back).min_dihedral > jtet.stats(mesh).min_dihedral
    for label in (1, 2):  # materials keep their volumes
        before = mesh.volumes[mesh.region == label].sum()
        assert back.volumes[back.region == label].sum() == pytest.approx(before, rel=1e-12)
    for label in np.unique(mesh.protected_face_labels):  # boundaries keep their areas
        assert _areas(back, label) == pytest.approx(_areas(mesh, label), rel=1e-12)


VOL = """mesh3d
dimension
3
geomtype
0
surfaceelements
2
1 7 1 0 3 1 3 2
1 7 1 0 3 2 3 4
volumeelements
{count}
{elements}
points
5
0 0 0
1 0 0
0 1 0
0 0 1
1 1 1
{extra}endmesh
"""
# two tets in Netgen's order (the mirror of VTK's): 1 3 2 4 and 2 3 5 4
TETS = "1 4 1 3 2 4\n1 4 2 3 5 4"


def _vol(tmp_path, count=2, elements=TETS, extra="", name="m.vol") -> Path:
    path = tmp_path / name
    path.write_text(VOL.format(count=count, elements=elements, extra=extra))
    return path


def test_small_file_and_its_identifications(tmp_path):
    m = jtet.load(_vol(tmp_path))
    assert m.n_tets == 2 and (m.volumes > 0).all()
    assert m.protected_face_labels.tolist() == [7, 7]
    ident = "identifications\n3\n1 2 1\n3 5 2\n4 2 1\nidentificationtypes\n2\n 2 2\n"
    m = jtet.load(_vol(tmp_path, extra=ident))
    assert [(link.tags, link.pairs.tolist()) for link in m.periodic] == [
        ((1, 1), [[0, 1], [3, 1]]),
        ((2, 2), [[2, 4]]),
    ]


def test_older_and_stl_geometry_sections(tmp_path):
    """Netgen writes ``surfaceelementsgi`` (STL geometries: a triangle number per point)
    and, before 6.2, ``edgesegmentsgi2`` rows "si 0 p1 p2 trignum1 trignum2 surfnr1
    surfnr2 ednr1 dist1 ednr2 dist2": the same faces, edges and labels come out."""
    text = VOL.format(
        count=2, elements=TETS, extra="edgesegmentsgi2\n1\n4 0 1 2 -1 -1 1 2 3 0 3 1\n"
    )
    text = text.replace(
        "1 7 1 0 3 1 3 2\n1 7 1 0 3 2 3 4", "1 7 1 0 3 1 3 2 5 6 7\n1 7 1 0 3 2 3 4 8 9 10"
    )
    (tmp_path / "gi.vol").write_text(text.replace("surfaceelements\n", "surfaceelementsgi\n"))
    m = jtet.load(tmp_path / "gi.vol")
    assert m.protected_faces.tolist() == [
        [0, 1, 2],
        [1, 2, 3],
    ] and m.protected_face_labels.tolist() == [7, 7]
    assert m.protected_edges.tolist() == [[0, 1]] and m.protected_edge_labels.tolist() == [4]


def _identified(path: Path) -> list[tuple[int, int, int]]:
    lines = (
        gzip.decompress(path.read_bytes()).decode() if path.suffix == ".gz" else path.read_text()
    )
    lines = lines.splitlines()
    start = lines.index("identifications")
    rows = lines[start + 2 : start + 2 + int(lines[start + 1])]
    return sorted(tuple(int(v) for v in row.split()) for row in rows)


def test_periodic_netgen_mesh_keeps_its_identifications(tmp_path):
    """Netgen's cube periodic in x and y: the identifications become two periodic links,
    the run keeps their vertices and the triangles of the periodic faces, and the output
    holds the same identifications (NGSolve reads them back: experiments/ngsolve_vol.py)."""
    path = DATA / "netgen_periodic.vol.gz"
    mesh = jtet.load(path)
    assert [link.tags for link in mesh.periodic] == [(1, 1), (2, 2)]
    result = jtet.improve(mesh, check=True)
    assert result.stats_after.min_dihedral > result.stats_before.min_dihedral
    jtet.save(result.mesh, tmp_path / "out.vol")
    assert _identified(tmp_path / "out.vol") == _identified(path)
    back = jtet.load(tmp_path / "out.vol")
    points, before = np.asarray(back.points), np.asarray(mesh.points)
    for link in back.periodic:  # the linked vertices did not move
        np.testing.assert_array_equal(points[link.pairs], before[link.pairs])
    x0 = np.sort(back.protected_faces[(points[back.protected_faces][:, :, 0] == 0).all(1)], 1)
    x0_before = np.sort(
        mesh.protected_faces[(before[mesh.protected_faces][:, :, 0] == 0).all(1)], 1
    )
    assert sorted(map(tuple, x0.tolist())) == sorted(map(tuple, x0_before.tolist()))


@pytest.mark.parametrize(
    ("count", "elements", "extra", "error", "match"),
    [
        (2, TETS, "strangesection\n1\n1\n", MeshFileError, "unknown Netgen mesh section"),
        (3, TETS, "", MeshFileError, "announces 3 lines"),
        (2, "1 4 1 3 2 4\n1 4 2 3 x 4", "", MeshFileError, "unreadable Netgen volume"),
        (1, "1 8 1 2 3 4 5 1 2 3", "", MeshInputError, "hexahedron"),
        (1, "1 10 1 2 3 4 5 1 2 3 4 5", "", MeshInputError, "tetra10"),
        (2, "1 4 1 3 2 4\n1 4 2 3 5 9", "", MeshInputError, "out of range|index"),
    ],
)
def test_bad_netgen_files_say_why(tmp_path, count, elements, extra, error, match):
    with pytest.raises(error, match=match):
        jtet.load(_vol(tmp_path, count, elements, extra))


def test_bad_netgen_files_without_sections(tmp_path):
    (tmp_path / "a.vol").write_text("mesh2d\n")
    with pytest.raises(MeshFileError, match="mesh3d"):
        jtet.load(tmp_path / "a.vol")
    (tmp_path / "b.vol").write_text("mesh3d\ndimension\n2\npoints\n0\nendmesh\n")
    with pytest.raises(MeshInputError, match="2-D"):
        jtet.load(tmp_path / "b.vol")
    (tmp_path / "c.vol").write_text("mesh3d\ndimension\n3\npoints\n0\nendmesh\n")
    with pytest.raises(MeshInputError, match="no points or no volume elements"):
        jtet.load(tmp_path / "c.vol")
    (tmp_path / "e.vol").write_text("mesh3d\ndimension\n")  # fuzz: cut after a keyword
    with pytest.raises(MeshFileError, match="dimension has no value"):
        jtet.load(tmp_path / "e.vol")
    (tmp_path / "d.vol.gz").write_bytes(b"not gzip at all")
    with pytest.raises(MeshFileError, match="cannot read"):
        jtet.load(tmp_path / "d.vol.gz")


def test_second_order_tets_read_as_linear(tmp_path):
    """A 10-node volume element (Netgen's second order: the corners first) is refused
    with the --linear hint and read as its corners with ``linear=True``."""
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    listed = corners[[0, 2, 1, 3]]  # the element's corners as the file lists them
    edges = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]  # of the listed corners
    points = np.vstack([corners, [(listed[a] + listed[b]) / 2 for a, b in edges]])
    text = "mesh3d\ndimension\n3\nvolumeelements\n1\n1 10 1 3 2 4 5 6 7 8 9 10\n"
    text += f"points\n{len(points)}\n" + "".join(f"{x} {y} {z}\n" for x, y, z in points)
    path = tmp_path / "tet10.vol"
    path.write_text(text + "endmesh\n")
    with pytest.raises(MeshInputError, match="--linear"):
        jtet.load(path)
    with pytest.warns(UserWarning, match="6 mid-edge node"):
        mesh = jtet.load(path, linear=True)
    np.testing.assert_array_equal(mesh.points, corners)
    np.testing.assert_array_equal(mesh.tets, [[0, 1, 2, 3]])  # Netgen's order undone
    assert not mesh.has_curved_edges  # every edge node at its edge's midpoint


def test_netgen_second_order_file_keeps_its_curved_ball(tmp_path):
    """Netgen's own second-order file (``netgen_ball_o2.vol.gz``: ``Mesh.SecondOrder``
    of the ball in the cube at maxh 0.4) read with ``linear=True``: its boundaries
    from the 6-node surface elements, and as curved edges exactly the edges of the
    interface's triangles, their nodes on the sphere. Written quadratic, Gmsh's own
    Jacobians give the ball the volume of Netgen's curved ball: 1.2e-3 off the
    sphere's, where the linear ball is 9.4e-2 off, and the two materials fill the cube."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = jtet.load(DATA / "netgen_ball_o2.vol.gz", linear=True)
    names = {n for (d, _), n in mesh.label_names.items() if d == 2}
    assert names == {"left", "right", "wall", "interface"}
    interface = np.isin(mesh.protected_face_labels, _labels_named(mesh, 2, "interface"))
    faces = mesh.protected_faces[interface]
    edges = np.unique(np.sort(faces[:, [[0, 1], [1, 2], [0, 2]]].reshape(-1, 2), axis=1), axis=0)
    np.testing.assert_array_equal(mesh.curved_edges.edges, edges)
    radius = np.linalg.norm(mesh.curved_edges.points - 0.5, axis=1)
    np.testing.assert_allclose(radius, 0.25, rtol=0, atol=1e-15)
    jtet.save(mesh, tmp_path / "ball.msh", quadratic=True)
    jtet.save(mesh, tmp_path / "linear.msh")
    volumes, types = gmsh_region_volumes(tmp_path / "ball.msh")
    assert types == {11}  # 10-node tets
    sphere = 4 / 3 * np.pi * 0.25**3
    assert abs(volumes["inclusion"] - sphere) / sphere < 2e-3
    linear, _ = gmsh_region_volumes(tmp_path / "linear.msh")
    # the cube is filled: to Gmsh's integration, whose rule sums the linear mesh's
    # straight tets to 1 - 3.4e-12 too
    assert abs(volumes["inclusion"] + volumes["matrix"] - 1) < 1e-10
    assert abs(linear["inclusion"] + linear["matrix"] - 1) < 1e-10
    assert abs(linear["inclusion"] - sphere) / sphere > 5e-2


def _vol_cells(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (n, 3), volume elements (m, 10), surface elements (k, 6)) 0-based, of a
    second-order .vol file, parsed line by line (independently of jtet's reader)."""
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as f:
        lines = [ln.strip() for ln in f]

    def section(name: str, width: int, first: int) -> np.ndarray:
        at = next(i for i, ln in enumerate(lines) if ln.startswith(name))
        count = int(lines[at + 1])
        rows = [ln.split() for ln in lines[at + 2 : at + 2 + count]]
        return np.array([[float(v) for v in r[first : first + width]] for r in rows])

    points = section("points", 3, 0)
    volume = section("volumeelements", 10, 2).astype(np.int64) - 1
    surface = section("surfaceelements", 6, 5).astype(np.int64) - 1
    return points, volume, surface


def _nodes_by_edge(points, cells, pairs) -> dict:
    """{(sorted corner coordinates of an edge): its node's coordinates} of ``cells``
    whose edge nodes follow their corners on the corner pairs ``pairs``."""
    out = {}
    corners = len(cells[0]) - len(pairs)
    for k, (a, b) in enumerate(pairs):
        for row in cells:
            ends = sorted([tuple(points[row[a]]), tuple(points[row[b]])])
            out[tuple(ends)] = tuple(points[row[corners + k]])
    return out


def test_quadratic_vol_output_has_netgens_nodes(tmp_path):
    """Netgen's second-order file read with --linear and written with quadratic=True:
    parsed by hand, its 10-node tets and 6-node surface elements put on every edge the
    node Netgen's own file has there (Netgen's orders: tets 01 02 03 12 13 23, triangles
    12 02 01), and it reads back the same. (Netgen 6.2.2608 reads the file too, and its
    Gmsh export puts every node where jtet's quadratic mesh has it:
    ``experiments/ngsolve_vol.py --quadratic-check``.)"""
    tet_pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    tri_pairs = [(1, 2), (0, 2), (0, 1)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = jtet.load(DATA / "netgen_ball_o2.vol.gz", linear=True)
        jtet.save(mesh, tmp_path / "q.vol", quadratic=True)
        again = jtet.load(tmp_path / "q.vol", linear=True)
    theirs = _vol_cells(DATA / "netgen_ball_o2.vol.gz")
    ours = _vol_cells(tmp_path / "q.vol")
    for column, pairs in ((1, tet_pairs), (2, tri_pairs)):
        got = _nodes_by_edge(ours[0], ours[column], pairs)
        want = _nodes_by_edge(theirs[0], theirs[column], pairs)
        assert got.keys() == want.keys()
        # the curved nodes are Netgen's to the bit; jtet puts a straight edge's node at
        # 0.5 (a + b), which may differ from Netgen's by an ulp
        difference = np.array([got[k] for k in want]) - np.array(list(want.values()))
        assert np.abs(difference).max() <= 2.3e-16
    np.testing.assert_array_equal(again.points, mesh.points)
    np.testing.assert_array_equal(again.tets, mesh.tets)
    np.testing.assert_array_equal(again.curved_edges.points, mesh.curved_edges.points)
    np.testing.assert_array_equal(again.protected_faces, mesh.protected_faces)
    assert again.label_names == mesh.label_names
