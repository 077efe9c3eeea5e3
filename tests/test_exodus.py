"""Exodus II meshes (``jtet._exodus``): files other writers made, VTK's own Exodus reader
on jtet's files, round trips and bad files.

``tests/data/exodus_classic.exo`` (netCDF classic 64-bit offset, written with the netCDF
C library variable by variable) and ``exodus_meshio.exo`` (meshio 5.3's writer: netCDF-4,
HDF5 inside) hold one Delaunay mesh; ``experiments/exodus_fixtures.py`` made both.
"""

import warnings
from pathlib import Path

import numpy as np
import pytest
from helpers import delaunay_mesh, read_as_unit_tet, unit_tet10

import jtet
from jtet._errors import MeshFileError, MeshInputError
from jtet.cli import main

DATA = Path(__file__).parent / "data"
CLASSIC, MESHIO = DATA / "exodus_classic.exo", DATA / "exodus_meshio.exo"


def _rows(a) -> set:
    return {tuple(sorted(r)) for r in np.asarray(a).tolist()}


def test_classic_file_blocks_side_set_and_node_sets():
    """Blocks 10 "left" / 20 "right" are the tets on each side of x = 0.5, side set 7
    "wall" every boundary face at x = 0 (found here by NumPy), its node set (id 7, the
    same nodes) is derived from it, node set 4 "probe" (nodes 3 and 7) is a node set."""
    mesh = jtet.load(CLASSIC)
    x = mesh.points[mesh.tets].mean(axis=1)[:, 0]
    np.testing.assert_array_equal(mesh.region, np.where(x < 0.5, 10, 20))
    assert dict(mesh.label_names) == {(3, 10): "left", (3, 20): "right", (2, 7): "wall"}
    T = mesh.topology
    boundary = T.faces[T.boundary_face]
    wall = boundary[(mesh.points[boundary][:, :, 0] == 0).all(axis=1)]
    assert len(wall) > 2 and _rows(mesh.protected_faces) == _rows(wall)
    assert set(mesh.protected_face_labels.tolist()) == {7}
    assert len(mesh.protected_vertices) == 0
    assert [(ns.name, ns.ids.tolist(), ns.label) for ns in mesh.node_sets] == [("probe", [3, 7], 4)]


def test_meshio_netcdf4_file_reads_as_the_classic_one():
    """meshio's netCDF-4 file (HDF5, read through h5py; its ``coord`` variable and
    "TETRA" type names) holds the same points and tets."""
    a, b = jtet.load(MESHIO), jtet.load(CLASSIC)
    np.testing.assert_array_equal(a.points, b.points)
    assert _rows(a.tets) == _rows(b.tets)
    assert sorted(np.unique(a.region).tolist()) == [0, 1]
    assert [(ns.name, ns.ids.tolist(), ns.label) for ns in a.node_sets] == [("probe", [3, 7], 0)]


@pytest.fixture(scope="module")
def labelled():
    mesh = delaunay_mesh(80, seed=8, surface_points=40)
    T = mesh.topology
    faces = T.faces[T.boundary_face]
    centre = mesh.points[faces].mean(axis=1)
    labels = np.where(np.isclose(centre[:, 2], 0), 5, np.where(np.isclose(centre[:, 2], 1), 6, 9))
    inside = np.setdiff1d(np.arange(mesh.n_points), np.unique(faces))
    return mesh.replace(
        region=np.where(mesh.points[mesh.tets].mean(axis=1)[:, 2] < 0.5, 1, 2),
        protected_faces=faces,
        protected_face_labels=labels,
        protected_vertices=inside[:3],
        protected_vertex_labels=[5, 5, 11],  # 5 is a side set's id too: renumbered
        label_names={
            (3, 1): "bottom half",
            (2, 5): "floor",
            (2, 6): "lid",
            (0, 5): "probes",
        },
        # overlapping sets; id 6 is a side set's, the second set has none
        node_sets=[("inlet", inside[2:6], 6), ("tip", inside[4:8])],
    )


