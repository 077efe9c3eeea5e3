"""Mesh I/O: format round trips, region labels, bad inputs, atomic saves, demo meshes."""

import os
import sys
import warnings
from pathlib import Path

import meshio
import numpy as np
import pytest
import pyvista as pv
from helpers import delaunay_mesh

import jtet
from jtet import _io
from jtet._errors import MeshFileError, MeshInputError
from jtet._quality import tet_dihedrals
from jtet._topology import CORNER
from jtet.cli import main

FORMATS = ["vtu", "vtk", "msh", "mesh", "meshb", "node", "ele", "xdmf"]

# Two positively oriented tets sharing the face (1, 2, 3), written by hand below in
# every file format (0-based here; files are 1-based).
PTS5 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=np.float64)
TETS2 = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])


def _vol6(points, tets):
    p = points[tets]
    return np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))


@pytest.fixture(scope="module")
def labelled():
    """A small Delaunay mesh with 3 regions (by x), protected faces and edges."""
    m = delaunay_mesh(60, seed=3)
    centroid_x = m.points[m.tets].mean(axis=1)[:, 0]
    region = np.digitize(centroid_x, [0.33, 0.66]) + 1
    return m.replace(
        region=region, protected_faces=m.tets[:5, :3], protected_edges=m.tets[:4, [0, 3]]
    )


def _quiet_save(*args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return jtet._io.save(*args, **kw)


# ---------------------------------------------------------------------------------------
# round trips


@pytest.mark.parametrize("ext", FORMATS)
def test_round_trip(tmp_path, labelled, ext):
    path = tmp_path / f"mesh.{ext}"
    out = _quiet_save(labelled, str(path))
    back = _io.load(str(path))
    np.testing.assert_array_equal(back.points, labelled.points)  # bit-exact float64
    np.testing.assert_array_equal(back.tets, labelled.tets)
    np.testing.assert_array_equal(back.region, labelled.region)
    assert back.points.dtype == np.float64 and back.tets.dtype == np.int64
    assert (back.volumes > 0).all()
    tetgen = {"mesh.node", "mesh.ele"} | ({"mesh.face"} if len(labelled.protected_faces) else set())
    expected = tetgen if ext in ("node", "ele") else {path.name}
    if ext == "xdmf":
        expected = {path.name, "mesh.h5"}  # its heavy data
    assert {p.name for p in tmp_path.iterdir()} == expected  # no temp files left behind
    assert out.name in expected


@pytest.mark.parametrize("ext", ["vtu", "vtk"])
def test_vtk_keeps_cell_data_and_protection(tmp_path, labelled, ext):
    q = labelled.quality()
    vec = np.arange(3 * labelled.n_tets, dtype=np.float64).reshape(-1, 3)
    path = tmp_path / f"m.{ext}"
    _io.save(labelled, path, cell_data={"quality": q, "vec": vec})
    back = _io.load(path)
    np.testing.assert_array_equal(back.protected_faces, labelled.protected_faces)
    np.testing.assert_array_equal(back.protected_edges, labelled.protected_edges)
    grid = pv.read(path)
    np.testing.assert_array_equal(grid.cell_data["quality"], q)
    np.testing.assert_array_equal(grid.cell_data["vec"], vec)
    np.testing.assert_array_equal(grid.cell_data["region"], labelled.region)


def test_msh_keeps_cell_data_and_physical_tags(tmp_path, labelled):
    plain = labelled.replace(protected_faces=None, protected_edges=None)
    q = plain.quality()
    path = tmp_path / "m.msh"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing is left out
        _io.save(plain, path, cell_data={"quality": q})
    m = meshio.gmsh.read(path)
    np.testing.assert_array_equal(m.cell_data["quality"][0], q)
    np.testing.assert_array_equal(m.cell_data["gmsh:physical"][0], plain.region)
    # with protected entities (element blocks of their own) the per-tet arrays are left
    # out, with a warning: meshio would refuse the file
    with pytest.warns(UserWarning, match=r"1 cell array\(s\) \(with protected triangles, lines"):
        _io.save(labelled, path, cell_data={"quality": q})
    assert "quality" not in meshio.gmsh.read(path).cell_data


@pytest.mark.parametrize("ext", ["msh", "mesh", "meshb", "vtu", "vtk", "node", "xdmf"])
def test_protected_entities_round_trip(tmp_path, labelled, ext):
    """Protected faces, edges and vertices with their labels come back from every format
    that stores them: Gmsh triangles, lines and points tagged with their labels
    (physical groups); Medit triangles and edges with references, RequiredVertices
    without labels; VTK field data; TetGen's .face file
    with the face labels as boundary markers (no edges or vertices).
    A warning names what a format leaves out."""
    mesh = labelled.replace(
        protected_faces=labelled.protected_faces,
        protected_face_labels=np.arange(len(labelled.protected_faces)) + 11,
        protected_edges=labelled.protected_edges,
        protected_edge_labels=np.arange(len(labelled.protected_edges)) + 31,
        protected_vertices=[7, 3, 12],
        protected_vertex_labels=[41, 42, 43],
    )
    assert mesh.protected_vertex_labels.tolist() == [42, 41, 43]  # with their sorted ids
    path = tmp_path / f"m.{ext}"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _io.save(mesh, path)
    dropped = " ".join(str(w.message) for w in caught)
    back = _io.load(path)
    names = ("protected_faces", "protected_face_labels", "protected_edges",
             "protected_edge_labels", "protected_vertices", "protected_vertex_labels")  # fmt: skip
    stored = {"node": names[:2], "meshb": names[:5], "mesh": names[:5]}.get(ext, names)
    for name in names:
        if name in stored:
            np.testing.assert_array_equal(getattr(back, name), getattr(mesh, name), err_msg=name)
        elif name == "protected_vertex_labels" and ext in ("mesh", "meshb"):
            assert back.protected_vertex_labels.tolist() == [0, 0, 0]
        else:
            assert len(getattr(back, name)) == 0, name
            if not name.endswith("labels"):  # the entities are named in the warning
                assert name.replace("_", " ") in dropped, (name, dropped)
    np.testing.assert_array_equal(back.region, mesh.region)
    assert back.protected_vertices.tolist() == ([3, 7, 12] if ext != "node" else [])


@pytest.mark.parametrize("ext", ["msh", "mesh", "vtu", "node", "xdmf"])
def test_labelled_protected_faces_round_trip(tmp_path, labelled, ext):
    # Gmsh physical surfaces / Medit triangle references / VTK field data: a Gmsh ->
    # jtet -> solver chain keeps its boundary-condition groups
    labels = np.arange(len(labelled.protected_faces)) + 11
    mesh = labelled.replace(protected_faces=labelled.protected_faces, protected_face_labels=labels)
    path = tmp_path / f"m.{ext}"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # protected edges / cell arrays a format drops
        _io.save(mesh, path, cell_data={"quality": mesh.quality()})
    back = _io.load(path)
    np.testing.assert_array_equal(back.protected_faces, mesh.protected_faces)
    np.testing.assert_array_equal(back.protected_face_labels, labels)
    np.testing.assert_array_equal(back.region, mesh.region)


def test_tetgen_face_file_follows_the_mesh(tmp_path, labelled):
    """The .face file beside a TetGen output is the mesh's: written with its protected
    faces, refused like the other files without overwrite, removed when the new mesh
    has none (else the next load would read the old mesh's faces)."""
    path = tmp_path / "m.node"
    faces = labelled.replace(protected_edges=None)
    _io.save(faces, path)
    text = (tmp_path / "m.face").read_text().splitlines()
    assert text[1] == f"{len(faces.protected_faces)} 1"
    row = [int(v) for v in text[2].split()]
    assert row == [0, *faces.protected_faces[0], faces.protected_face_labels[0]]
    bare = labelled.replace(protected_faces=None, protected_edges=None)
    _io.save(bare, tmp_path / "n.node")
    assert _listing(tmp_path) == ["m.ele", "m.face", "m.node", "n.ele", "n.node"]
    (tmp_path / "k.face").write_bytes((tmp_path / "m.face").read_bytes())
    with pytest.raises(MeshFileError, match=r"k\.face: the file exists"):
        _io.save(bare, tmp_path / "k.node", overwrite=False)
    assert "k.node" not in _listing(tmp_path)
    _io.save(bare, tmp_path / "k.node")
    assert "k.face" not in _listing(tmp_path)
    assert len(_io.load(tmp_path / "k.node").protected_faces) == 0
    _io.save(bare, path)  # replaces m.node / m.ele and removes m.face
    assert _listing(tmp_path) == ["k.ele", "k.node", "m.ele", "m.node", "n.ele", "n.node"]


@pytest.mark.parametrize("ext", ["mesh", "node"])
def test_region_only_formats_warn_about_dropped_data(tmp_path, labelled, ext):
    with pytest.warns(UserWarning, match="stores only the region"):
        _io.save(labelled, tmp_path / f"m.{ext}", cell_data={"q": labelled.quality()})


def test_grid_round_trip(labelled):
    q = labelled.quality()
    grid = labelled.to_pyvista(cell_data={"q": q})
    assert isinstance(grid, pv.UnstructuredGrid)
    assert (np.asarray(grid.celltypes) == pv.CellType.TETRA).all()
    np.testing.assert_array_equal(grid.cell_data["region"], labelled.region)
    np.testing.assert_array_equal(grid.cell_data["q"], q)
    back = jtet.TetMesh.from_pyvista(grid)
    np.testing.assert_array_equal(back.points, labelled.points)
    np.testing.assert_array_equal(back.tets, labelled.tets)
    np.testing.assert_array_equal(back.region, labelled.region)
    np.testing.assert_array_equal(back.protected_faces, labelled.protected_faces)


def test_mesh_to_grid_rejects_bad_cell_data(labelled):
    with pytest.raises(MeshInputError, match="one value per tet"):
        _io.mesh_to_grid(labelled, {"q": np.zeros(labelled.n_tets + 1)})
    with pytest.raises(MeshInputError, match="region"):
        _io.mesh_to_grid(labelled, {"region": labelled.region})
    with pytest.raises(MeshInputError, match="holds <U1 values, not numbers"):
        _io.save(labelled, "never.xdmf", cell_data={"name": np.array(["a"] * labelled.n_tets)})
    assert not Path("never.xdmf").exists()


def test_from_pyvista_wraps_vtk_and_meshio_objects():
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: TETS2}, PTS5)
    grid.cell_data["gmsh:physical"] = np.array([4.0, 5.0])  # integral floats are accepted
    for obj in (grid, pv.UnstructuredGrid(grid).copy(), meshio.Mesh(PTS5, [("tetra", TETS2)])):
        m = jtet.TetMesh.from_pyvista(obj)
        np.testing.assert_array_equal(m.tets, TETS2)
    vtk_obj = grid.copy()
    m = jtet.TetMesh.from_pyvista(vtk_obj)
    np.testing.assert_array_equal(m.region, [4, 5])


