"""XDMF meshes (.xdmf + .h5): dolfinx's layout written and read, files of dolfinx, meshio
and VTK's reader as independent references, bad files refused with clear errors."""

import shutil
import warnings
from pathlib import Path

import h5py
import meshio
import numpy as np
import pytest
from helpers import delaunay_mesh

import jtet
from jtet._errors import MeshFileError, MeshInputError
from jtet.cli import main

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def labelled():
    """Three regions by x with names, protected faces / edges / vertices with labels,
    two protected tets."""
    m = delaunay_mesh(80, seed=4)
    region = np.digitize(m.points[m.tets].mean(axis=1)[:, 0], [0.33, 0.66]) + 1
    T = m.topology
    faces = T.faces[T.boundary_face][:30]
    return m.replace(
        region=region,
        protected_faces=faces,
        protected_face_labels=np.arange(len(faces)) % 4 + 5,
        protected_edges=T.edges[:6],
        protected_edge_labels=np.arange(6) + 20,
        protected_vertices=[3, 9],
        protected_vertex_labels=[31, 32],
        protected_tets=m.tets[[0, 7]],
        label_names={(3, 1): "left", (3, 2): "middle", (2, 5): "wall"},
    )


def _save(mesh, path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return jtet.save(mesh, path, **kw)


def _area(points, faces):
    p = points[faces]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def test_everything_jtet_keeps_comes_back(tmp_path, labelled):
    path = tmp_path / "m.xdmf"
    q = labelled.quality()
    vec = np.arange(3 * labelled.n_tets, dtype=np.float64).reshape(-1, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing is left out
        jtet.save(labelled, path, cell_data={"quality": q, "a/b": vec})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.h5", "m.xdmf"]
    back = jtet.load(path)
    for name in ("points", "tets", "region", "protected_faces", "protected_face_labels",
                 "protected_edges", "protected_edge_labels", "protected_vertices",
                 "protected_vertex_labels", "protected_tets"):  # fmt: skip
        np.testing.assert_array_equal(getattr(back, name), getattr(labelled, name), err_msg=name)
    assert dict(back.label_names) == dict(labelled.label_names)
    # the per-tet arrays are cell attributes of the "mesh" grid, in the HDF5 file
    with h5py.File(tmp_path / "m.h5") as f:
        np.testing.assert_array_equal(f["Mesh/mesh/cell_data/0"][()], q)
        np.testing.assert_array_equal(f["Mesh/mesh/cell_data/1"][()], vec)
    text = path.read_text()
    assert 'Name="quality"' in text and 'Name="a/b"' in text and "m.h5:/Mesh/mesh/topology" in text


def test_vtk_reader_sees_the_grids(tmp_path, labelled):
    """VTK's XDMF reader (ParaView's) is an independent reader of the written file."""
    import pyvista as pv
    from vtkmodules.vtkIOXdmf2 import vtkXdmfReader

    path = tmp_path / "m.xdmf"
    _save(labelled, path, cell_data={"quality": labelled.quality()})
    reader = vtkXdmfReader()
    reader.SetFileName(str(path))
    reader.Update()
    blocks = pv.wrap(reader.GetOutputDataObject(0))
    names = [blocks.get_block_name(i) for i in range(blocks.n_blocks)]
    assert names == ["mesh", "cell_tags", "facet_tags", "edge_tags", "vertex_tags"]
    mesh = blocks["mesh"]
    assert (mesh.celltypes == 10).all() and mesh.n_cells == labelled.n_tets  # VTK_TETRA
    np.testing.assert_array_equal(mesh.points, labelled.points)
    np.testing.assert_array_equal(mesh.cell_data["region"], labelled.region)
    np.testing.assert_array_equal(mesh.cell_data["quality"], labelled.quality())
    facets = blocks["facet_tags"]
    assert (facets.celltypes == 5).all()  # VTK_TRIANGLE
    np.testing.assert_array_equal(facets.cell_data["facet_tags"], labelled.protected_face_labels)


def test_file_written_by_dolfinx():
    """tests/data/dolfinx_cube.xdmf was written by dolfinx 0.5.2
    (experiments/dolfinx_xdmf.py --write-fixture): a 4x4x4 unit cube, cell tags 1
    (x < 0.5) and 2, the exterior facets tagged 1-6 by side. dolfinx renumbers cells and
    vertices, so the checks are closed forms: each region is half the cube, each side a
    unit square."""
    mesh = jtet.load(DATA / "dolfinx_cube.xdmf")
    assert mesh.n_tets == 384 and mesh.n_points == 125
    assert mesh.is_valid().ok
    for label in (1, 2):
        assert mesh.volumes[mesh.region == label].sum() == pytest.approx(0.5, abs=1e-14)
    x = mesh.points[mesh.tets].mean(axis=1)[:, 0]
    assert ((x < 0.5) == (mesh.region == 1)).all()
    assert len(mesh.protected_faces) == 192  # 6 sides x 16 squares x 2 triangles
    area = _area(mesh.points, mesh.protected_faces)
    for side in range(1, 7):
        assert area[mesh.protected_face_labels == side].sum() == pytest.approx(1.0, abs=1e-14)


@pytest.mark.parametrize("data_format", ["XML", "HDF"])
def test_files_written_by_meshio(tmp_path, labelled, data_format):
    """meshio writes one grid; with triangles too its topology is Mixed (cell type ids,
    then nodes) and its cell data runs over all cells: the tets and labelled triangles
    come back as written."""
    faces, labels = labelled.protected_faces, labelled.protected_face_labels
    m = meshio.Mesh(
        labelled.points,
        [("tetra", labelled.tets), ("triangle", faces)],
        cell_data={"gmsh:physical": [labelled.region, labels]},
    )
    path = tmp_path / "mixed.xdmf"
    meshio.xdmf.write(path, m, data_format=data_format)
    assert 'TopologyType="Mixed"' in path.read_text()
    back = jtet.load(path)
    np.testing.assert_array_equal(back.points, labelled.points)
    np.testing.assert_array_equal(back.tets, labelled.tets)
    np.testing.assert_array_equal(back.region, labelled.region)
    np.testing.assert_array_equal(back.protected_faces, labelled.protected_faces)
    np.testing.assert_array_equal(back.protected_face_labels, labelled.protected_face_labels)
    # the tets alone: a Tetrahedron topology
    meshio.xdmf.write(
        tmp_path / "tets.xdmf", meshio.Mesh(labelled.points, [("tetra", labelled.tets)])
    )
    plain = jtet.load(tmp_path / "tets.xdmf")
    np.testing.assert_array_equal(plain.tets, labelled.tets)
    assert (plain.region == 0).all()


def test_files_written_by_vtk(tmp_path, labelled):
    """VTK's XDMF writer (ParaView's "Xdmf" writer, XDMF 2.2): tets and triangles in one
    Mixed topology, the region as a cell attribute."""
    import pyvista as pv
    from vtkmodules.vtkIOXdmf2 import vtkXdmfWriter

    faces = labelled.protected_faces
    grid = pv.UnstructuredGrid(
        {pv.CellType.TETRA: labelled.tets, pv.CellType.TRIANGLE: faces}, labelled.points
    )
    grid.cell_data["region"] = np.concatenate([labelled.region, labelled.protected_face_labels])
    writer = vtkXdmfWriter()
    writer.SetFileName(str(tmp_path / "vtk.xdmf"))
    writer.SetInputData(grid)
    writer.Write()
    assert 'TopologyType="Mixed"' in (tmp_path / "vtk.xdmf").read_text()
    back = jtet.load(tmp_path / "vtk.xdmf")
    np.testing.assert_array_equal(back.points, labelled.points)
    np.testing.assert_array_equal(back.tets, labelled.tets)
    np.testing.assert_array_equal(back.region, labelled.region)
    np.testing.assert_array_equal(back.protected_faces, labelled.protected_faces)
    np.testing.assert_array_equal(back.protected_face_labels, labelled.protected_face_labels)


def test_time_series_gives_its_first_step(tmp_path, labelled, monkeypatch):
    """A temporal collection (meshio's TimeSeriesWriter, solvers' output) holds the mesh
    once per time step: the first step is read. meshio's steps include the grid that
    holds the mesh by an XPointer."""
    monkeypatch.chdir(tmp_path)  # meshio writes the .h5 in the working directory
    path = tmp_path / "series.xdmf"
    with meshio.xdmf.TimeSeriesWriter(path) as writer:
        writer.write_points_cells(labelled.points, [("tetra", labelled.tets)])
        for t in (0.0, 1.0):
            writer.write_data(t, cell_data={"region": [labelled.region]})
    back = jtet.load(path)
    np.testing.assert_array_equal(back.tets, labelled.tets)
    np.testing.assert_array_equal(back.region, labelled.region)


def test_improve_cli_reads_and_writes_xdmf(tmp_path, labelled):
    src, out = tmp_path / "in.xdmf", tmp_path / "out.xdmf"
    _save(labelled, src)
    assert main(["improve", str(src), str(out), "-q", "--max-passes", "2", "--perturb", "0"]) == 0
    back = jtet.load(out)
    assert back.is_valid().ok
    assert jtet.stats(back).min_dihedral >= jtet.stats(labelled).min_dihedral
    np.testing.assert_array_equal(back.protected_tets, labelled.protected_tets)
    for label in (1, 2, 3):  # regions keep their volumes
        before = labelled.volumes[labelled.region == label].sum()
        assert back.volumes[back.region == label].sum() == pytest.approx(before, rel=1e-12)
    with h5py.File(tmp_path / "out.h5") as f:  # the quality arrays for ParaView
        assert f["Mesh/mesh/cell_data/0"].shape == (back.n_tets,)


def test_output_never_replaces_the_inputs_heavy_data(tmp_path, labelled, capsys):
    """An XDMF input reads its .h5 file: an output whose .h5 is that file is refused
    without --overwrite, and so is a TetGen output whose .node / .ele is the input's."""
    src = tmp_path / "a.xdmf"
    _save(labelled, src)
    shutil.move(tmp_path / "a.h5", tmp_path / "b.h5")
    src.write_text(src.read_text().replace("a.h5:", "b.h5:"))
    before = (tmp_path / "b.h5").read_bytes()
    assert main(["convert", str(src), str(tmp_path / "b.xdmf")]) == 2
    err = capsys.readouterr().err
    assert "also writes" in err and "b.h5" in err and "--overwrite" in err
    assert (tmp_path / "b.h5").read_bytes() == before and not (tmp_path / "b.xdmf").exists()
    # a batch: the output of one input would replace the heavy data of another
    other = tmp_path / "a.vtu"
    _save(labelled, other)
    args = ["improve", str(other), str(src), "--out-dir", str(tmp_path / "out"), "-q"]
    (tmp_path / "out").mkdir()
    src.write_text(src.read_text().replace("b.h5:", "out/b.h5:"))
    shutil.move(tmp_path / "b.h5", tmp_path / "out" / "b.h5")
    other.rename(tmp_path / "b.vtu")
    args[1] = str(tmp_path / "b.vtu")
    assert main([*args, "--out-ext", "xdmf"]) == 2
    err = capsys.readouterr().err
    assert "(the output of" in err and "which the input" in err and "a.xdmf reads" in err
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["b.h5"]
    node = tmp_path / "t.node"
    _save(labelled, node)
    before = node.read_bytes()
    assert main(["improve", str(node), str(tmp_path / "t.ele"), "-q"]) == 2
    assert "t.node, the input file" in capsys.readouterr().err
    assert node.read_bytes() == before


def _grid(topology: str, nodes: int, cells: str, points: str, dims: str = "3") -> str:
    return f"""<?xml version="1.0"?>
<Xdmf Version="3.0"><Domain><Grid Name="g">
<Topology TopologyType="{topology}" NodesPerElement="{nodes}">
<DataItem Dimensions="{len(cells.split())}" NumberType="Int" Format="XML">{cells}</DataItem>
</Topology>
<Geometry GeometryType="{"XYZ" if dims == "3" else "XY"}">
<DataItem Dimensions="{len(points.split())}" Format="XML">{points}</DataItem>
</Geometry></Grid></Domain></Xdmf>"""


CUBE = " ".join(f"{x} {y} {z}" for z in (0, 1) for y in (0, 1) for x in (0, 1))


@pytest.mark.parametrize(
    "text, error, match",
    [
        ("<Xdmf><Domain><Grid", MeshFileError, "not a readable XDMF file"),
        ("<html/>", MeshFileError, "no Xdmf / Domain element"),
        (_grid("Hexahedron", 8, "0 1 3 2 4 5 7 6", CUBE), MeshInputError, "VTK|hexahedron x 1"),
        (_grid("Tetrahedron_10", 10, " ".join(["0 1 2 4"] * 2 + ["0 1"]), CUBE), MeshInputError,
         "quadratic"),
        (_grid("Tetrahedron", 4, "0 1 2 4", "0 0 1 0 0 1 1 1", "2"), MeshInputError, "2-D"),
        (_grid("Tetrahedron", 4, "0 1 2 9", CUBE), MeshInputError, "out of range"),
        (_grid("Tetrahedron", 4, "0 1 2", CUBE), MeshFileError, "no whole number"),
        (_grid("Mixed", 4, "6 0 1 2 4 77 1 2", CUBE), MeshFileError, "unknown cell type 77"),
        (_grid("Mixed", 4, "6 0 1 2 4 6 1 2", CUBE), MeshFileError, "cut short"),
        (_grid("Tetrahedron", 4, "0 1 2 x", CUBE), MeshFileError, "not numbers"),
        (_grid("Triangle", 3, "0 1 2", CUBE), MeshInputError, "no tetrahedra"),
        (_grid("Tetrahedron", 4, "0 1 2 4", CUBE).replace(
            'Format="XML">0 1 2 4', 'Format="HDF">nothere.h5:/t'), MeshFileError,
         "HDF5 file nothere.h5 is missing"),
        (_grid("Tetrahedron", 4, "0 1 2 4", CUBE).replace('Dimensions="4"', 'Dimensions="2 4"'),
         MeshFileError, "4 values for Dimensions 2 4"),
        (_grid("Tetrahedron", 4, "0 1 2 4", CUBE).replace('Format="XML">0 0 0',
         'Precision="z" Format="XML">0 0 0'), MeshFileError, "bad Precision 'z'"),
        (_grid("Polyline", "x", "0 1", CUBE), MeshFileError, "bad NodesPerElement 'x'"),
        (_grid("Mixed", 4, "6 0 1 2 4.5", CUBE).replace('NumberType="Int" ', ""),
         MeshInputError, "node ids that are not integers"),
        (_grid("Tetrahedron", 4, "0 1 2 4", CUBE).replace(
            'Format="XML">0 1 2 4', 'Reference="XML">/Xdmf/Domain/DataItem'), MeshFileError,
         "not supported"),
    ],
)  # fmt: skip
def test_bad_files_are_refused(tmp_path, text, error, match):
    path = tmp_path / "bad.xdmf"
    path.write_text(text)
    with pytest.raises(error, match=match) as e:
        jtet.load(path)
    assert str(path) in str(e.value)


def test_h5_file_given_as_the_mesh_names_the_xdmf(tmp_path, labelled):
    _save(labelled, tmp_path / "m.xdmf")
    with pytest.raises(MeshFileError, match="read the .xdmf file that names it"):
        jtet.load(tmp_path / "m.h5")


def test_damaged_heavy_data_is_refused(tmp_path, labelled):
    path = tmp_path / "m.xdmf"
    _save(labelled, path)
    heavy = tmp_path / "m.h5"
    data = heavy.read_bytes()
    heavy.write_bytes(data[: len(data) // 3])  # cut short
    with pytest.raises(MeshFileError, match=r"m.h5|not a readable"):
        jtet.load(path)
    heavy.write_bytes(data)
    with h5py.File(heavy, "a") as f:
        del f["Mesh/mesh/topology"]
    with pytest.raises(MeshFileError, match="no dataset /Mesh/mesh/topology in m.h5"):
        jtet.load(path)
    # a dataset that claims 3.2 TB (chunked, never written: the file stays small) is
    # refused at once, whether Dimensions says so too or not
    with h5py.File(heavy, "a") as f:
        f.create_dataset("Mesh/mesh/topology", shape=(10**11, 4), dtype=np.int64, chunks=True)
    with pytest.raises(MeshFileError, match=f"holds {4 * 10**11} values for Dimensions"):
        jtet.load(path)
    text = path.read_text()
    path.write_text(text.replace(f'"{labelled.n_tets} 4"', f'"{10**11} 4"', 1))
    with pytest.raises(MeshFileError, match="too large to read|unreadable"):
        jtet.load(path)
    path.write_text(text)
    heavy.unlink()
    with pytest.raises(MeshFileError, match="HDF5 file m.h5 is missing"):
        jtet.load(path)


def test_periodic_links_are_named_as_dropped(tmp_path):
    m = delaunay_mesh(30, seed=2)
    with pytest.warns(UserWarning, match="no periodic links; not saved: 1 periodic link"):
        jtet.save(m.replace(periodic=[(2, (2, 1), None, [[0, 1]])]), tmp_path / "p.xdmf")


def test_cell_tags_in_any_order_on_a_large_vertex_numbering(tmp_path, labelled):
    """dolfinx lists its cell tags in its own order, each tet's vertices in any order,
    and may tag only some tets: they are matched to the mesh's tets by their vertex
    sets, the others get region 0. With 70k points (ids past the range where a tet's
    four ids make one exact int64 key) the match must still pair each tagged tet with
    its own (it paired ranks among different sets of tets)."""
    import xml.etree.ElementTree as ET

    from helpers import shifted

    mesh = shifted(labelled.replace(label_names={}, protected_tets=None))
    path = tmp_path / "m.xdmf"
    _save(mesh, path)
    rng = np.random.default_rng(0)
    order = rng.permutation(mesh.n_tets)[: 3 * mesh.n_tets // 4]
    tagged = np.array(
        [np.roll(t, k) for t, k in zip(mesh.tets[order], rng.integers(0, 4, len(order)))]
    )
    with h5py.File(tmp_path / "m.h5", "a") as f:
        f["MeshTags/cell_tags/topology"] = tagged
        f["MeshTags/cell_tags/Values"] = mesh.region[order].astype(np.int32)
    tree = ET.parse(path)
    grids = {g.get("Name"): g for g in tree.getroot().iter("Grid")}
    grids["mesh"].remove(grids["mesh"].find("Attribute[@Name='region']"))
    cell_tags = grids["cell_tags"]
    topology = cell_tags.find("Topology/DataItem")
    topology.text = "m.h5:/MeshTags/cell_tags/topology"
    topology.attrib["Dimensions"] = f"{len(order)} 4"
    item = cell_tags.find("Attribute/DataItem")
    item.text, item.attrib["Precision"] = "m.h5:/MeshTags/cell_tags/Values", "4"
    item.attrib["Dimensions"] = str(len(order))
    tree.write(path)
    back = jtet.load(path)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    expected = np.zeros(mesh.n_tets, np.int64)
    expected[order] = mesh.region[order]
    np.testing.assert_array_equal(back.region, expected)
    assert len(np.unique(back.region)) == 4


def test_quadratic_round_trip(tmp_path, labelled):
    """``quadratic=True`` writes 10-node tets (a node off its midpoint on one edge) that
    ``linear=True`` reads back as the same mesh: corners, regions and names, protected
    entities and tets (of 10 nodes in the file: found by their corners), point data and
    the curved edge."""
    a, b = labelled.tets[0, :2]
    bent = labelled.points[[a, b]].mean(axis=0) + 0.01
    mesh = labelled.replace(
        curved_edges=([[a, b]], [bent]), point_data={"x": labelled.points[:, 0].copy()}
    )
    path = tmp_path / "q.xdmf"
    _save(mesh, path, quadratic=True)  # (a sliver folds under the bent edge: a warning)
    assert 'TopologyType="Tetrahedron_10"' in path.read_text()
    with pytest.warns(UserWarning, match="read as linear"):
        back = jtet.load(path, linear=True)
    for name in ("points", "tets", "region", "protected_faces", "protected_face_labels",
                 "protected_edges", "protected_edge_labels", "protected_vertices",
                 "protected_vertex_labels", "protected_tets"):  # fmt: skip
        np.testing.assert_array_equal(getattr(back, name), getattr(mesh, name), err_msg=name)
    assert back.label_names == mesh.label_names
    np.testing.assert_array_equal(back.point_data["x"], mesh.point_data["x"])
    np.testing.assert_array_equal(back.curved_edges.edges, [sorted([a, b])])
    np.testing.assert_array_equal(back.curved_edges.points, [bent])
