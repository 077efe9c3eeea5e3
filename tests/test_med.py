"""MED meshes (``jtet._med``): files Gmsh writes with the MED library, Gmsh and meshio
reading jtet's files, round trips and bad files."""

import warnings

import h5py
import numpy as np
import pytest
from helpers import delaunay_mesh, gmsh_model, named_ball_in_box, unit_tet10

import jtet
from jtet._errors import MeshFileError, MeshInputError
from jtet.cli import main


def _rows(a) -> set:
    return {tuple(sorted(r)) for r in np.asarray(a).tolist()}


def _by_name(mesh, dim: int, labels) -> dict:
    """{name: the rows whose label carries it} of labelled cells (regions: dim 3)."""
    out = {}
    for label in np.unique(labels).tolist():
        out[mesh.label_names.get((dim, label), "")] = np.flatnonzero(labels == label)
    return out


def test_gmsh_med_file_reads_as_its_msh_file(tmp_path):
    """Gmsh writes one mesh (a ball in a box, the box's walls a physical surface) as .msh
    and, through the MED library, as .med: jtet reads the same points, tets (positive:
    the MED tet order is undone), regions and walls, by name."""
    msh, med = tmp_path / "m.msh", tmp_path / "m.med"
    named_ball_in_box(msh, med)
    a, b = jtet.load(msh), jtet.load(med)
    # the .msh file is text with 16 digits (within an ulp of Gmsh's coordinates in [0, 1]),
    # the .med file binary
    np.testing.assert_allclose(a.points, b.points, rtol=0, atol=2e-16)
    assert (b.volumes > 0).all()
    np.testing.assert_array_equal(a.tets, b.tets)
    regions_a, regions_b = _by_name(a, 3, a.region), _by_name(b, 3, b.region)
    assert set(regions_b) == {"ball", "box"}
    for name in regions_b:
        np.testing.assert_array_equal(regions_a[name], regions_b[name])
    walls = _by_name(b, 2, b.protected_face_labels)
    assert set(walls) == {"walls"}
    assert _rows(b.protected_faces) == _rows(a.protected_faces[a.protected_face_labels == 10])


def _boundary_faces(tets) -> np.ndarray:
    """(k, 3) sorted faces of one tet (NumPy, independent of jtet's topology)."""
    sides = np.sort(tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1)
    faces, count = np.unique(sides, axis=0, return_counts=True)
    return faces[count == 1]


def _labelled_mesh():
    """A Delaunay cube with two named regions, two face labels (x = 0 named "x0", y = 0
    in two groups: "inlet+wall"), an edge, a corner, overlapping node sets, a vector and
    a scalar point array and an integer cell array."""
    mesh = delaunay_mesh(60, seed=3, surface_points=20)
    p = mesh.points
    region = np.where(p[mesh.tets].mean(axis=1)[:, 0] < 0.5, 1, 2)
    faces = _boundary_faces(mesh.tets)
    on_x0 = (p[faces][:, :, 0] == 0).all(axis=1)
    on_y0 = (p[faces][:, :, 1] == 0).all(axis=1) & ~on_x0
    chosen = np.concatenate([faces[on_x0], faces[on_y0]])
    labels = np.concatenate([np.full(on_x0.sum(), 1), np.full(on_y0.sum(), 3)])
    edge = faces[on_x0][:1, :2]
    corner = np.flatnonzero(np.isclose(p, 0).all(axis=1))
    assert len(corner) == 1
    rng = np.random.default_rng(0)
    return mesh.replace(
        region=region,
        protected_faces=chosen,
        protected_face_labels=labels,
        protected_edges=edge,
        protected_edge_labels=[5],
        protected_vertices=corner,
        protected_vertex_labels=[2],
        label_names={(3, 1): "left", (3, 2): "right", (2, 1): "x0", (2, 3): "inlet+wall"},
        node_sets=[("probe", [4, 7, 9]), ("fix", [7, 9, 11, 30]), ("", [0])],
        point_data={"T": rng.random(mesh.n_points), "u": rng.random((mesh.n_points, 3))},
        cell_data={"material": rng.integers(0, 5, mesh.n_tets)},
    )