def test_region_array_preference_and_bad_labels():
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: TETS2}, PTS5)
    grid.cell_data["CellEntityIds"] = np.array([1, 2])
    grid.cell_data["medit:ref"] = np.array([3, 4])
    assert jtet.TetMesh.from_pyvista(grid).region.tolist() == [3, 4]
    grid.cell_data["region"] = np.array([5, 6])
    assert jtet.TetMesh.from_pyvista(grid).region.tolist() == [5, 6]
    grid.cell_data["region"] = np.array([0.5, 1.0])
    with pytest.raises(MeshInputError, match="integer region labels"):
        jtet.TetMesh.from_pyvista(grid)


# ---------------------------------------------------------------------------------------
# region labels from hand-written files of other tools

MSH22 = """$MeshFormat
2.2 0 8
$EndMeshFormat
$PhysicalNames
3
2 3 "skin"
3 7 "lower"
3 9 "upper"
$EndPhysicalNames
$Nodes
5
1 0 0 0
2 1 0 0
3 0 1 0
4 0 0 1
5 1 1 1
$EndNodes
$Elements
5
1 15 2 0 1 1
2 1 2 0 1 1 2
3 2 2 3 1 1 2 3
4 4 2 7 1 1 2 3 4
5 4 2 9 2 2 3 4 5
$EndElements
"""

MSH41 = """$MeshFormat
4.1 0 8
$EndMeshFormat
$PhysicalNames
3
2 3 "skin"
3 7 "lower"
3 9 "upper"
$EndPhysicalNames
$Entities
0 0 1 2
1 0 0 0 1 1 0 1 3 0
1 0 0 0 1 1 1 1 7 0
2 0 0 0 1 1 1 1 9 0
$EndEntities
$Nodes
2 5 1 5
3 1 0 4
1
2
3
4
0 0 0
1 0 0
0 1 0
0 0 1
3 2 0 1
5
1 1 1
$EndNodes
$Elements
3 3 1 3
2 1 2 1
1 1 2 3
3 1 4 1
2 1 2 3 4
3 2 4 1
3 2 3 4 5
$EndElements
"""

MEDIT = """MeshVersionFormatted 2
Dimension 3
Vertices
5
0 0 0 1
1 0 0 1
0 1 0 1
0 0 1 1
1 1 1 1
Triangles
1
1 2 3 10
Tetrahedra
2
1 2 3 4 4
2 3 4 5 6
End
"""

TETGEN_NODE = """# TetGen nodes, 1-based, with a boundary marker column
5 3 0 1
1 0 0 0 1
2 1 0 0 1
3 0 1 0 1
4 0 0 1 1
5 1 1 1 1
"""

TETGEN_ELE = """# one region attribute per tet
2 4 1
1 1 2 3 4 -1
2 2 3 4 5 3
"""


