"""Quadratic meshes read as linear ones (``jtet.load(path, linear=True)``, ``--linear``):
Gmsh's second-order mesh in five formats against the linear mesh it was made from,
node sets and point data after the mid-edge nodes are left out, the refusal without
the flag."""

import warnings

import numpy as np
import pytest
from helpers import named_ball_in_box, read_as_unit_tet, unit_tet10

import jtet
from jtet._errors import MeshInputError
from jtet.cli import main


def _key_rows(points, cells) -> set:
    """The cells as sets of rounded coordinates (independent of the vertex numbering)."""
    p = np.round(points, 12)
    return {tuple(sorted(map(tuple, p[c]))) for c in np.asarray(cells)}


@pytest.fixture(scope="module")
def gmsh_files(tmp_path_factory):
    """Gmsh's ball in a box (``named_ball_in_box``): the linear mesh as .msh, then the
    same mesh at order 2 in five formats."""
    out = tmp_path_factory.mktemp("quadratic")
    second = [out / f"quadratic.{ext}" for ext in ("msh", "vtk", "inp", "med")]
    named_ball_in_box(out / "linear.msh", second_order=[*second, (out / "quadratic22.msh", 2.2)])
    return out


@pytest.mark.parametrize("name", ["quadratic.msh", "quadratic22.msh", "quadratic.vtk",
                                  "quadratic.inp", "quadratic.med"])  # fmt: skip
def test_gmsh_second_order_mesh_reads_as_its_linear_mesh(gmsh_files, name):
    linear = jtet.load(gmsh_files / "linear.msh")
    with pytest.raises(MeshInputError, match="--linear"):
        jtet.load(gmsh_files / name)
    with pytest.warns(UserWarning, match=r"read as linear ones .* mid-edge node\(s\) left out"):
        mesh = jtet.load(gmsh_files / name, linear=True)
    assert mesh.n_points == linear.n_points  # every mid-edge node left out, no corner
    assert _key_rows(mesh.points, mesh.tets) == _key_rows(linear.points, linear.tets)
    assert (mesh.volumes > 0).all()
    assert mesh.volumes.sum() == pytest.approx(1.0, rel=1e-12)
    assert _key_rows(mesh.points, mesh.protected_faces) == _key_rows(
        linear.points, linear.protected_faces
    )
    if name != "quadratic.vtk":  # Gmsh's legacy VTK files carry no physical groups
        names = {mesh.label_names[(3, int(r))] for r in np.unique(mesh.region)}
        assert names == {"ball", "box"}
        for region in ("ball", "box"):
            a = linear.volumes[linear.region == (1 if region == "ball" else 2)].sum()
            (label,) = [k for (d, k), v in mesh.label_names.items() if d == 3 and v == region]
            assert mesh.volumes[mesh.region == label].sum() == pytest.approx(a, rel=1e-12)


INP = """*NODE
{nodes}*ELEMENT, TYPE=C3D10, ELSET=SOLID
1, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10
*NSET, NSET=FIXED
1, 2, 5
*NSET, NSET=MIDS
6, 7
"""


def test_node_sets_and_point_order_follow(tmp_path):
    """A C3D10 element whose nodes 5-10 are its mid-edge nodes, written in a shuffled
    order: the linear mesh keeps the 4 corners in file order, and the node sets keep
    their corners (a set of mid-edge nodes only ends empty)."""
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    edges = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]  # C3D10's mid-node order
    mids = np.array([(corners[a] + corners[b]) / 2 for a, b in edges])
    # file node ids 1-4 the corners, 5-10 the mid nodes, listed mids first
    rows = [(5 + i, *mids[i]) for i in range(6)] + [(1 + i, *corners[i]) for i in range(4)]
    text = "".join(f"{r[0]}, {r[1]}, {r[2]}, {r[3]}\n" for r in rows)
    path = tmp_path / "tet10.inp"
    path.write_text(INP.format(nodes=text))
    with pytest.warns(UserWarning, match="6 mid-edge node"):
        mesh = jtet.load(path, linear=True)
    np.testing.assert_array_equal(mesh.points, corners)  # the corners, in file order
    np.testing.assert_array_equal(mesh.tets, [[0, 1, 2, 3]])
    sets = {ns.name: ns.ids.tolist() for ns in mesh.node_sets}
    assert sets["FIXED"] == [0, 1]
    assert sets.get("MIDS", []) == []


def test_vtu_point_data_follows(tmp_path):
    """A VTK quadratic tet with a point array: the array keeps the corners' values."""
    pv = pytest.importorskip("pyvista")
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    edges = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]  # VTK_QUADRATIC_TETRA's order
    points = np.vstack([[(corners[a] + corners[b]) / 2 for a, b in edges], corners])
    ids = [6, 7, 8, 9, 0, 1, 2, 3, 4, 5]  # corners first, as VTK lists them
    grid = pv.UnstructuredGrid(np.array([10, *ids]), np.array([24]), points)
    grid.point_data["T"] = points[:, 0] + 10 * points[:, 1]
    grid.save(tmp_path / "q.vtu")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = jtet.load(tmp_path / "q.vtu", linear=True)
    np.testing.assert_array_equal(mesh.points, corners)
    np.testing.assert_array_equal(mesh.point_data["T"], corners[:, 0] + 10 * corners[:, 1])


def test_cli_flag(tmp_path, gmsh_files, capsys):
    out = tmp_path / "out.msh"
    src = gmsh_files / "quadratic.inp"
    assert main(["improve", str(src), str(out), "-q", "--max-passes", "2", "--perturb", "0"]) == 2
    assert "--linear" in capsys.readouterr().err and not out.exists()
    args = ["improve", str(src), str(out), "-q", "--max-passes", "2", "--perturb", "0", "--linear"]
    assert main(args) == 0
    improved = jtet.load(out)
    assert improved.n_points == jtet.load(gmsh_files / "linear.msh").n_points
    assert main(["stats", str(src), "--linear"]) == 0


def test_xdmf_written_by_meshio(tmp_path):
    """meshio's XDMF file of one ``tetra10``: refused, then read as its corners."""
    meshio = pytest.importorskip("meshio")
    _, points = unit_tet10()
    path = tmp_path / "q.xdmf"
    meshio.write(path, meshio.Mesh(points, [("tetra10", np.arange(10)[None])]))
    read_as_unit_tet(path)


def test_quadratic_vtk_cell_of_the_wrong_size_is_refused(tmp_path):
    """A damaged VTK file: a quadratic triangle of 1 vertex names no corners and
    mid-edge nodes; refused with its cell id (fuzz_files.py --quadratic found it as a
    NumPy error)."""
    pv = pytest.importorskip("pyvista")
    _, points = unit_tet10()
    cells = np.array([10, *range(10), 1, 0])
    grid = pv.UnstructuredGrid(cells, np.array([24, 22], np.uint8), points)
    grid.save(tmp_path / "bad.vtu")
    with pytest.raises(MeshInputError, match=r"cell 1 is a quadratic cell of 1 vertices"):
        jtet.load(tmp_path / "bad.vtu", linear=True)