def test_round_trip_keeps_everything_by_name(tmp_path):
    mesh = _labelled_mesh()
    path = tmp_path / "out.med"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # MED stores all of it: no warning
        jtet.save(mesh, path, cell_data={"q": mesh.quality("min_sine")})
        back = jtet.load(path)
    np.testing.assert_array_equal(back.points, mesh.points)  # float64, bit for bit
    np.testing.assert_array_equal(back.tets, mesh.tets)
    # labels keep their numbers where two kinds of cells do not want the same family
    np.testing.assert_array_equal(back.region, mesh.region)
    assert back.label_names[(3, 1)] == "left" and back.label_names[(3, 2)] == "right"
    faces = _by_name(back, 2, back.protected_face_labels)
    assert set(faces) == {"x0", "inlet+wall"}
    assert _rows(back.protected_faces[faces["x0"]]) == _rows(
        mesh.protected_faces[mesh.protected_face_labels == 1]
    )
    assert _rows(back.protected_faces[faces["inlet+wall"]]) == _rows(
        mesh.protected_faces[mesh.protected_face_labels == 3]
    )
    assert back.protected_face_labels[faces["inlet+wall"]][0] == 3  # free: kept
    assert back.protected_face_labels[faces["x0"]][0] != 1  # region 1 took family -1
    assert _rows(back.protected_edges) == _rows(mesh.protected_edges)
    assert back.label_names[(1, int(back.protected_edge_labels[0]))] == "edge_5"
    np.testing.assert_array_equal(back.protected_vertices, mesh.protected_vertices)
    assert back.label_names[(0, int(back.protected_vertex_labels[0]))] == "vertex_2"
    sets = {ns.name: ns.ids.tolist() for ns in back.node_sets}
    assert sets == {"probe": [4, 7, 9], "fix": [7, 9, 11, 30], "nodes_2": [0]}
    np.testing.assert_array_equal(back.point_data["T"], mesh.point_data["T"])
    np.testing.assert_array_equal(back.point_data["u"], mesh.point_data["u"])
    np.testing.assert_array_equal(back.cell_data["material"], mesh.cell_data["material"])
    np.testing.assert_array_equal(back.cell_data["q"], mesh.quality("min_sine"))


def test_quality_arrays_are_not_read_back(tmp_path):
    """The per-tet arrays ``jtet improve`` writes are fields of its MED output; loading
    that output leaves them out (every output gets fresh ones), as for the other formats."""
    from jtet._report import quality_cell_data

    mesh = _labelled_mesh()
    path = tmp_path / "out.med"
    jtet.save(mesh, path, cell_data=quality_cell_data(mesh))
    with h5py.File(path) as f:
        assert {"min_dihedral", "volume", "material"} <= set(f["CHA"])
    assert list(jtet.load(path).cell_data) == ["material"]


def test_gmsh_reads_jtet_files(tmp_path):
    """Gmsh (the MED library) reads jtet's file: positive tets in Gmsh's vertex order,
    the groups as physical groups with their names, the fields as views."""
    mesh = _labelled_mesh()
    path = tmp_path / "out.med"
    jtet.save(mesh, path, cell_data={"q": mesh.quality("min_sine")})
    with gmsh_model() as gmsh:
        gmsh.open(str(path))
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        xyz = np.empty((int(node_tags.max()) + 1, 3))
        xyz[node_tags.astype(np.int64)] = coords.reshape(-1, 3)
        types, _, nodes = gmsh.model.mesh.getElements(3)
        assert list(types) == [4]  # 4-node tets
        tets = nodes[0].astype(np.int64).reshape(-1, 4)
        a, b, c, d = (xyz[tets[:, i]] for i in range(4))
        volumes = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6
        groups = {gmsh.model.getPhysicalName(*g) for g in gmsh.model.getPhysicalGroups()}
        views = [gmsh.option.getString(f"View[{i}].Name") for i in range(len(gmsh.view.getTags()))]
    assert len(tets) == mesh.n_tets
    assert (volumes > 0).all()
    assert volumes.sum() == pytest.approx(mesh.volumes.sum(), rel=1e-12)
    assert {"left", "right", "x0", "inlet", "wall"} <= groups
    assert {"T", "u", "material", "q"} <= set(views)