@pytest.mark.parametrize(("name", "text"), [("v22.msh", MSH22), ("v41.msh", MSH41)])
def test_gmsh_physical_volumes_become_regions(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    m = _io.load(path)  # the triangle, line and vertex elements are ignored
    np.testing.assert_array_equal(m.points, PTS5)
    np.testing.assert_array_equal(m.tets, TETS2)
    assert m.region.tolist() == [7, 9]
    # pyvista reads the same file as a mixed grid; from_pyvista ignores the 0-2-D cells.
    g = pv.read(path)
    assert g.n_cells > 2
    assert jtet.TetMesh.from_pyvista(g).region.tolist() == [7, 9]


def _msh41(volume_tags: tuple[str, str], surface_tag: str = "1 3") -> str:
    """``MSH41`` with the physical tags of volume entities 1, 2 and surface 1 replaced
    ("n t1 ..." lists; "0" for none), as Gmsh writes them with ``Mesh.SaveAll = 1``."""
    lines = MSH41.splitlines()
    i = lines.index("$Entities") + 2
    lines[i] = f"1 0 0 0 1 1 0 {surface_tag} 0"
    lines[i + 1] = f"1 0 0 0 1 1 1 {volume_tags[0]} 0"
    lines[i + 2] = f"2 0 0 0 1 1 1 {volume_tags[1]} 0"
    return "\n".join(lines) + "\n"


def test_gmsh41_tets_in_no_physical_group(tmp_path):
    # meshio 5.3 alone refuses these files ("Incompatible cell data 'gmsh:physical'")
    path = tmp_path / "m.msh"
    path.write_text(_msh41(("0", "0")))  # a physical surface only: the volume entities
    assert _io.load(path).region.tolist() == [1, 2]
    path.write_text(_msh41(("0", "0"), surface_tag="0"))  # no physical group at all
    assert _io.load(path).region.tolist() == [1, 2]
    path.write_text(_msh41(("1 7", "0")))  # one volume in a group, one in none
    with pytest.warns(UserWarning, match="1 of 2 tets are in no physical group"):
        assert _io.load(path).region.tolist() == [7, 0]
    # the patched reader is meshio's own again after each read
    from meshio.gmsh import _gmsh41

    assert _gmsh41._read_elements.__module__ == _gmsh41.__name__


def _with_data(text: str, element_ids: tuple, node_ids: tuple) -> str:
    """An ASCII Gmsh file with a view's ``$ElementData`` / ``$NodeData`` over some of its
    elements / nodes appended, as Gmsh saves a view with its mesh."""
    blocks = [
        f'${tag}\n1\n"err"\n1\n0.0\n3\n0\n1\n{len(ids)}\n'
        + "".join(f"{i} {0.25 * i}\n" for i in ids)
        + f"$End{tag}\n"
        for tag, ids in (("ElementData", element_ids), ("NodeData", node_ids))
        if ids
    ]
    return text + "".join(blocks)


@pytest.mark.parametrize("on", ["tets", "nodes"])
@pytest.mark.parametrize(
    ("text", "tet_ids"), [(MSH22, (4, 5)), (MSH41, (2, 3))], ids=["v22", "v41"]
)
def test_gmsh_files_with_data_are_read(tmp_path, text, tet_ids, on):
    # a view over the tets or over two nodes saved with the mesh: meshio 5.3 alone
    # refuses it (data on the wrong blocks, too few node values); jtet reads the view
    # over every tet as cell data (by element number: the tets are elements 4-5 of the
    # 2.2 file, 2-3 of the 4.1 one) and names the one over 2 of the 5 nodes as not read
    import meshio

    path = tmp_path / "view.msh"
    if on == "tets":
        path.write_text(_with_data(text, tet_ids, ()))
        refusal = "Incompatible cell data"
    else:
        path.write_text(_with_data(text, (), (2, 3)))
        refusal = "len\\(points\\) = 5"
    with pytest.raises(ValueError, match=refusal):
        meshio.read(path)
    if on == "tets":
        m = _io.load(path)
        np.testing.assert_array_equal(m.cell_data["err"], 0.25 * np.array(tet_ids))
    else:
        with pytest.warns(UserWarning, match="point view 'err' .values at 2 of 5 nodes.; not"):
            m = _io.load(path)
        assert not m.point_data
    np.testing.assert_array_equal(m.tets, TETS2)
    assert m.region.tolist() == [7, 9]
    # the mended readers are meshio's own again after the read
    from meshio.gmsh import _gmsh22, _gmsh41

    assert _gmsh22._read_data.__module__ == _gmsh41._read_data.__module__ == "meshio.gmsh.common"
    assert _gmsh22.read_buffer.__module__ == _gmsh22._read_cells_binary.__module__
    assert _gmsh22.read_buffer.__module__ == _gmsh22.__name__


def test_gmsh22_binary_element_data_over_two_blocks(tmp_path):
    # meshio 5.3 writes such files but its reader splits the data at element 2 (the
    # triangle block gets two values) and refuses them
    import meshio

    tri = np.array([[1, 2, 3]])
    tags = [np.array([3]), np.array([7, 9])]
    written = meshio.Mesh(
        PTS5,
        [meshio.CellBlock("triangle", tri), meshio.CellBlock("tetra", TETS2)],
        cell_data={"gmsh:physical": tags, "gmsh:geometrical": tags, "q": [[0.1], [0.2, 0.3]]},
    )
    path = tmp_path / "b.msh"
    meshio.gmsh.write(str(path), written, fmt_version="2.2", binary=True)
    with pytest.raises(ValueError, match="Incompatible"):
        meshio.read(path)
    m = _io.load(path)
    assert m.region.tolist() == [7, 9]
    assert m.protected_faces.tolist() == [[1, 2, 3]]
    assert m.protected_face_labels.tolist() == [3]
    # the data over all elements, read at the tets' element numbers (2 and 3)
    np.testing.assert_array_equal(m.cell_data["q"], [0.2, 0.3])


def _partitioned_msh41() -> str:
    """``MSH41`` split into two partitions as Gmsh writes it: every element on a partition
    entity (a piece of a model entity, or of the interface between partitions), plus a
    ghost entity holding a copy of the second tet in the first partition."""
    lines = MSH41.splitlines()
    start, end = lines.index("$Elements"), lines.index("$EndElements")
    partitioned = """$PartitionedEntities
2
1
23 1
0 0 2 3
11 2 1 1 1 0 0 0 1 1 0 1 3 0
12 3 1 2 1 2 0 0 0 1 1 1 0 0
21 3 1 1 1 0 0 0 1 1 1 1 7 0
22 3 2 1 2 0 0 0 1 1 1 1 9 0
23 3 2 1 1 0 0 0 1 1 1 1 9 0
$EndPartitionedEntities"""
    elements = """$Elements
5 5 1 5
2 11 2 1
1 1 2 3
2 12 2 1
4 2 3 4
3 21 4 1
2 1 2 3 4
3 22 4 1
3 2 3 4 5
3 23 4 1
5 2 3 4 5"""
    i = lines.index("$EndEntities") + 1
    return "\n".join([*lines[:i], partitioned, *lines[i:start], elements, *lines[end:]]) + "\n"


def test_gmsh41_partitioned(tmp_path):
    # meshio 5.3 alone fails on the partition entities (KeyError); jtet reads the tets by
    # their parent volumes, drops the interface triangle (2, 3, 4) and the ghost copy
    import meshio

    path = tmp_path / "parts.msh"
    path.write_text(_partitioned_msh41())
    with pytest.raises(KeyError):
        meshio.read(path)
    m = _io.load(path)
    np.testing.assert_array_equal(m.tets, TETS2)
    assert m.region.tolist() == [7, 9]
    assert m.protected_faces.tolist() == [[0, 1, 2]]
    assert m.protected_face_labels.tolist() == [3]


def test_gmsh41_partitioned_element_data_leaves_the_ghost_out(tmp_path):
    # a view over the tets (elements 2, 3) and the ghost copy of the second (element 5):
    # the tets' values, in their order
    path = tmp_path / "parts.msh"
    path.write_text(_with_data(_partitioned_msh41(), (3, 5, 2), ()))
    m = _io.load(path)
    np.testing.assert_array_equal(m.tets, TETS2)
    np.testing.assert_array_equal(m.cell_data["err"], [0.5, 0.75])


@pytest.mark.parametrize("binary", [0, 1])
def test_gmsh_partitioned_mesh_reads_as_the_whole_mesh(tmp_path, binary):
    """Two volumes with physical groups, partitioned by Gmsh into 3 (4.1, the default
    format): the same tets, regions and labelled surfaces as the file written before
    partitioning (compared by coordinates: the node order differs)."""
    gmsh = pytest.importorskip("gmsh")
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        gmsh.model.occ.addBox(1, 0, 0, 1, 1, 1)
        gmsh.model.occ.fragment([(3, 1)], [(3, 2)])
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [1], 11)
        gmsh.model.addPhysicalGroup(3, [2], 12)
        gmsh.model.addPhysicalGroup(2, [1, 2], 21)
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.4)
        gmsh.option.setNumber("Mesh.Binary", binary)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(tmp_path / "whole.msh"))
        gmsh.model.mesh.partition(3)
        gmsh.write(str(tmp_path / "parts.msh"))
    finally:
        gmsh.finalize()

    def by_coordinates(m):
        def rows(cells, labels):
            corners = np.sort(m.points[cells].reshape(len(cells), -1).round(12), axis=1)
            return sorted(zip(map(tuple, corners), labels.tolist()))

        return rows(m.tets, m.region), rows(m.protected_faces, m.protected_face_labels)

    whole, parts = _io.load(tmp_path / "whole.msh"), _io.load(tmp_path / "parts.msh")
    assert set(whole.region.tolist()) == {11, 12} and len(whole.protected_faces) > 0
    assert by_coordinates(parts) == by_coordinates(whole)


def _msh22_with(path, elements: list[str]):
    """``MSH22`` with the element lines ``elements`` appended, written to ``path``."""
    lines = MSH22.splitlines()
    start, end = lines.index("$Elements"), lines.index("$EndElements")
    elements = lines[start + 2 : end] + elements
    lines[start + 1 : end] = [str(len(elements)), *elements]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_gmsh_triangles_become_labelled_protected_faces(tmp_path):
    # the two tets share face (2, 3, 4) (1-based); a triangle element there is an embedded
    # or internal surface: protected, so flips and smoothing keep it. The boundary
    # triangle (1, 2, 3) of physical surface 3 is protected with its label, so its
    # patch keeps its border and is written back; (1, 2, 5) is no face of a tet.
    path = _msh22_with(tmp_path / "inner.msh", ["6 2 2 4 1 2 3 4", "7 2 2 4 1 1 2 5"])
    with pytest.warns(UserWarning, match="1 triangle.* not faces of its tets"):
        m = _io.load(path)
    assert m.protected_faces.tolist() == [[0, 1, 2], [1, 2, 3]]
    assert m.protected_face_labels.tolist() == [3, 4]
    assert m.region.tolist() == [7, 9]


def test_vtk_triangles_become_labelled_protected_faces(tmp_path):
    # the same in a VTK grid (Gmsh's VTK export writes its triangles as cells too, with
    # their entities in CellEntityIds)
    cells = {pv.CellType.TETRA: TETS2, pv.CellType.TRIANGLE: np.array([[1, 2, 3], [0, 1, 2]])}
    grid = pv.UnstructuredGrid(cells, PTS5)
    m = jtet.TetMesh.from_pyvista(grid)
    assert m.protected_faces.tolist() == [[0, 1, 2], [1, 2, 3]]
    assert m.protected_face_labels.tolist() == [0, 0]
    grid.cell_data["CellEntityIds"] = np.array([1, 1, 20, 5])  # the tets', then the triangles'
    grid.save(tmp_path / "m.vtu")
    m = _io.load(tmp_path / "m.vtu")
    assert m.protected_face_labels.tolist() == [5, 20] and m.region.tolist() == [1, 1]


def test_every_face_as_unlabelled_triangles_protects_the_boundary_only(tmp_path):
    """A grid that holds every face of its tets as a triangle cell, none labelled (an
    export of all faces): the inner face is on no surface and stays free, as in TetGen's
    ``-f`` listing; the boundary faces are protected."""
    faces = np.unique(
        np.sort(TETS2[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]], 2).reshape(-1, 3), axis=0
    )
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: TETS2, pv.CellType.TRIANGLE: faces}, PTS5)
    m = jtet.TetMesh.from_pyvista(grid)
    assert len(faces) == 7 and len(m.protected_faces) == 6
    assert [1, 2, 3] not in m.protected_faces.tolist()
    grid.cell_data["CellEntityIds"] = np.r_[1, 1, np.where((faces == [1, 2, 3]).all(1), 9, 0)]
    grid.save(tmp_path / "m.vtu")  # labelled, the inner face is a surface of its own
    m = _io.load(tmp_path / "m.vtu")
    assert len(m.protected_faces) == 7 and sorted(m.protected_face_labels.tolist())[-1] == 9