def test_round_trip(tmp_path, labelled):
    """Everything comes back (coordinates bit for bit), but the ids of a vertex label
    and of a node set that a side set already uses, and the id of a node set without
    one: each takes the next free id, with its name; overlapping node sets stay whole."""
    path = tmp_path / "m.exo"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jtet.save(labelled, path, cell_data={"q": labelled.quality()})
    back = jtet.load(path)
    for name in ("points", "tets", "region", "protected_faces", "protected_face_labels",
                 "protected_vertices"):  # fmt: skip
        np.testing.assert_array_equal(getattr(back, name), getattr(labelled, name), name)
    assert back.protected_vertex_labels.tolist() == [12, 12, 11]
    got = [(ns.name, ns.ids.tolist(), ns.label) for ns in back.node_sets]
    expected = [(ns.name, ns.ids.tolist(), k) for ns, k in zip(labelled.node_sets, [13, 14])]
    assert got == expected
    assert dict(back.label_names) == {**{k: v for k, v in labelled.label_names.items()
                                         if k[0] != 0}, (0, 12): "probes"}  # fmt: skip


def test_vtk_reads_jtet_files(tmp_path, labelled):
    """VTK's Exodus reader (independent of jtet): the blocks' tets, each side set's faces
    as ``_exodus``'s table would not know them (VTK's own side table), pointing out of
    the mesh, and the element variable's values."""
    vtk = pytest.importorskip("vtkmodules.vtkIOExodus")
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import vtkCompositeDataSet

    path = tmp_path / "m.exo"
    q = labelled.quality()
    jtet.save(labelled, path, cell_data={"q": q})
    reader = vtk.vtkExodusIIReader()
    reader.SetFileName(str(path))
    reader.UpdateInformation()
    kind = vtk.vtkExodusIIReader.SIDE_SET
    for i in range(reader.GetNumberOfObjects(kind)):
        reader.SetObjectStatus(kind, i, 1)
    block = vtk.vtkExodusIIReader.ELEM_BLOCK
    reader.SetObjectArrayStatus(block, "q", 1)
    reader.GenerateGlobalNodeIdArrayOn()
    reader.Update()
    it = reader.GetOutput().NewIterator()
    it.InitTraversal()
    seen_faces, seen_q = {}, []
    while not it.IsDoneWithTraversal():
        ds = it.GetCurrentDataObject()
        name = it.GetCurrentMetaData().Get(vtkCompositeDataSet.NAME())
        ids = vtk_to_numpy(ds.GetPointData().GetArray("PedigreeNodeId")) - 1
        cells = vtk_to_numpy(ds.GetCells().GetConnectivityArray())
        if ds.GetCell(0).GetNumberOfPoints() == 3:
            seen_faces[name] = ids[cells.reshape(-1, 3)]
        else:
            seen_q.append(vtk_to_numpy(ds.GetCellData().GetArray("q")))
        it.GoToNextItem()
    expected = {"floor": 5, "lid": 6, "SURFACE9": 9}
    assert set(seen_faces) == {"floor", "lid"} | {n for n in seen_faces if "9" in n}
    p = labelled.points
    for name, faces in seen_faces.items():
        label = expected.get(name, 9)
        mine = labelled.protected_faces[labelled.protected_face_labels == label]
        assert _rows(faces) == _rows(mine), name
        normal = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
        outward = p[faces].mean(axis=1) - 0.5  # the unit cube's centre
        assert ((normal * outward).sum(axis=1) > 0).all(), name
    order = np.argsort(labelled.region, kind="stable")
    np.testing.assert_array_equal(np.concatenate(seen_q), q[order])


def test_improve_cli(tmp_path):
    out = tmp_path / "out.exo"
    assert (
        main(["improve", str(CLASSIC), str(out), "-q", "--max-passes", "2", "--perturb", "0"]) == 0
    )
    before, after = jtet.load(CLASSIC), jtet.load(out)
    # the side set covers the same wall (its faces may be flipped within the flat wall)
    assert set(after.protected_faces.ravel().tolist()) == set(
        before.protected_faces.ravel().tolist()
    )

    def area(m):
        p = m.points[m.protected_faces]
        return np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum() / 2

    assert area(after) == pytest.approx(area(before), rel=1e-12) == pytest.approx(1.0)
    assert after.node_sets[0].ids.tolist() == [3, 7]
    assert jtet.mesh_stats(after).min_dihedral > jtet.mesh_stats(before).min_dihedral


def _write_netcdf(path, build):
    from scipy.io import netcdf_file

    f = netcdf_file(str(path), "w", version=2)
    build(f)
    f.close()
    return path


def _base(f, n=5, dims=3):
    f.createDimension("num_nodes", n)
    for axis in "xyz"[:dims]:
        f.createVariable(f"coord{axis}", "f8", ("num_nodes",))[:] = np.eye(n, 3, -1)[:, 0]