def test_meshio_reads_jtet_files(tmp_path):
    """meshio's MED reader (which keeps MED's vertex order) sees the tets with their second
    and third vertices swapped, and the families' groups. (meshio 5.3 cannot read a field
    on the tets of a file that has other cells too: the cell arrays are left out here.)"""
    meshio = pytest.importorskip("meshio")
    mesh = _labelled_mesh().replace(cell_data=None)
    path = tmp_path / "out.med"
    jtet.save(mesh, path)
    m = meshio.read(path)
    tetra = next(b.data for b in m.cells if b.type == "tetra")
    np.testing.assert_array_equal(tetra, mesh.tets[:, [0, 2, 1, 3]])
    groups = {name for names in m.cell_tags.values() for name in names}
    assert {"left", "right", "x0", "inlet", "wall", "edge_5", "vertex_2"} <= groups


def test_improve_cli(tmp_path):
    src, out = tmp_path / "in.med", tmp_path / "out.med"
    named_ball_in_box(src)
    assert main(["improve", str(src), str(out), "-q", "--max-passes", "3", "--perturb", "0"]) == 0
    before, after = jtet.load(src), jtet.load(out)
    assert sorted(after.label_names.values()) == sorted(before.label_names.values())
    for name in ("ball", "box"):
        vb = before.volumes[_by_name(before, 3, before.region)[name]].sum()
        va = after.volumes[_by_name(after, 3, after.region)[name]].sum()
        assert va == pytest.approx(vb, rel=1e-12)
    assert jtet.mesh_stats(after).min_dihedral > jtet.mesh_stats(before).min_dihedral
    with h5py.File(out) as f:  # the mesh is named after the file, as Salome names it
        assert list(f["ENS_MAA"]) == ["out"]
        assert "min_dihedral" in f["CHA"]  # the output's per-tet arrays, as fields


def _tiny(tmp_path, edit=None, name="bad.med"):
    """A valid one-tet MED file written by jtet, then changed by ``edit(h5py.File)``."""
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    path = tmp_path / name
    jtet.save(jtet.TetMesh(pts, [[0, 1, 2, 3]]), path)
    if edit is not None:
        with h5py.File(path, "r+") as f:
            edit(f)
    return path


def _step(f):
    mesh = next(iter(f["ENS_MAA"].values()))
    return next(iter(mesh.values()))


def _add_cells(kind, nodes, count):
    def edit(f):
        mai = _step(f)["MAI"]
        g = mai.create_group(kind)
        d = g.create_dataset("NOD", data=np.ones(nodes * count, np.int64))
        d.attrs["NBR"] = count

    return edit


def _second_mesh(f):
    f.copy(f["ENS_MAA"]["bad"], f["ENS_MAA"], name="other")


def _flat(f):
    f["ENS_MAA"]["bad"].attrs["ESP"] = 2


def _no_tets(f):
    del _step(f)["MAI"]["TE4"]
    _add_cells("TR3", 3, 1)(f)


@pytest.mark.parametrize(
    "edit, error, match",
    [
        (_add_cells("HE8", 8, 2), MeshInputError, r"2 cells are not tetrahedra \(HEXA8 x 2\)"),
        (_add_cells("T10", 10, 1), MeshInputError, "quadratic"),
        (_second_mesh, MeshInputError, "2 meshes"),
        (_flat, MeshInputError, "2-D"),
        (_no_tets, MeshInputError, "no tetrahedra"),
        (lambda f: f.__delitem__("ENS_MAA"), MeshFileError, "not a MED file"),
        (lambda f: _step(f)["NOE"].__delitem__("COO"), MeshFileError, "not a readable MED"),
    ],
)
def test_bad_files_are_clear_errors(tmp_path, edit, error, match):
    with pytest.raises(error, match=match):
        jtet.load(_tiny(tmp_path, edit))