def test_every_edge_as_unlabelled_lines_protects_the_boundary_edges_only():
    """Every edge of a mesh as an unlabelled line cell: the edges inside (on no
    boundary face) stay free, or no edge removal could run; a labelled inner edge is
    a curve of its own and stays protected. Reference: the boundary faces' edges, by
    NumPy."""
    mesh = delaunay_mesh(40, seed=1)
    tets = np.asarray(mesh.tets)
    edges = np.unique(
        np.sort(tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]], 2).reshape(-1, 2), axis=0
    )
    faces, count = np.unique(
        np.sort(tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]], 2).reshape(-1, 3),
        axis=0,
        return_counts=True,
    )
    outer = np.unique(faces[count == 1][:, [[0, 1], [1, 2], [0, 2]]].reshape(-1, 2), axis=0)
    assert len(outer) < len(edges)
    cells = {pv.CellType.TETRA: tets, pv.CellType.LINE: edges}
    grid = pv.UnstructuredGrid(cells, np.asarray(mesh.points))
    np.testing.assert_array_equal(jtet.TetMesh.from_pyvista(grid).protected_edges, outer)
    inner = np.flatnonzero(~(edges[:, None] == outer[None]).all(2).any(1))[0]
    grid.cell_data["region"] = np.r_[np.ones(len(tets), int), (np.arange(len(edges)) == inner) * 7]
    m = jtet.TetMesh.from_pyvista(grid)
    assert len(m.protected_edges) == len(outer) + 1
    assert edges[inner].tolist() in m.protected_edges[m.protected_edge_labels == 7].tolist()


def test_line_and_vertex_cells_become_protected_edges_and_vertices(tmp_path):
    # lines that are edges of the tets (the shared edge (1, 2) inside, (0, 1) on the
    # boundary) and points that are their vertices are protected; (0, 4) is no edge and
    # vertex 5 is in no tet: both ignored with a warning
    points = np.vstack([PTS5, [[3.0, 3.0, 3.0]]])
    cells = {
        pv.CellType.TETRA: TETS2,
        pv.CellType.LINE: np.array([[2, 1], [0, 1], [0, 4]]),
        pv.CellType.VERTEX: np.array([[4], [5], [4]]),
    }
    with pytest.warns(UserWarning) as caught:
        m = jtet.TetMesh.from_pyvista(pv.UnstructuredGrid(cells, points))
    messages = " ".join(str(w.message) for w in caught)
    assert "1 line(s) of the file are not edges of its tets" in messages
    assert "1 vertex cell(s) of the file are not vertices of its tets" in messages
    assert m.protected_edges.tolist() == [[0, 1], [1, 2]]
    assert m.protected_vertices.tolist() == [4]
    T = m.topology
    assert T.subsegment[[T.edges.tolist().index(e) for e in ([0, 1], [1, 2])]].all()
    assert T.vertex_kind[4] == CORNER
    # the same from a Gmsh file: line elements (1) and point elements (15)
    path = _msh22_with(tmp_path / "lines.msh", ["6 1 2 0 5 2 3", "7 15 2 0 6 5"])
    m = _io.load(path)  # with MSH22's own line (1, 2) and point (1) elements (1-based)
    assert m.protected_edges.tolist() == [[0, 1], [1, 2]]
    assert m.protected_vertices.tolist() == [0, 4]


def test_medit_required_vertices(tmp_path):
    # MMG never moves its RequiredVertices (1-based); meshio skips the section, jtet reads
    # it, with MMG's other sections around it (Corners, Ridges: skipped)
    text = MEDIT.replace("End\n", "Corners\n1\n1\nRequiredVertices\n2\n5\n 2\nRidges\n0\nEnd\n")
    path = tmp_path / "mmg.mesh"
    path.write_text(text)
    assert _io.load(path).protected_vertices.tolist() == [1, 4]
    path.write_text(MEDIT.replace("End\n", "RequiredVertices\n3\n5\n2\nEnd\n"))
    with pytest.raises(jtet.MeshInputError, match="unreadable RequiredVertices"):
        _io.load(path)


def _gmsh_box_with(tmp_path, add):
    """A Gmsh unit box with the entities ``add(occ, box)`` returns embedded in it, meshed
    (h = 0.15, Delaunay, unoptimized) into ``embedded.msh``. ``add`` returns the
    (dim, tag) pairs to embed and the (dim, tags, physical tag) groups to define."""
    gmsh = pytest.importorskip("gmsh")
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        box = gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        embedded, groups = add(gmsh.model.occ, box)
        for dim, tag in embedded:
            gmsh.model.mesh.embed(dim, [tag], 3, box)
        for dim, tags, physical in groups:
            gmsh.model.addPhysicalGroup(dim, tags, physical)
        for name, value in (("MeshSizeMax", 0.15), ("Algorithm3D", 1), ("Optimize", 0)):
            gmsh.option.setNumber(f"Mesh.{name}", value)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(tmp_path / "embedded.msh"))
    finally:
        gmsh.finalize()
    return tmp_path / "embedded.msh"


def test_gmsh_embedded_point_and_curve_stay(tmp_path):
    """A point and a curve embedded in a Gmsh volume (``gmsh.model.mesh.embed``): the
    point element's vertex never moves and the curve's edges stay, as Gmsh keeps nodes
    on their model entities. Unprotected, the point's vertex moves."""

    def point_and_curve(occ, box):
        point = occ.addPoint(0.31, 0.47, 0.53)
        line = occ.addLine(occ.addPoint(0.2, 0.2, 0.3), occ.addPoint(0.8, 0.7, 0.6))
        occ.synchronize()
        return [(0, point), (1, line)], [(3, [box], 1), (1, [line], 40), (0, [point], 50)]

    mesh = _io.load(_gmsh_box_with(tmp_path, point_and_curve))
    target = np.array([0.31, 0.47, 0.53])
    (vertex,) = np.flatnonzero((mesh.points == target).all(axis=1))
    assert mesh.protected_vertices.tolist() == [vertex]  # the only physical point
    assert mesh.protected_vertex_labels.tolist() == [50]
    a, b = np.array([0.2, 0.2, 0.3]), np.array([0.8, 0.7, 0.6])

    def on_curve(m):
        p = m.points[m.protected_edges]
        off = np.linalg.norm(np.cross(p - a, b - a), axis=2).max(axis=1)
        return m.protected_edges[off < 1e-12]

    curve = on_curve(mesh)
    assert len(curve) >= 4
    result = jtet.improve(mesh, check=True)
    out = result.mesh
    assert result.stats_after.min_dihedral > result.stats_before.min_dihedral
    assert (out.points[vertex] == target).all()
    np.testing.assert_array_equal(on_curve(out), curve)
    np.testing.assert_array_equal(out.points[curve], mesh.points[curve])
    # the physical curve and point keep their group numbers through the run and a save
    jtet.save(out, tmp_path / "out.msh")
    back = _io.load(tmp_path / "out.msh")
    assert set(back.protected_edge_labels.tolist()) == {40}
    assert back.protected_vertex_labels.tolist() == [50]
    free = jtet.improve(mesh.replace(protected_vertices=None, protected_edges=None))
    assert (free.mesh.points[curve.reshape(-1)] != mesh.points[curve.reshape(-1)]).any()


def test_gmsh_embedded_surface_survives_improve(tmp_path):
    """A Gmsh surface embedded in a volume (``gmsh.model.mesh.embed``) stays where it is.
    Before its triangles were protected, smoothing moved its vertices up to 0.033 off the
    plane (h = 0.08)."""

    def square(occ, box):
        tag = occ.addRectangle(0.2, 0.2, 0.5, 0.6, 0.6)
        occ.synchronize()
        return [(2, tag)], [(3, [box], 1), (2, [tag], 20)]

    mesh = _io.load(_gmsh_box_with(tmp_path, square))
    inner = mesh.protected_faces
    assert len(inner) > 10 and np.allclose(mesh.points[inner][..., 2], 0.5)
    result = jtet.improve(mesh, check=True)
    out = result.mesh
    assert result.stats_after.min_dihedral > result.stats_before.min_dihedral
    on_plane = out.points[out.protected_faces]
    assert np.array_equal(on_plane[..., 2], np.full(on_plane.shape[:2], 0.5))

    def area(points, faces):
        p = points[faces]
        return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()

    assert area(out.points, out.protected_faces) == pytest.approx(0.36, rel=1e-12)


def test_gmsh_file_without_tets_says_why(tmp_path):
    path = tmp_path / "skin.msh"
    lines = MSH41.splitlines()
    start, end = lines.index("$Elements"), lines.index("$EndElements")
    # only the triangle block: what Gmsh writes when only a surface is in a group
    lines[start + 1 : end] = ["1 1 1 1", "2 1 2 1", "1 1 2 3"]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(MeshInputError, match="no tetrahedra .* add a physical volume") as e:
        _io.load(path)
    _one_line(e)