def _block(f, b, cells, kind):
    cells = np.asarray(cells, np.int32)
    f.createDimension(f"num_el_in_blk{b}", len(cells))
    f.createDimension(f"num_nod_per_el{b}", cells.shape[1])
    v = f.createVariable(f"connect{b}", "i4", (f"num_el_in_blk{b}", f"num_nod_per_el{b}"))
    v[:] = cells
    v.elem_type = kind


@pytest.mark.parametrize(
    "build, error, match",
    [
        (lambda f: _base(f, dims=2), MeshInputError, "2-D"),
        (lambda f: f.createDimension("x", 1), MeshInputError, "no node coordinates"),
        (lambda f: (_base(f), _block(f, 1, [[1, 2, 3]], "TRI3")), MeshInputError,
         "no tetrahedra"),
        (lambda f: (_base(f, 8), _block(f, 1, [[1, 2, 3, 4, 5, 6, 7, 8]], "HEX8")),
         MeshInputError, "HEX8"),
        (lambda f: (_base(f), _block(f, 1, [[1, 2, 3, 9]], "TETRA4")), MeshInputError,
         "range|index"),
    ],
)  # fmt: skip
def test_bad_files_are_clear_errors(tmp_path, build, error, match):
    with pytest.raises(error, match=match):
        jtet.load(_write_netcdf(tmp_path / "bad.exo", build))


def test_not_netcdf_and_cdf5(tmp_path):
    path = tmp_path / "bad.exo"
    for data, match in [(b"hello world", "not a netCDF file"), (b"CDF\x05" + bytes(60), "CDF5")]:
        path.write_bytes(data)
        with pytest.raises(MeshFileError, match="not a readable Exodus file") as e:
            jtet.load(path)
        assert match in str(e.value)


def test_side_set_past_the_elements(tmp_path):
    def build(f):
        _base(f)
        _block(f, 1, [[1, 2, 3, 4], [2, 3, 4, 5]], "TETRA4")
        f.createDimension("num_side_ss1", 1)
        f.createVariable("elem_ss1", "i4", ("num_side_ss1",))[:] = [3]
        f.createVariable("side_ss1", "i4", ("num_side_ss1",))[:] = [1]

    with pytest.raises(MeshInputError, match="side set 1 names element 3"):
        jtet.load(_write_netcdf(tmp_path / "bad.exo", build))


def test_element_variables_are_cell_data(tmp_path):
    """A solver's element variables in the file (a stress) are cell data; jtet's own
    per-tet arrays are not read back (they are recomputed for every output)."""
    mesh = jtet.load(CLASSIC)
    path = tmp_path / "results.exo"
    stress = np.column_stack([mesh.volumes, -mesh.volumes])
    with_data = mesh.replace(cell_data={"stress": stress})
    jtet.save(with_data, path, cell_data={"quality_min_sine": mesh.quality()})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = jtet.load(path)
    assert list(back.cell_data) == ["stress"]
    np.testing.assert_array_equal(back.cell_data["stress"], stress)


def test_element_variables_of_two_blocks_at_the_last_time_step(tmp_path):
    """Element variables per block, at the last of two time steps; a block without
    the variable (the truth table's 0) gets NaN; one of another length is refused."""

    def build(f, count=1):
        f.createDimension("time_step", None)
        f.createDimension("len_name", 33)
        f.createVariable("time_whole", "f8", ("time_step",))[:2] = [0.0, 2.5]
        _base(f)
        f.variables["coordy"][:] = [0, 0, 1, 0, 0]
        f.variables["coordz"][:] = [0, 0, 0, 1, -1]
        _block(f, 1, [[1, 2, 3, 4]], "TETRA4")
        _block(f, 2, [[1, 3, 2, 5]], "TETRA4")
        f.createDimension("num_elem_var", 2)
        f.createVariable("name_elem_var", "c", ("num_elem_var", "len_name"))[:] = np.array(
            [list("s".ljust(33, "\0")), list("e".ljust(33, "\0"))], "S1"
        )
        f.createDimension("two", count)
        for name, values in (("vals_elem_var1eb1", [1.0, 2.0]), ("vals_elem_var1eb2", [3.0, 4.0])):
            f.createVariable(name, "f8", ("time_step", "two"))[:2] = np.reshape(values, (2, 1))
        f.createVariable("vals_elem_var2eb1", "f8", ("time_step", "num_el_in_blk1"))[:2] = [
            [5.0],
            [6.0],
        ]

    with pytest.raises(MeshInputError, match="element variable 's' does not hold one value"):
        jtet.load(_write_netcdf(tmp_path / "bad.exo", lambda f: build(f, count=3)))
    with pytest.warns(UserWarning, match=r"element variables are read at the last of 2"):
        mesh = jtet.load(_write_netcdf(tmp_path / "two.exo", build))
    np.testing.assert_array_equal(mesh.cell_data["s"], [2.0, 4.0])
    np.testing.assert_array_equal(mesh.cell_data["e"], [6.0, np.nan])