def test_not_hdf5_and_truncated(tmp_path):
    path = tmp_path / "bad.med"
    path.write_text("hello world\n")
    with pytest.raises(MeshFileError, match="not a readable MED file"):
        jtet.load(path)
    good = _tiny(tmp_path, name="good.med").read_bytes()
    path.write_bytes(good[: len(good) // 2])
    with pytest.raises(MeshFileError, match="not a readable MED file"):
        jtet.load(path)


def test_other_cells_are_left_out_with_a_warning(tmp_path):
    path = _tiny(tmp_path, _add_cells("QU4", 4, 1))
    with pytest.warns(UserWarning, match=r"left out: QU4 x 1"):
        mesh = jtet.load(path)
    assert mesh.n_tets == 1


def test_fields_at_the_last_step(tmp_path):
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    path = tmp_path / "f.med"
    jtet.save(jtet.TetMesh(pts, [[0, 1, 2, 3]], point_data={"T": [1.0, 2, 3, 4]}), path)
    with h5py.File(path, "r+") as f:
        field = f["CHA"]["T"]
        first = next(iter(field))
        field.copy(field[first], field, name="0000000000000000000200000000000000000001")
        later = field["0000000000000000000200000000000000000001"]
        later.attrs["NDT"] = 2
        co = later["NOE"]["MED_NO_PROFILE_INTERNAL"]["CO"]
        co[...] = co[()] * 10
    with pytest.warns(UserWarning, match="last step: T"):
        mesh = jtet.load(path)
    np.testing.assert_array_equal(mesh.point_data["T"], [10.0, 20, 30, 40])


def _medcoupling_file(path, mesh, faces, x0, y0, left):
    """``mesh`` written by MEDCoupling (Salome's MED library for Python): tets in MED's
    vertex order, groups "left" and "all" of tets (overlapping), "x0" and "y0" of
    triangles, a node group "probe" and a field "T" on the nodes."""
    mc = pytest.importorskip("medcoupling")

    def umesh(dim, kind, cells):
        um = mc.MEDCouplingUMesh("m", dim)
        um.setCoords(mc.DataArrayDouble(np.ascontiguousarray(mesh.points)))
        k = cells.shape[1]
        conn = np.hstack([np.full((len(cells), 1), kind), cells]).astype(np.int64).ravel()
        index = np.arange(len(cells) + 1, dtype=np.int64) * (k + 1)
        um.setConnectivity(mc.DataArrayInt64(conn), mc.DataArrayInt64(index))
        return um

    def group(name, ids):
        a = mc.DataArrayInt64(np.asarray(ids, np.int64))
        a.setName(name)
        return a

    vol = umesh(3, mc.NORM_TETRA4, mesh.tets[:, [0, 2, 1, 3]])
    tri = umesh(2, mc.NORM_TRI3, np.concatenate([faces[x0], faces[y0]]))
    tri.setCoords(vol.getCoords())
    mm = mc.MEDFileUMesh()
    mm.setMeshAtLevel(0, vol)
    mm.setMeshAtLevel(-1, tri)
    mm.setGroupsAtLevel(0, [group("left", left), group("all", np.arange(mesh.n_tets))])
    mm.setGroupsAtLevel(
        -1, [group("x0", np.arange(len(x0))), group("y0", len(x0) + np.arange(len(y0)))]
    )
    mm.addNodeGroup(group("probe", [4, 7, 9]))
    mm.write(str(path), 2)
    field = mc.MEDCouplingFieldDouble(mc.ON_NODES, mc.ONE_TIME)
    field.setMesh(vol)
    field.setName("T")
    field.setArray(mc.DataArrayDouble(np.ascontiguousarray(mesh.points[:, 0])))
    field.setTime(0.0, 0, 0)
    mc.WriteFieldUsingAlreadyWrittenMesh(str(path), field)


def test_medcoupling_files_both_ways(tmp_path):
    """MEDCoupling, the MED library Salome reads and writes with, as the reference: its
    file loads with jtet's tets, groups, node group and field; jtet's file loads in it
    with positive volumes (MED's orientation), the same groups and the fields."""
    mesh = delaunay_mesh(60, seed=3, surface_points=20)
    p = mesh.points
    faces = _boundary_faces(mesh.tets)
    x0 = np.flatnonzero((p[faces][:, :, 0] == 0).all(axis=1))
    y0 = np.flatnonzero(
        (p[faces][:, :, 1] == 0).all(axis=1) & ~(p[faces][:, :, 0] == 0).all(axis=1)
    )
    left = np.flatnonzero(p[mesh.tets].mean(axis=1)[:, 0] < 0.5)
    theirs = tmp_path / "mc.med"
    _medcoupling_file(theirs, mesh, faces, x0, y0, left)
    back = jtet.load(theirs)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    regions = _by_name(back, 3, back.region)
    assert set(regions) == {"all", "all+left"}  # the tets of both groups, and the others
    np.testing.assert_array_equal(regions["all+left"], left)
    assert len(regions["all"]) == mesh.n_tets - len(left)
    faces_back = _by_name(back, 2, back.protected_face_labels)
    assert _rows(back.protected_faces[faces_back["x0"]]) == _rows(faces[x0])
    assert _rows(back.protected_faces[faces_back["y0"]]) == _rows(faces[y0])
    assert [(s.name, s.ids.tolist()) for s in back.node_sets] == [("probe", [4, 7, 9])]
    np.testing.assert_array_equal(back.point_data["T"], p[:, 0])

    import medcoupling as mc

    ours = tmp_path / "ours.med"
    jtet.save(back, ours, cell_data={"q": back.quality("min_sine")})
    mm = mc.MEDFileUMesh.New(str(ours))
    assert set(mm.getGroupsNames()) == {"all", "left", "x0", "y0", "probe"}
    volumes = mm.getMeshAtLevel(0).getMeasureField(False).getArray().toNumPyArray()
    np.testing.assert_allclose(volumes, mesh.volumes, rtol=1e-12)  # signed: all positive
    left_again = mm.getGroupArr(0, "left").toNumPyArray()
    np.testing.assert_array_equal(np.sort(left_again), left)
    np.testing.assert_array_equal(np.sort(mm.getGroupArr(1, "probe").toNumPyArray()), [4, 7, 9])
    assert set(mc.MEDFileFields.New(str(ours)).getFieldsNames()) == {"T", "q"}


def test_med2_layout_reads_as_the_med3_one(tmp_path):
    """MED 2 files keep the nodes and cells in the mesh's group itself (no computing
    step) and the families under it: the same file moved to that layout loads the same."""
    mesh = _labelled_mesh()
    med3, med2 = tmp_path / "a.med", tmp_path / "b.med"
    jtet.save(mesh, med3)
    jtet.save(mesh, med2)
    with h5py.File(med2, "r+") as f:
        group = f["ENS_MAA"]["b"]
        (step,) = list(group)
        for key in ("NOE", "MAI"):
            group.move(f"{step}/{key}", key)
        del group[step]
        f.move("FAS/b", "ENS_MAA/b/FAS")
    a, b = jtet.load(med3), jtet.load(med2)
    np.testing.assert_array_equal(a.tets, b.tets)
    np.testing.assert_array_equal(a.region, b.region)
    assert a.label_names == b.label_names
    assert [(s.name, s.ids.tolist()) for s in a.node_sets] == [
        (s.name, s.ids.tolist()) for s in b.node_sets
    ]


def test_mesh_of_several_steps_reads_its_last(tmp_path):
    """A mesh whose coordinates change over computing steps: the last step (by NDT) is
    read, with a warning."""
    path = _tiny(tmp_path, name="steps.med")
    with h5py.File(path, "r+") as f:
        group = f["ENS_MAA"]["steps"]
        (first,) = list(group)
        later = "0000000000000000000200000000000000000001"
        group.copy(group[first], group, name=later)
        group[later].attrs["NDT"] = 2
        coords = group[later]["NOE"]["COO"]
        coords[...] = coords[()] * 2
    with pytest.warns(UserWarning, match="last of its 2 computing steps"):
        mesh = jtet.load(path)
    assert mesh.volumes.sum() == pytest.approx(8 / 6)  # the unit tet scaled by 2


def test_linear_tets_beside_quadratic_ones(tmp_path):
    """TE4 and T10 cells in one file, read with ``linear=True``: both kinds of tets
    (the T10's corners in MED's order swapped too), the T10 without families in region
    0, its 6 mid-edge nodes left out."""
    corners, nodes = unit_tet10()
    apex = np.array([[1 / 3, 1 / 3, -1.0]])  # below the face z = 0
    points = np.vstack([corners, apex, nodes[4:]])  # 5 corners, then 6 mid-edge nodes
    path = tmp_path / "mixed.med"
    jtet.save(jtet.TetMesh(points, [[0, 1, 2, 3]], region=[3]), path)
    below = np.array([0, 2, 1, 4])  # jtet's order, positive
    with h5py.File(path, "r+") as f:
        group = _step(f)["MAI"].create_group("T10")
        nod = np.concatenate([below[[0, 2, 1, 3]], np.arange(5, 11)])  # MED's order
        d = group.create_dataset("NOD", data=nod + 1)
        d.attrs["NBR"] = 1
    with pytest.warns(UserWarning, match="6 mid-edge node"):
        mesh = jtet.load(path, linear=True)
    np.testing.assert_array_equal(mesh.points, points[:5])
    # the types in the file's (HDF5's, by name) order: T10 before TE4
    np.testing.assert_array_equal(mesh.tets, [below, [0, 1, 2, 3]])
    np.testing.assert_array_equal(mesh.region, [0, 3])
    assert (mesh.volumes > 0).all()