def test_medit_refs_become_regions(tmp_path):
    path = tmp_path / "m.mesh"
    path.write_text(MEDIT)
    m = _io.load(path)
    np.testing.assert_array_equal(m.tets, TETS2)
    assert m.region.tolist() == [4, 6]


def test_tetgen_region_attribute_becomes_region(tmp_path):
    (tmp_path / "m.node").write_text(TETGEN_NODE)
    (tmp_path / "m.ele").write_text(TETGEN_ELE)
    for name in ("m.node", "m.ele"):
        m = _io.load(tmp_path / name)
        np.testing.assert_array_equal(m.points, PTS5)
        np.testing.assert_array_equal(m.tets, TETS2)
        assert m.region.tolist() == [-1, 3]


def test_tetgen_without_attributes_has_region_zero(tmp_path):
    (tmp_path / "m.node").write_text(TETGEN_NODE)
    (tmp_path / "m.ele").write_text("2 4 0\n1 1 2 3 4\n2 2 3 4 5\n")
    assert _io.load(tmp_path / "m.ele").region.tolist() == [0, 0]


def test_tetgen_constrained_internal_facets_become_protected_faces(tmp_path):
    # TetGen lists the boundary and the constrained internal facets in its .face file
    # (with -p, -r); the internal ones must stay where they are, as Gmsh's embedded ones
    (tmp_path / "m.node").write_text(TETGEN_NODE)
    (tmp_path / "m.ele").write_text(TETGEN_ELE)
    face = "# faces: id, nodes, marker\n2 1\n1 2 3 4 20\n2 1 2 3 1\n# Generated by tetgen\n"
    (tmp_path / "m.face").write_text(face)
    for name in ("m.node", "m.ele"):
        m = _io.load(tmp_path / name)
        assert m.protected_faces.tolist() == [[0, 1, 2], [1, 2, 3]]
        assert m.protected_face_labels.tolist() == [1, 20]  # the facet markers
    # tetgen -nn adds each face's two tets; an empty face list is a valid file
    (tmp_path / "m.face").write_text("2 1\n1 2 3 4 20 1 2\n2 1 2 3 1 1 -1\n")
    assert _io.load(tmp_path / "m.ele").protected_face_labels.tolist() == [1, 20]
    (tmp_path / "m.face").write_text("0 1\n")
    assert len(_io.load(tmp_path / "m.ele").protected_faces) == 0
    (tmp_path / "m.face").write_text("3 1\n1 2 3 4 20\n")  # fewer faces than announced
    with pytest.warns(UserWarning, match="not a readable TetGen face file"):
        m = _io.load(tmp_path / "m.ele")
    assert m.n_tets == 2 and len(m.protected_faces) == 0


def test_tetgen_all_faces_listing_protects_only_the_facets(tmp_path):
    """``tetgen -f`` lists every face of the mesh in the .face file, the inner ones with
    marker 0 (on no facet): those are not protected, or no flip could ever run. A face
    of such a listing with a marker of its own (a constrained internal facet) is."""
    (tmp_path / "m.node").write_text(TETGEN_NODE)
    (tmp_path / "m.ele").write_text(TETGEN_ELE)
    faces = np.sort(TETS2[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), 1)
    faces = np.unique(faces, axis=0)  # the 7 faces of the two tets, [1, 2, 3] shared
    inner = (faces == [1, 2, 3]).all(axis=1)
    for inner_marker, protected in ((0, 6), (5, 7)):
        markers = np.where(inner, inner_marker, 1 + np.arange(len(faces)))
        rows = [
            f"{i + 1} {a + 1} {b + 1} {c + 1} {k}"
            for i, ((a, b, c), k) in enumerate(zip(faces, markers))
        ]
        (tmp_path / "m.face").write_text("\n".join([f"{len(faces)} 1", *rows]) + "\n")
        m = _io.load(tmp_path / "m.ele")
        assert len(m.protected_faces) == protected
        listed = {tuple(f): k for f, k in zip(faces.tolist(), markers.tolist())}
        for f, k in zip(np.sort(m.protected_faces, 1).tolist(), m.protected_face_labels.tolist()):
            assert listed[tuple(f)] == k