def _solution_file(path, values, stacked=False):
    """Two tets over 5 nodes with nodal variables "T" and "u_x" at len(values) time
    steps (``values``: (steps, 2, 5)), as MOOSE writes results; ``stacked``: the older
    single (time, variable, node) array ``vals_nod_var``."""

    def build(f):
        f.createDimension("time_step", None)
        f.createDimension("len_name", 33)
        f.createVariable("time_whole", "f8", ("time_step",))
        _base(f)
        f.variables["coordy"][:] = [0, 0, 1, 0, 0]
        f.variables["coordz"][:] = [0, 0, 0, 1, -1]
        _block(f, 1, [[1, 2, 3, 4], [1, 3, 2, 5]], "TETRA4")
        f.createDimension("num_nod_var", 2)
        f.createVariable("name_nod_var", "c", ("num_nod_var", "len_name"))[:] = np.array(
            [list("T".ljust(33, "\0")), list("u_x".ljust(33, "\0"))], "S1"
        )
        f.variables["time_whole"][: len(values)] = np.arange(len(values)) * 0.5
        if stacked:
            v = f.createVariable("vals_nod_var", "f8", ("time_step", "num_nod_var", "num_nodes"))
            v[:] = values
        else:
            for k in range(2):
                v = f.createVariable(f"vals_nod_var{k + 1}", "f8", ("time_step", "num_nodes"))
                v[:] = values[:, k]

    return _write_netcdf(path, build)


@pytest.mark.parametrize("stacked", [False, True])
def test_nodal_variables_at_the_last_time_step(tmp_path, stacked):
    """A solver's nodal variables are point data, read at the last time step (with a
    warning naming it); jtet writes them back as nodal variables at one time step."""
    values = np.arange(30, dtype=float).reshape(3, 2, 5)
    path = _solution_file(tmp_path / "results.exo", values, stacked)
    with pytest.warns(UserWarning, match=r"last of 3 time steps \(time 1\)"):
        mesh = jtet.load(path)
    assert list(mesh.point_data) == ["T", "u_x"]
    np.testing.assert_array_equal(mesh.point_data["T"], values[-1, 0])
    np.testing.assert_array_equal(mesh.point_data["u_x"], values[-1, 1])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = jtet.load(jtet.save(mesh, tmp_path / "out.exo"))
    for name, a in mesh.point_data.items():
        np.testing.assert_array_equal(back.point_data[name], a)


def test_nodal_variable_of_another_length_refused(tmp_path):
    def build(f):
        f.createDimension("len_name", 33)
        _base(f)
        _block(f, 1, [[1, 2, 3, 4]], "TETRA4")
        f.createDimension("num_nod_var", 1)
        f.createDimension("three", 3)
        f.createVariable("name_nod_var", "c", ("num_nod_var", "len_name"))[:] = np.array(
            [list("T".ljust(33, "\0"))], "S1"
        )
        f.createVariable("vals_nod_var1", "f8", ("three",))[:] = [1, 2, 3]

    with pytest.raises(MeshInputError, match="nodal variable 'T' does not hold one value per"):
        jtet.load(_write_netcdf(tmp_path / "bad.exo", build))


def test_tetra10_block_reads_as_linear(tmp_path):
    """A TETRA10 block (corners first, then the mid-edge nodes) is refused with the
    --linear hint, and read as its TETRA4 corners with ``linear=True``."""
    _, points = unit_tet10()

    def build(f):
        f.createDimension("num_nodes", len(points))
        for c, axis in enumerate("xyz"):
            f.createVariable(f"coord{axis}", "f8", ("num_nodes",))[:] = points[:, c]
        _block(f, 1, [np.arange(1, 11)], "TETRA10")

    path = _write_netcdf(tmp_path / "tet10.exo", build)
    read_as_unit_tet(path)