def test_tetgen_f_output_is_improved(tmp_path):
    """TetGen's own ``-f`` output (tetgenpy, experiments only): a cube whose six facets
    have markers 1-6. Its .face file lists all 3,780 faces; jtet protects the 492 on the
    facets, with their markers, and the run raises the worst angle (with every face
    protected it could not: the bug this guards against)."""
    tetgenpy = pytest.importorskip("tetgenpy")
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    quads = [[0, 1, 3, 2], [4, 5, 7, 6], [0, 1, 5, 4], [2, 3, 7, 6], [0, 2, 6, 4], [1, 3, 7, 5]]
    triangles = [t for q in quads for t in ([q[0], q[1], q[2]], [q[0], q[2], q[3]])]
    plc = tetgenpy.TetgenIO()
    plc.setup_plc(corners, triangles, facet_markers=[[1 + i // 2] for i in range(12)])
    out = tetgenpy.tetrahedralize("pqfa0.001Q", plc)
    base = str(tmp_path / "cube")
    out.save_nodes(base), out.save_elements(base), out.save_faces(base)
    mesh = _io.load(tmp_path / "cube.ele")
    listed = int((tmp_path / "cube.face").read_text().split()[0])
    on_boundary = mesh.topology.boundary_face
    assert listed == len(on_boundary)  # every face of the mesh
    assert len(mesh.protected_faces) == on_boundary.sum()
    assert set(mesh.protected_face_labels.tolist()) == {1, 2, 3, 4, 5, 6}
    result = jtet.improve(mesh, max_passes=4, perturb=0)
    assert result.stats_after.min_dihedral > result.stats_before.min_dihedral + 5


def test_tetgen_reads_and_refines_jtet_output(tmp_path):
    """TetGen itself (tetgenpy, experiments only) reads jtet's .node / .ele output with
    its regions as the same tets, and ``tetgen -r`` refines it, keeping both regions.
    (With labels alternating tet by tet instead of two volumes, ``tetgen -rq`` stops
    with an error on the same arrays.)"""
    tetgenpy = pytest.importorskip("tetgenpy")
    mesh = delaunay_mesh(80, seed=5)
    mesh = mesh.replace(region=np.where(mesh.points[mesh.tets].mean(axis=1)[:, 0] < 0.5, 1, 2))
    jtet.save(mesh, tmp_path / "out.node")
    io = tetgenpy.TetgenIO()
    io.load_node(str(tmp_path / "out")), io.load_tet(str(tmp_path / "out"))
    np.testing.assert_array_equal(io.points(), mesh.points)
    np.testing.assert_array_equal(io.tetrahedra(), mesh.tets)
    np.testing.assert_array_equal(np.ravel(io.tetrahedronattributes()), mesh.region)
    refined = tetgenpy.tetrahedralize("rq1.4Q", io)
    assert len(refined.tetrahedra()) > mesh.n_tets
    assert set(np.ravel(refined.tetrahedronattributes()).tolist()) == {1, 2}


def test_tetgen_zero_based_numbering(tmp_path):
    # ``tetgen -z`` numbers nodes and elements from 0
    node = "\n".join(
        ["5 3 0 0", *(f"{i} {x} {y} {z}" for i, (x, y, z) in enumerate(PTS5.tolist()))]
    )
    (tmp_path / "z.node").write_text(node + "\n")
    (tmp_path / "z.ele").write_text("2 4 0\n0 0 1 2 3\n1 1 2 3 4\n")
    (tmp_path / "z.face").write_text("1 0\n0 1 2 3\n")
    m = _io.load(tmp_path / "z.node")
    np.testing.assert_array_equal(m.tets, TETS2)
    assert m.protected_faces.tolist() == [[1, 2, 3]]


@pytest.mark.parametrize(("nodes", "reason"), [(10, "quadratic"), (8, "8 nodes per element")])
def test_tetgen_other_elements_say_so(tmp_path, nodes, reason):
    # ``tetgen -o2`` writes 10-node tets; meshio refused them without a reason
    (tmp_path / "m.node").write_text(TETGEN_NODE)
    ids = " ".join(["1", "2", "3", "4", "5"] * 2)[: 2 * nodes - 1]
    (tmp_path / "m.ele").write_text(f"# header comment\n1 {nodes} 0\n1 {ids}\n")
    for name in ("m.node", "m.ele"):
        with pytest.raises(MeshInputError, match=reason) as e:
            _io.load(tmp_path / name)
        _one_line(e)


@pytest.mark.parametrize("attribute", ["1.5", "2.0"])
@pytest.mark.parametrize("last", [True, False])
def test_tetgen_attributes_that_are_no_integers_say_so(tmp_path, attribute, last):
    # a region attribute of 1.5 in the .poly file: meshio reads element attributes as
    # integers; it failed with "could not be read to its end", or, on the last line,
    # read 1.5 as 1
    (tmp_path / "m.node").write_text(TETGEN_NODE)
    lines = ["1 1 2 3 4 1", f"2 2 3 4 5 {attribute}"]
    lines = lines if last else lines[::-1]
    (tmp_path / "m.ele").write_text("2 4 1\n" + "\n".join(lines) + "\n# end\n")
    with pytest.raises(MeshInputError, match=f"element 2 has the attribute '{attribute}'") as e:
        _io.load(tmp_path / "m.node")
    assert "integer region labels" in _one_line(e)
    (tmp_path / "m.ele").write_text("1 4 1\n1 1 2 3 4 2\n")
    assert _io.load(tmp_path / "m.node").region.tolist() == [2]


# ---------------------------------------------------------------------------------------
# bad inputs: the specific jtet exception, with the path and a useful reason


def _one_line(e: pytest.ExceptionInfo) -> str:
    msg = str(e.value)
    assert "\n" not in msg and "Traceback" not in msg
    assert e.value.__cause__ is None  # no chained raw VTK / meshio traceback
    return msg


def test_missing_file_directory_extension_empty(tmp_path):
    with pytest.raises(MeshFileError, match="no such file") as e:
        _io.load(tmp_path / "nope.vtu")
    assert "nope.vtu" in _one_line(e)
    with pytest.raises(MeshFileError, match="is a directory"):
        _io.load(tmp_path)
    (tmp_path / "m.stl").write_text("solid x\nendsolid x\n")
    with pytest.raises(MeshFileError, match=r"unknown mesh file extension '\.stl'"):
        _io.load(tmp_path / "m.stl")
    (tmp_path / "e.msh").write_bytes(b"")
    with pytest.raises(MeshFileError, match="empty"):
        _io.load(tmp_path / "e.msh")
    (tmp_path / "lonely.node").write_text(TETGEN_NODE)
    with pytest.raises(MeshFileError, match=r"companion file lonely\.ele"):
        _io.load(tmp_path / "lonely.node")


@pytest.mark.parametrize("ext", ["vtu", "vtk", "msh", "mesh", "meshb", "node", "exo", "med"])
def test_random_bytes_are_a_file_error_and_print_nothing(tmp_path, capfd, ext):
    rng = np.random.default_rng(7)
    path = tmp_path / f"junk.{ext}"
    path.write_bytes(rng.bytes(4000))
    if ext == "node":
        (tmp_path / "junk.ele").write_bytes(rng.bytes(4000))
    with pytest.raises(MeshFileError, match="not a readable") as e:
        _io.load(path)
    assert str(path) in _one_line(e)
    assert _one_line(e).isascii()
    out, err = capfd.readouterr()
    assert out == "" and err == ""  # VTK / meshio chatter is captured, not printed


@pytest.mark.parametrize("ext", ["msh", "vtu", "vtk", "mesh", "meshb", "exo", "med"])
@pytest.mark.parametrize("frac", [0.3, 0.8, 0.99])
def test_truncated_files_are_a_file_error(tmp_path, capfd, labelled, ext, frac):
    full = tmp_path / f"full.{ext}"
    _quiet_save(labelled, full, cell_data={"q": labelled.quality()} if ext != "mesh" else None)
    data = full.read_bytes()
    cut = tmp_path / f"cut.{ext}"
    cut.write_bytes(data[: int(len(data) * frac)])
    with pytest.raises(MeshFileError, match="not a readable") as e:
        _io.load(cut)
    _one_line(e)
    assert capfd.readouterr() == ("", "")


@pytest.mark.parametrize("which", ["ele", "node"])
def test_tetgen_file_of_comments_only(tmp_path, which):
    # meshio's TetGen reader waited forever for a header line in such a file (a copy cut
    # short after its comment)
    (tmp_path / "m.node").write_text(TETGEN_NODE)
    (tmp_path / "m.ele").write_text(TETGEN_ELE)
    (tmp_path / f"m.{which}").write_text("# This file was crea")
    with pytest.raises(MeshFileError, match=f"m.{which}: not a readable TetGen file .no header"):
        _io.load(tmp_path / "m.node")


def test_vtk_reader_crash_is_a_file_error(tmp_path, labelled, monkeypatch, capfd):
    """VTK's readers are run in a forked child: a legacy file truncated inside its field
    data (a segmentation fault in VTK 9) and a reader that dies by a signal become a
    one-line ``MeshFileError``; the process goes on and prints nothing."""
    full = tmp_path / "full.vtk"
    _quiet_save(labelled, full)
    cut = tmp_path / "cut.vtk"
    cut.write_bytes(full.read_bytes()[:102])  # in the FIELD header
    with pytest.raises(MeshFileError, match="cut.vtk: not a readable legacy VTK file") as e:
        _io.load(cut)
    _one_line(e)
    if sys.platform.startswith("linux"):
        import signal

        def crash(*args):
            os.kill(os.getpid(), signal.SIGSEGV)

        monkeypatch.setattr(_io, "_vtk_arrays_here", crash)
        with pytest.raises(MeshFileError, match=r"VTK's reader crashed with SIGSEGV: the file is"):
            _io.load(full)
    assert capfd.readouterr() == ("", "")


def test_vtk_reader_warnings_reach_the_caller(tmp_path):
    # the child's warnings (here: a triangle that is no face of the tets) are raised
    # again in the loading process
    cells = {pv.CellType.TETRA: TETS2, pv.CellType.TRIANGLE: np.array([[0, 1, 4]])}
    pv.UnstructuredGrid(cells, PTS5).save(tmp_path / "stray.vtu")
    with pytest.warns(UserWarning, match="1 triangle.* not faces of its tets"):
        m = _io.load(tmp_path / "stray.vtu")
    np.testing.assert_array_equal(m.tets, TETS2)


@pytest.mark.parametrize(("name", "text"), [("v22.msh", MSH22), ("v41.msh", MSH41)])
def test_truncated_handwritten_msh(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text[: int(len(text) * 0.7)])
    with pytest.raises(MeshFileError, match="not a readable Gmsh file"):
        _io.load(path)


def _grid_file(tmp_path, points, cells: dict, name="bad.vtu"):
    grid = pv.UnstructuredGrid(cells, np.asarray(points, dtype=np.float64))
    path = tmp_path / name
    grid.save(path)
    return path


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_coordinates(tmp_path, bad):
    pts = PTS5.copy()
    pts[4, 1] = bad
    path = _grid_file(tmp_path, pts, {pv.CellType.TETRA: TETS2})
    with pytest.raises(MeshInputError, match="NaN or infinite"):
        _io.load(path)
    with pytest.raises(MeshInputError, match="point 4"):
        jtet.TetMesh.from_arrays(pts, TETS2)


def test_index_out_of_range(tmp_path):
    (tmp_path / "m.mesh").write_text(MEDIT.replace("2 3 4 5 6", "2 3 4 9 6"))
    with pytest.raises(MeshInputError, match="out of range"):
        _io.load(tmp_path / "m.mesh")
    with pytest.raises(MeshInputError, match="out of range"):
        jtet.TetMesh.from_arrays(PTS5, [[0, 1, 2, -1]])


def test_repeated_vertex(tmp_path):
    (tmp_path / "m.node").write_text(TETGEN_NODE)
    (tmp_path / "m.ele").write_text(TETGEN_ELE.replace("2 2 3 4 5 3", "2 2 3 3 5 3"))
    with pytest.raises(MeshInputError, match="repeats a vertex"):
        _io.load(tmp_path / "m.ele")


def test_empty_mesh(tmp_path):
    path = _grid_file(tmp_path, PTS5, {pv.CellType.TETRA: np.zeros((0, 4), np.int64)})
    with pytest.raises(MeshInputError, match="empty"):
        _io.load(path)
    with pytest.raises(MeshInputError, match="empty"):
        jtet.TetMesh.from_pyvista(pv.UnstructuredGrid())
    with pytest.raises(MeshInputError, match="empty"):
        jtet.TetMesh.from_arrays(PTS5, np.zeros((0, 4), np.int64))


def test_non_tet_cells(tmp_path):
    hexes = pv.ImageData(dimensions=(3, 3, 3)).cast_to_unstructured_grid()
    path = tmp_path / "input.vtu"
    pv.UnstructuredGrid(
        {pv.CellType.HEXAHEDRON: hexes.cells_dict[pv.CellType.VOXEL][:, [0, 1, 3, 2, 4, 5, 7, 6]]},
        hexes.points,
    ).save(path)
    with pytest.raises(MeshInputError) as e:
        _io.load(path)
    msg = _one_line(e)
    assert "8 cells are not tetrahedra (VTK_HEXAHEDRON x 8)" in msg and "input.vtu" in msg
    # voxels straight from pyvista, through from_pyvista (cast to an unstructured grid)
    with pytest.raises(MeshInputError, match="VTK_VOXEL x 8"):
        jtet.TetMesh.from_pyvista(pv.ImageData(dimensions=(3, 3, 3)))
    # tets mixed with a pyramid: the pyramid is reported, not dropped
    mixed = pv.UnstructuredGrid(
        {pv.CellType.TETRA: TETS2, pv.CellType.PYRAMID: np.array([[0, 1, 4, 2, 3]])}, PTS5
    )
    with pytest.raises(MeshInputError, match=r"1 cells are not tetrahedra \(VTK_PYRAMID x 1\)"):
        jtet.TetMesh.from_pyvista(mixed)
    # a surface mesh has no tets at all
    with pytest.raises(MeshInputError, match="no tetrahedra"):
        jtet.TetMesh.from_pyvista(pv.Sphere())


def test_quadratic_tets_are_refused_with_a_hint(tmp_path):
    pts = np.vstack([PTS5[:4], (PTS5[[0, 1, 2, 0, 0, 1]] + PTS5[[1, 2, 0, 3, 3, 3]]) / 2])
    quad = pv.UnstructuredGrid({pv.CellType.QUADRATIC_TETRA: np.arange(10)[None]}, pts)
    with pytest.raises(MeshInputError, match="VTK_QUADRATIC_TETRA x 1.*quadratic"):
        jtet.TetMesh.from_pyvista(quad)
    path = tmp_path / "q.msh"
    meshio.gmsh.write(path, meshio.Mesh(pts, [("tetra10", np.arange(10)[None])]), "2.2")
    with pytest.raises(MeshInputError, match="tetra10 x 1.*quadratic"):
        _io.load(path)


def test_lower_dimensional_cells_are_ignored():
    grid = pv.UnstructuredGrid(
        {
            pv.CellType.TETRA: TETS2,
            pv.CellType.TRIANGLE: np.array([[0, 1, 2]]),
            pv.CellType.LINE: np.array([[0, 1]]),
            pv.CellType.VERTEX: np.array([[4]]),
        },
        PTS5,
    )
    grid.cell_data["region"] = np.arange(grid.n_cells)
    m = jtet.TetMesh.from_pyvista(grid)
    np.testing.assert_array_equal(m.tets, TETS2)
    tet_cells = np.flatnonzero(np.asarray(grid.celltypes) == pv.CellType.TETRA)
    np.testing.assert_array_equal(m.region, tet_cells)


def test_all_negative_orientation_is_fixed_with_a_warning(tmp_path, labelled):
    flipped = labelled.replace(tets=labelled.tets[:, [0, 2, 1, 3]])
    assert (flipped.volumes < 0).all()
    path = tmp_path / "neg.vtu"
    _io.save(flipped, path)
    with pytest.warns(UserWarning, match=r"neg\.vtu: all .* negatively oriented"):
        m = _io.load(path)
    assert (m.volumes > 0).all()
    np.testing.assert_array_equal(np.sort(m.tets, axis=1), np.sort(labelled.tets, axis=1))
    np.testing.assert_array_equal(m.region, labelled.region)


def test_tets_listed_inside_out_are_reordered_with_a_warning(tmp_path, labelled):
    # three tets listed in the opposite vertex order to their neighbours (not inverted:
    # reordering them makes the mesh consistent), see TetMesh.from_arrays
    tets = labelled.tets.copy()
    tets[:3] = tets[:3, [1, 0, 2, 3]]
    path = tmp_path / "mixed.msh"
    _quiet_save(labelled.replace(tets=tets), path)
    with pytest.warns(UserWarning, match="3 of .* tets were listed in the opposite vertex order"):
        m = _io.load(path)
    np.testing.assert_array_equal(m.tets, labelled.tets)


# ---------------------------------------------------------------------------------------
# atomic saves


def _listing(d):
    return sorted(p.name for p in d.iterdir())


def test_save_to_missing_directory_or_unknown_extension(tmp_path, labelled):
    with pytest.raises(MeshFileError, match="not an existing directory"):
        _io.save(labelled, tmp_path / "no" / "such" / "m.vtu")
    (tmp_path / "f").write_text("")
    with pytest.raises(MeshFileError, match="not an existing directory"):
        _io.save(labelled, tmp_path / "f" / "m.vtu")
    with pytest.raises(MeshFileError, match="unknown mesh file extension"):
        _io.save(labelled, tmp_path / "m.stl")
    with pytest.raises(MeshFileError, match="unknown mesh file extension"):
        _io.save(labelled, tmp_path / "m")
    (tmp_path / "d.vtu").mkdir()
    with pytest.raises(MeshFileError, match="is a directory"):
        _io.save(labelled, tmp_path / "d.vtu")
    with pytest.raises(MeshInputError, match="one value per tet"):
        _io.save(labelled, tmp_path / "m.vtu", cell_data={"q": [1.0, 2.0]})
    assert _listing(tmp_path) == ["d.vtu", "f"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write into read-only directories")
def test_save_to_unwritable_directory(tmp_path, labelled):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(MeshFileError, match="cannot create"):
            _io.save(labelled, ro / "m.vtu")
        assert _listing(ro) == []
    finally:
        ro.chmod(0o700)


@pytest.mark.parametrize("ext", ["vtu", "msh", "node", "xdmf"])
def test_failed_write_leaves_no_temp_and_keeps_the_old_file(tmp_path, labelled, monkeypatch, ext):
    path = tmp_path / f"keep.{ext}"
    _quiet_save(labelled, path)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def half_written(mesh, tmp, fmt, cell_data, heavy_name="", quad=None):
        tmp.write_bytes(b"partial")
        if fmt in ("tetgen", "xdmf"):
            tmp.with_suffix(".ele" if fmt == "tetgen" else ".h5").write_bytes(b"partial")
        raise RuntimeError("disk full")

    monkeypatch.setattr(_io, "_write", half_written)
    with pytest.raises(MeshFileError, match="disk full") as e:
        _quiet_save(labelled.replace(region=labelled.region + 1), path)
    assert str(path) in _one_line(e)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_region_labels_must_fit_32_bit_tags(tmp_path, labelled):
    big = labelled.replace(region=labelled.region + 2**40)
    for ext in ("msh", "mesh"):
        with pytest.raises(MeshFileError, match="32-bit"):
            _quiet_save(big, tmp_path / f"m.{ext}")
    _io.save(big, tmp_path / "m.vtu")  # int64 in VTK files
    np.testing.assert_array_equal(_io.load(tmp_path / "m.vtu").region, big.region)
    assert _listing(tmp_path) == ["m.vtu"]


def test_overwrite_false_and_file_mode(tmp_path, labelled):
    path = tmp_path / "m.vtu"
    _io.save(labelled, path)
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0600
    data = path.read_bytes()
    with pytest.raises(MeshFileError, match="exists"):
        _io.save(labelled.replace(region=labelled.region * 2), path, overwrite=False)
    assert path.read_bytes() == data
    _io.save(labelled.replace(region=labelled.region * 2), path)  # overwrite=True (default)
    np.testing.assert_array_equal(_io.load(path).region, labelled.region * 2)
    assert _listing(tmp_path) == ["m.vtu"]


def test_replaced_outputs_keep_their_mode(tmp_path, labelled):
    from jtet import _report

    mesh, report = tmp_path / "m.vtu", tmp_path / "r.json"
    _io.save(labelled, mesh)
    _report.write_text_atomic(report, "{}")
    for path, mode in ((mesh, 0o640), (report, 0o604)):
        os.chmod(path, mode)
    _io.save(labelled.replace(region=labelled.region * 2), mesh)
    _report.write_text_atomic(report, '{"a": 1}')
    assert mesh.stat().st_mode & 0o777 == 0o640
    assert report.stat().st_mode & 0o777 == 0o604
    assert report.read_text() == '{"a": 1}'
    assert _listing(tmp_path) == ["m.vtu", "r.json"]


def test_write_text_to_missing_directory(tmp_path):
    from jtet import _report

    with pytest.raises(MeshFileError, match="cannot write"):
        _report.write_text_atomic(tmp_path / "no" / "r.json", "{}")


# ---------------------------------------------------------------------------------------
# demo meshes


def test_demo_mesh():
    m = _io.demo_mesh()
    assert m is _io.demo_mesh("demo")  # cached
    assert 4000 <= m.n_tets <= 8000
    assert m.points.dtype == np.float64
    assert (m.volumes > 0).all()
    assert np.unique(m.region).tolist() == [0]
    _, lo, hi = tet_dihedrals(m.points, m.tets)
    assert lo.min() < 5.0  # unoptimized Delaunay: slivers left for jtet to remove
    assert hi.max() > 170.0
    # box [0,2]x[0,1]x[0,1] minus a ball of radius 0.3: the inscribed polyhedral hole is
    # a little smaller than the ball (94 % at this resolution)
    ball = 4 / 3 * np.pi * 0.3**3
    assert 2.0 - ball < m.volumes.sum() < 2.0 - 0.85 * ball


def test_demo_two_regions():
    m = _io.demo_mesh("two_regions")
    assert 1000 <= m.n_tets <= 3000
    assert (m.volumes > 0).all()
    assert np.unique(m.region).tolist() == [1, 2]
    z = m.points[m.tets][:, :, 2]
    lower = m.region == 1
    assert (z[lower] <= 0.45 + 1e-12).all() and (z[~lower] >= 0.45 - 1e-12).all()
    np.testing.assert_allclose(m.volumes[lower].sum(), 0.45, rtol=1e-12)
    np.testing.assert_allclose(m.volumes.sum(), 1.0, rtol=1e-12)


def test_unknown_demo_mesh():
    with pytest.raises(MeshInputError, match="unknown demo mesh"):
        _io.demo_mesh("nope")


def test_damaged_files_fuzz(tmp_path, capsys):
    """A short run of experiments/fuzz_files.py: 20 damaged versions of a labelled mesh
    in five formats each load or are refused with a JtetError (none crashes, none raises
    another exception). Each format costs ~1.5 s of its own (a fresh process), so the
    default run takes these five (every format: 30 s); the script runs them all, with
    hundreds of tries each."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
    try:
        import fuzz_files
    finally:
        sys.path.pop(0)
    formats = "vtu,node,msh,xdmf,exo"
    code = fuzz_files.main(
        ["--tries", "20", "--seed", "3", "--formats", formats, "--keep", str(tmp_path)]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    rows = [line.split() for line in out.splitlines() if line.split()[:1] in (["vtu"], ["node"])]
    assert len(rows) == 2 and all(int(r[1]) + int(r[2]) == 20 for r in rows), out


@pytest.mark.parametrize(
    ("name", "values"),
    [("jtet:protected_edges", [0, 1, 2]), ("jtet:protected_faces", [0.0, 1.0, 2.0])],
)
def test_damaged_protected_field_data(tmp_path, name, values):
    # found by fuzz_files: a damaged .vtu whose protected edges held 3 ids (a bare
    # ValueError from a reshape before); float ids are no ids either
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: TETS2}, PTS5)
    grid.field_data[name] = np.array(values)
    grid.save(tmp_path / "m.vtu")
    with pytest.raises(MeshInputError, match=f"field data '{name}' .* not a list of"):
        _io.load(tmp_path / "m.vtu")


def test_damaged_vtk_array_name():
    # found by fuzz_files: a legacy file whose cell array name lost a byte ('reg\xc1on',
    # not UTF-8): pyvista gives bytes as its key and refused dict() with a TypeError;
    # the arrays are now taken by name, and the file's real fault (a damaged tet) is
    # what the error says
    path = Path(__file__).parent / "data" / "damaged_array_name.vtk"
    with pytest.raises(MeshInputError, match="tet 17 has vertex indices .* out of range"):
        _io.load(path)


@pytest.mark.parametrize("label", [0, 1])
def test_msh_region_0_is_in_no_physical_group(tmp_path, label):
    """Gmsh reads physical tag 0 as no physical group: the save warns that region 0's
    tets are invisible to solvers that read cells by physical group, and only then."""
    gmsh = pytest.importorskip("gmsh")
    from helpers import gmsh_model

    mesh = jtet.demo_mesh().replace(region=np.full(jtet.demo_mesh().n_tets, label))
    path = tmp_path / "m.msh"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _io.save(mesh, path)
    said = [str(w.message) for w in caught if "region 0" in str(w.message)]
    with gmsh_model():
        gmsh.open(str(path))
        groups = gmsh.model.getPhysicalGroups(3)
    assert groups == ([] if label == 0 else [(3, 1)])
    assert len(said) == (label == 0) and all(f"{mesh.n_tets} tet(s) of region 0" in m for m in said)


def test_arrays_of_numbers_carried_others_named(tmp_path):
    """A point field (a temperature) and a cell field (a material) are read, carried
    through ``jtet improve`` and written to the output; arrays that are no numbers are
    left out with a warning naming them, while the region array and jtet's own per-tet
    arrays (recomputed for each output) pass in silence."""
    grid = jtet.demo_mesh().to_pyvista()
    grid.point_data["temperature"] = np.arange(grid.n_points, dtype=float)
    grid.point_data["label"] = np.array(["x"] * grid.n_points)  # no numbers: dropped
    grid.cell_data["material"] = np.ones(grid.n_cells)
    grid.cell_data["name"] = np.array(["steel"] * grid.n_cells)  # no numbers: dropped
    grid.save(tmp_path / "fields.vtu")
    with pytest.warns(UserWarning) as said:
        mesh = jtet.load(tmp_path / "fields.vtu")
    messages = [str(w.message) for w in said]
    assert any(m.endswith("not read: 1 point array(s) (label)") for m in messages), messages
    assert any(m.endswith("not read: 1 cell array(s) (name)") for m in messages), messages
    np.testing.assert_array_equal(mesh.point_data["temperature"], np.arange(mesh.n_points))
    np.testing.assert_array_equal(mesh.cell_data["material"], np.ones(mesh.n_tets))
    out = tmp_path / "out.vtu"
    args = ["improve", str(tmp_path / "fields.vtu"), str(out), "-q", "--max-passes", "1"]
    assert main([*args, "--perturb", "0"]) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = jtet.load(out)  # region + quality_*, min/max_dihedral, volume: nothing to say
    assert list(back.point_data) == ["temperature"]
    assert back.point_data["temperature"].shape == (back.n_points,)
    np.testing.assert_array_equal(back.cell_data["material"], np.ones(back.n_tets))


@pytest.mark.parametrize("fmt, binary", [("gmsh22", False), ("gmsh22", True), ("gmsh", True)])
def test_gmsh_views_written_by_meshio(tmp_path, fmt, binary):
    """A Gmsh file's $NodeData / $ElementData written by meshio (a solution saved with
    the mesh) are read as point and cell data. meshio's ASCII writer prints NumPy 2
    scalars as "np.float64(0.0)": those sections do not parse and are named as not
    read. jtet's own per-tet arrays in its .msh outputs are not read back."""
    mesh = jtet.demo_mesh()
    temperature = np.arange(mesh.n_points, dtype=float)
    stress = np.linspace(0, 1, mesh.n_tets)
    m = meshio.Mesh(
        mesh.points,
        [("tetra", mesh.tets)],
        point_data={"T": temperature},
        cell_data={
            "stress": [stress],
            "gmsh:physical": [np.ones(mesh.n_tets, int)],
            "gmsh:geometrical": [np.ones(mesh.n_tets, int)],
        },
    )
    path = tmp_path / "views.msh"
    meshio.write(path, m, file_format=fmt, binary=binary)
    if binary:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            back = _io.load(path)
        np.testing.assert_array_equal(back.point_data["T"], temperature)
        np.testing.assert_array_equal(back.cell_data["stress"], stress)
    else:
        with pytest.warns(
            UserWarning,
            match=r"not read: 1 point array\(s\) \(T\) and 1 cell array\(s\) \(stress\)",
        ):
            back = _io.load(path)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    own = tmp_path / "own.msh"
    _io.save(back, own, cell_data={"quality_min_sine": back.quality()})
    again = _io.load(own)
    assert set(again.cell_data) == set(back.cell_data)


@pytest.mark.parametrize("binary", [0, 1])
def test_gmsh_parametric_nodes(tmp_path, binary):
    """A file saved with ``Mesh.SaveParametric = 1`` (nodes on curves and surfaces carry
    their u / u v): MSH 4.1 reads as the same file without them (meshio 5.3 alone
    refuses it, and its reader gives the same nodes on the plain file); MSH 2.2 writes
    such nodes in a ``$ParametricNodes`` section, which is refused with the way out."""
    gmsh = pytest.importorskip("gmsh")
    from meshio.gmsh import _gmsh41

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.addSphere(0, 0, 0, 1)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.4)
        gmsh.model.mesh.generate(3)
        gmsh.option.setNumber("Mesh.Binary", binary)
        gmsh.write(str(tmp_path / "plain.msh"))
        gmsh.option.setNumber("Mesh.SaveParametric", 1)
        gmsh.write(str(tmp_path / "param.msh"))
        gmsh.option.setNumber("Mesh.MshFileVersion", 2.2)
        gmsh.write(str(tmp_path / "param22.msh"))
    finally:
        gmsh.finalize()
    with pytest.raises(meshio.ReadError, match="parametric"):
        meshio.gmsh.read(str(tmp_path / "param.msh"))
    plain, param = _io.load(tmp_path / "plain.msh"), _io.load(tmp_path / "param.msh")
    np.testing.assert_array_equal(param.points, plain.points)
    np.testing.assert_array_equal(param.tets, plain.tets)
    np.testing.assert_array_equal(param.protected_faces, plain.protected_faces)
    np.testing.assert_array_equal(plain.points, meshio.read(tmp_path / "plain.msh").points)
    assert _gmsh41._read_nodes.__module__ == _gmsh41.__name__  # meshio's own again
    with pytest.raises(MeshFileError, match=r"\$ParametricNodes .* MSH 4.1"):
        _io.load(tmp_path / "param22.msh")
