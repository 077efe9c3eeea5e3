"""Quadratic output (``save(..., quadratic=True)``, ``--quadratic``) and the curved
edges a quadratic input keeps (``TetMesh.curved_edges``): the nodes against Gmsh's own
second-order mesh (read by meshio and by Gmsh), volumes by Gmsh's Jacobians, the
Jacobian check against a brute-force isoparametric map, the field through improve."""

import warnings

import numpy as np
import pytest
from helpers import (
    TETGEN_EDGES,
    delaunay_mesh,
    gmsh_model,
    gmsh_region_volumes,
    named_ball_in_box,
    tetgen_file,
)

import jtet
from jtet._errors import MeshFileError, MeshInputError
from jtet._quadratic import MID_EDGES, folded_tets, jacobian_ratios, quadratic_mesh
from jtet.cli import main

FORMATS = ["vtu", "vtk", "msh", "inp", "med", "exo", "xdmf", "node", "mesh", "meshb"]


@pytest.fixture(scope="module")
def gmsh_files(tmp_path_factory):
    """Gmsh's ball in a box (``named_ball_in_box``), linear and at order 2 (.msh 4.1)."""
    out = tmp_path_factory.mktemp("quadratic_output")
    named_ball_in_box(out / "linear.msh", second_order=[out / "quadratic.msh"])
    return out


def _load_linear(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return jtet.load(path, linear=True)


def _edge_nodes(points, tets10, order=MID_EDGES[4]) -> dict:
    """{(sorted rounded corner coordinates of an edge): rounded node coordinates} of 10-node
    tets in VTK's order (meshio's; or the edges ``order``), independent of the node
    numbering."""
    p = np.round(np.asarray(points, np.float64), 12)
    out = {}
    for (i, j), col in zip(order, range(4, 10), strict=True):
        for a, b, m in zip(p[tets10[:, i]], p[tets10[:, j]], p[tets10[:, col]], strict=True):
            out[tuple(sorted([tuple(a), tuple(b)]))] = tuple(m)
    return out


def _gmsh_tets10(path):
    """(points, 10-node tets 0-based in Gmsh's order) of a file Gmsh opens."""
    with gmsh_model() as gmsh:
        gmsh.open(str(path))
        tags, coords, _ = gmsh.model.mesh.getNodes()
        at = np.zeros(int(tags.max()) + 1, np.int64)
        at[tags.astype(np.int64)] = np.arange(len(tags))
        kinds, _, nodes = gmsh.model.mesh.getElements(3)
        assert [int(k) for k in kinds] == [11]  # 10-node tets only
        return coords.reshape(-1, 3), at[nodes[0].astype(np.int64)].reshape(-1, 10)


def _meshb_tets10(path):
    """(points, TetrahedraP2 rows 0-based) of a binary Medit file of version 2 (4-byte
    positions: ``save`` writes that below 2 GiB), walked keyword by keyword by hand."""
    data = np.fromfile(path, np.uint8)
    assert data[:8].view("<i4").tolist() == [1, 2]
    points, tets, at = None, None, 8
    while True:
        code, nxt = data[at : at + 8].view("<i4").tolist()
        if code == 54:  # End
            return points, tets
        count = int(data[at + 8 : at + 12].view("<i4")[0])
        body = data[at + 12 : nxt]
        if code == 4:  # Vertices: x y z (float64) and a reference (int32)
            rows = body.view(np.dtype([("xyz", "<f8", 3), ("ref", "<i4")]))
            points = rows["xyz"].astype(np.float64)
        elif code == 30:  # TetrahedraP2: 10 nodes and a reference
            tets = body.view("<i4").reshape(count, 11)[:, :10].astype(np.int64) - 1
        at = nxt


@pytest.mark.parametrize("ext", FORMATS)
def test_written_nodes_are_gmsh_second_order_nodes(gmsh_files, tmp_path, ext):
    """Gmsh's order-2 mesh read with --linear and written with quadratic=True has
    Gmsh's nodes on every edge (its curved ones on the ball among them), read back in
    VTK's order by VTK (.vtu, .vtk, .exo, .xdmf) or meshio from jtet's file and by meshio from
    Gmsh's (MED: by Gmsh and MEDCoupling, below)."""
    meshio = pytest.importorskip("meshio")
    mesh = _load_linear(gmsh_files / "quadratic.msh")
    assert len(mesh.curved_edges.edges) > 50  # the ball's curved edges
    out = tmp_path / f"out.{ext}"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the 2 tets Gmsh's own mesh folds (folded_tets)
        jtet.save(mesh, out, quadratic=True)
    reference = meshio.read(gmsh_files / "quadratic.msh")
    tets10 = reference.get_cells_type("tetra10")
    expected = _edge_nodes(reference.points, tets10)
    if ext in ("vtu", "vtk", "exo"):  # VTK's readers (meshio 5.3: no int64 legacy arrays)
        pv = pytest.importorskip("pyvista")
        grid = pv.read(out)
        if ext == "exo":  # VTK's Exodus reader: a block per region
            grid = grid.combine()
        # VTK_QUADRATIC_TETRA (and the Exodus side sets' faces, VTK_QUADRATIC_TRIANGLE)
        assert set(grid.celltypes.tolist()) == ({22, 24} if ext == "exo" else {24})
        got = _edge_nodes(grid.points, grid.cells_dict[24])
        if ext == "exo":  # VTK's Exodus reader rounds the points to float32
            expected = _edge_nodes(reference.points.astype(np.float32), tets10)
        assert got == expected
    elif ext == "xdmf":  # VTK's XDMF reader (ParaView's); meshio reads one grid only
        pv = pytest.importorskip("pyvista")
        from vtkmodules.vtkIOXdmf2 import vtkXdmfReader

        reader = vtkXdmfReader()
        reader.SetFileName(str(out))
        reader.Update()
        grid = pv.wrap(reader.GetOutputDataObject(0))["mesh"]
        assert set(grid.celltypes.tolist()) == {24}  # VTK_QUADRATIC_TETRA
        assert _edge_nodes(grid.points, grid.cells_dict[24]) == expected
    elif ext == "mesh":  # Medit P2, read by Gmsh (its tet10 order swaps the last two)
        points, tets = _gmsh_tets10(out)
        assert _edge_nodes(points, tets[:, [0, 1, 2, 3, 4, 5, 6, 7, 9, 8]]) == expected
    elif ext == "meshb":  # binary Medit P2 (keyword 30), parsed by hand
        points, tets = _meshb_tets10(out)
        assert _edge_nodes(points, tets) == expected
    elif ext == "node":  # TetGen's order, parsed by hand (tests/test_tetgen_o2.py)
        points, tets, _ = tetgen_file(out)
        assert _edge_nodes(points, tets, TETGEN_EDGES) == expected
    elif ext != "med":
        written = meshio.read(out)
        assert _edge_nodes(written.points, written.get_cells_type("tetra10")) == expected
    again = _load_linear(out)  # and the way back: the same corners and curved edges
    # the node sets written for regions, surfaces and side sets (with their edges'
    # nodes) are theirs again, not node sets of their own
    assert again.node_sets == mesh.node_sets == ()
    np.testing.assert_array_equal(again.points, mesh.points)
    np.testing.assert_array_equal(again.tets, mesh.tets)
    np.testing.assert_array_equal(again.curved_edges.edges, mesh.curved_edges.edges)
    np.testing.assert_array_equal(again.curved_edges.points, mesh.curved_edges.points)
    # the protected faces (the walls, the sphere), from the 6-node triangles
    assert len(mesh.protected_faces)
    np.testing.assert_array_equal(again.protected_faces, mesh.protected_faces)
    np.testing.assert_array_equal(again.protected_face_labels, mesh.protected_face_labels)


@pytest.mark.parametrize("ext", ["msh", "med"])
def test_gmsh_measures_the_curved_ball_after_improve(gmsh_files, tmp_path, ext):
    """improve keeps the ball's surface (a region interface), so the quadratic output's
    ball has, by Gmsh's own Jacobians, the volume of Gmsh's second-order ball (closer to
    the sphere's than the linear mesh's), and the box the volume of Gmsh's box."""
    mesh = _load_linear(gmsh_files / "quadratic.msh")
    result = jtet.improve(mesh, seed=0, max_passes=3, perturb=0)
    assert result.mesh.n_tets != mesh.n_tets or (result.mesh.tets != mesh.tets).any()
    np.testing.assert_array_equal(result.mesh.curved_edges.edges, mesh.curved_edges.edges)
    assert any("curved edges" in note for note in result.notes)
    out = tmp_path / f"improved.{ext}"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a folded tet or two, as in Gmsh's own mesh
        jtet.save(result.mesh, out, quadratic=True)
    got, types = gmsh_region_volumes(out)
    reference, _ = gmsh_region_volumes(gmsh_files / "quadratic.msh")
    assert types == {11}  # Gmsh's 10-node tet
    assert got["ball"] == pytest.approx(reference["ball"], rel=1e-12)
    # the unit cube, to Gmsh's own sum for its mesh (which misses 1 by 3.4e-12)
    assert got["box"] == pytest.approx(reference["box"], rel=1e-12)
    assert got["ball"] + got["box"] == pytest.approx(1.0, rel=1e-11)
    sphere = 4 / 3 * np.pi * 0.25**3
    linear = mesh.volumes[mesh.region == 1].sum()
    assert abs(got["ball"] - sphere) < 0.5 * abs(linear - sphere)


def test_quadratic_mesh_against_brute_force():
    """On a random mesh: one node per edge, shared by the tets around it, at the midpoint
    of the edge VTK's order names; point data averaged (integers: the smaller), node
    sets with the nodes of their edges."""
    mesh = delaunay_mesh(60, seed=3)
    n = mesh.n_points
    temperature = mesh.points @ [1.0, -2.0, 0.5]
    marker = (mesh.points[:, 0] > 0.5).astype(np.int64)
    chosen = np.flatnonzero(mesh.points[:, 2] < 0.4)
    mesh = mesh.replace(point_data={"T": temperature, "m": marker}, node_sets=[("low", chosen)])
    quad = quadratic_mesh(mesh)
    edges = {tuple(sorted(e)) for t in mesh.tets.tolist() for e in
             [(t[i], t[j]) for i, j in MID_EDGES[4]]}  # fmt: skip
    assert len(quad.points) == n + len(edges)
    node_of = {}
    for t, row in zip(mesh.tets, quad.tets, strict=True):
        np.testing.assert_array_equal(row[:4], t)
        for (i, j), node in zip(MID_EDGES[4], row[4:], strict=True):
            key = tuple(sorted((int(t[i]), int(t[j]))))
            assert node_of.setdefault(key, int(node)) == node  # one node per edge
            np.testing.assert_allclose(quad.points[node], mesh.points[list(key)].mean(axis=0))
            assert quad.point_data["T"][node] == pytest.approx(
                quad.points[node] @ [1.0, -2.0, 0.5], rel=1e-12, abs=1e-12
            )
            assert quad.point_data["m"][node] == marker[list(key)].min()
    low = set(quad.node_sets[0].ids.tolist())
    inside = set(chosen.tolist())
    assert low == inside | {node_of[e] for e in node_of if set(e) <= inside}
    assert not quad.curved.any() and folded_tets(quad) == (0, 1.0)


def _jacobian_dets_brute_force(x: np.ndarray) -> np.ndarray:
    """det J of one 10-node tet ``x`` (10, 3) at its 10 nodes, from the explicit shape
    functions in (u, v, w) and central differences (exact for their quadratics)."""

    def position(u, v, w):
        lam = [1 - u - v - w, u, v, w]
        shape = [lam[i] * (2 * lam[i] - 1) for i in range(4)]
        shape += [4 * lam[i] * lam[j] for i, j in MID_EDGES[4]]
        return np.array(shape) @ x

    nodes = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]
    nodes += [tuple((np.array(nodes[i]) + nodes[j]) / 2) for i, j in MID_EDGES[4]]
    h = 1e-3
    out = []
    for u in nodes:
        cols = []
        for d in np.eye(3):
            cols.append(
                (position(*(np.add(u, h * d))) - position(*(np.subtract(u, h * d)))) / (2 * h)
            )
        out.append(np.linalg.det(np.array(cols).T))
    return np.array(out)


def test_jacobian_ratios_against_brute_force():
    """Random 10-node tets (a random tet, its mid-edge nodes moved by up to 30 % of its
    size): the smallest det J at the nodes over the straight tet's, as the explicit
    shape functions give it (to 1e-9: central differences of quadratics are exact up
    to rounding)."""
    rng = np.random.default_rng(7)
    for _ in range(40):
        corners = rng.random((4, 3))
        if np.linalg.det(corners[1:] - corners[0]) < 0:
            corners = corners[[1, 0, 2, 3]]
        mids = np.array([(corners[i] + corners[j]) / 2 for i, j in MID_EDGES[4]])
        x = np.vstack([corners, mids + 0.3 * (rng.random((6, 3)) - 0.5)])
        got = jacobian_ratios(x, np.arange(10)[None])[0]
        straight = np.linalg.det(corners[1:] - corners[0])
        expected = _jacobian_dets_brute_force(x).min() / straight
        assert got == pytest.approx(expected, rel=1e-9, abs=1e-9)


def test_folded_tet_warns(tmp_path):
    """A curved edge bent into its tet (the node of edge 12 of the unit tet pulled to
    (0.1, 0.1, 0)): det J at corner 1 is 1 - 1.6 = -0.6 times the straight tet's (by
    hand: dx/dL2 - dx/dL0 gains 4 x (-0.4, -0.4, 0))."""
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    mesh = jtet.TetMesh(points, [[0, 1, 2, 3]], curved_edges=([[2, 1]], [[0.1, 0.1, 0]]))
    assert folded_tets(quadratic_mesh(mesh)) == (1, pytest.approx(-0.6))
    with pytest.warns(UserWarning, match=r"1 quadratic tet\(s\) have a non-positive Jacobian"):
        jtet.save(mesh, tmp_path / "folded.vtu", quadratic=True)
    outward = mesh.replace(curved_edges=([[1, 2]], [[0.6, 0.6, 0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jtet.save(outward, tmp_path / "bulging.vtu", quadratic=True)


def test_curved_edges_field_checks_and_moves():
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    mesh = jtet.TetMesh(
        points, [[0, 1, 2, 3]], curved_edges=([[3, 0], [0, 3]], [[0, 0, 0.6], [9, 9, 9]])
    )
    np.testing.assert_array_equal(mesh.curved_edges.edges, [[0, 3]])  # sorted, first kept
    np.testing.assert_array_equal(mesh.curved_edges.points, [[0, 0, 0.6]])
    assert "1 curved edges" in repr(mesh)
    for bad, what in [
        (([[0, 4]], [[0, 0, 0]]), "out of range"),
        (([[1, 1]], [[0, 0, 0]]), "to itself"),
        (([[0, 1]], [[np.nan, 0, 0]]), "NaN"),
        (([[0, 1], [0, 2]], [[0, 0, 0]]), "2 edges and 1"),
        ("x", "curved_edges must be"),
    ]:
        with pytest.raises(MeshInputError, match=what):
            mesh.replace(curved_edges=bad)
    assert mesh.replace(points=points.copy()).has_curved_edges  # nothing moved
    moved = points.copy()
    moved[3, 2] = 1.2
    assert not mesh.replace(points=moved).has_curved_edges  # an end moved: straight again
    moved = points.copy()
    moved[1, 0] = 1.2
    assert mesh.replace(points=moved).has_curved_edges  # another vertex moved


def test_refused_formats_and_cli(gmsh_files, tmp_path, capsys):
    """--quadratic to an unknown extension fails before the input is read (every
    format jtet writes takes it); the CLI's improve and convert write 10-node tets that
    Gmsh reads."""
    mesh = _load_linear(gmsh_files / "quadratic.msh")
    with pytest.raises(MeshFileError, match="extension"):
        jtet.save(mesh, tmp_path / "out.sol", quadratic=True)
    assert not (tmp_path / "out.sol").exists()
    missing = tmp_path / "missing.msh"
    assert main(["improve", str(missing), str(tmp_path / "o.sol"), "--quadratic"]) == 2
    assert "extension" in capsys.readouterr().err
    src = gmsh_files / "quadratic.msh"
    out = tmp_path / "improved.msh"
    args = ["improve", str(src), str(out), "-q", "--linear", "--quadratic", "--perturb", "0"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(args) == 0
        assert main(["convert", str(src), str(tmp_path / "c.inp"), "-q", "--linear",
                     "--quadratic"]) == 0  # fmt: skip
    _, types = gmsh_region_volumes(out)
    assert types == {11}
    text = (tmp_path / "c.inp").read_text()
    assert "TYPE=C3D10" in text and "TYPE=C3D4" not in text


def test_abaqus_sets_come_back_as_they_were(tmp_path):
    """An .inp written quadratic has region and surface node sets with their mid-edge
    nodes (as Gmsh's SaveGroupsOfNodes writes them); read back with --linear they are
    the region's and surface's again, not node sets of their own; a node set of the
    mesh keeps its corners and gains the nodes of its edges."""
    mesh = delaunay_mesh(40, seed=5)
    chosen = np.flatnonzero(mesh.points[:, 0] < 0.5)
    mesh = mesh.replace(node_sets=[("LEFT", chosen)])
    jtet.save(mesh, tmp_path / "q.inp", quadratic=True)
    again = _load_linear(tmp_path / "q.inp")
    assert [ns.name for ns in again.node_sets] == ["LEFT"]
    np.testing.assert_array_equal(again.node_sets[0].ids, chosen)


def test_medcoupling_reads_t10_cells(gmsh_files, tmp_path):
    """MEDCoupling (Salome's MED library) reads the T10 output: 10-node tets of positive
    volume, each node on its edge in MED's order (N5 on N1-N2, N6 on N2-N3, N7 on N3-N1,
    N8 on N1-N4, N9 on N2-N4, N10 on N3-N4): at its midpoint, or on the sphere with
    both ends; the groups, and the point and cell fields on the nodes and the T10 cells,
    which jtet reads back."""
    mc = pytest.importorskip("medcoupling")
    mesh = _load_linear(gmsh_files / "quadratic.msh")
    mesh = mesh.replace(
        point_data={"T": 2.0 * mesh.points[:, 0]}, cell_data={"mat": np.arange(mesh.n_tets) % 3}
    )
    out = tmp_path / "q.med"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        jtet.save(mesh, out, quadratic=True)
    mm = mc.MEDFileUMesh.New(str(out))
    volume = mm.getMeshAtLevel(0)
    assert volume.getAllGeoTypes() == [mc.NORM_TETRA10]
    assert (volume.getMeasureField(False).getArray().toNumPyArray() > 0).all()
    coords = mm.getCoords().toNumPyArray()
    conn = volume.getNodalConnectivity().toNumPyArray().reshape(-1, 11)[:, 1:]
    med_edges = [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)]

    def on_sphere(x):
        return abs(np.linalg.norm(x - 0.5, axis=1) - 0.25) < 1e-9

    n_curved = 0
    for column, (i, j) in enumerate(med_edges, start=4):
        a, b, node = coords[conn[:, i]], coords[conn[:, j]], coords[conn[:, column]]
        straight = np.linalg.norm(node - (a + b) / 2, axis=1) < 1e-12
        curved = on_sphere(node) & on_sphere(a) & on_sphere(b) & ~straight
        assert (straight | curved).all()
        n_curved += int(curved.sum())
    assert n_curved >= len(mesh.curved_edges.edges)  # each curved edge in a tet or more
    assert set(mm.getGroupsOnSpecifiedLev(0)) == {"ball", "box"}
    again = _load_linear(out)
    np.testing.assert_array_equal(again.cell_data["mat"], mesh.cell_data["mat"])
    np.testing.assert_array_equal(again.point_data["T"], mesh.point_data["T"])


def test_jacobian_ratios_are_gmsh_scaled_jacobians(gmsh_files):
    """jtet's smallest det J at the nodes over the straight tet's is, tet for tet, Gmsh's
    own minSJ quality of its 10-node tets (sorted: Gmsh lists them by entity), to 1e-12,
    the two folded ones of Gmsh's ball in a box included."""
    gmsh = pytest.importorskip("gmsh")
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Verbosity", 1)
        gmsh.open(str(gmsh_files / "quadratic.msh"))
        _, tags, _ = gmsh.model.mesh.getElements(3)
        expected = np.sort(gmsh.model.mesh.getElementQualities(np.concatenate(tags), "minSJ"))
    finally:
        gmsh.finalize()
    quad = quadratic_mesh(_load_linear(gmsh_files / "quadratic.msh"))
    got = np.sort(jacobian_ratios(quad.points, quad.tets))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
    assert (got <= 0).sum() == folded_tets(quad)[0] == 2


def test_stats_reports_the_curved_tets(gmsh_files, capsys):
    """jtet stats --linear of a quadratic file: its curved edges, the tets that fold and
    the smallest scaled Jacobian (text and JSON); nothing of the kind for a linear file."""
    import json

    src = str(gmsh_files / "quadratic.msh")
    mesh = _load_linear(gmsh_files / "quadratic.msh")
    n_curved = len(mesh.curved_edges.edges)
    # the gmsh ball's curved edges are the sphere's: every one bends the ball's surface
    topo = mesh.topology
    assert (topo.edge_n_subfacets[topo.edge_ids(mesh.curved_edges.edges)] > 0).all()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["stats", src, "--linear"]) == 0
        text = capsys.readouterr().out
        assert f"quadratic: {n_curved} curved edges ({n_curved} bend a bounding" in text
        assert "; 2 tet(s) folded" in text
        assert main(["stats", src, "--linear", "--json"]) == 0
        curved = json.loads(capsys.readouterr().out)["curved"]
        assert curved["edges"] == curved["surface_edges"] == n_curved
        assert curved["folded_tets"] == 2
        assert curved["min_scaled_jacobian"] == pytest.approx(-0.1155, abs=1e-4)
        assert main(["stats", str(gmsh_files / "linear.msh"), "--json"]) == 0
        assert "curved" not in json.loads(capsys.readouterr().out)


def test_improve_drops_curved_edges_it_flips_or_moves():
    """Every edge of a random mesh given a node off its midpoint: improve with the
    boundary sliding flips some edges away and moves some ends; the result keeps exactly
    the curved edges that are still edges of its tets with both ends in place (a
    brute-force set of the result's edges), and its note counts the dropped ones."""
    mesh = delaunay_mesh(80, seed=2)
    edges = np.unique(np.sort(mesh.tets[:, MID_EDGES[4]].reshape(-1, 2), axis=1), axis=0)
    bent = mesh.points[edges].mean(axis=1) + 1e-3
    mesh = mesh.replace(curved_edges=(edges, bent))
    result = jtet.improve(mesh, seed=0, boundary="slide", max_passes=3, perturb=0)
    out = result.mesh
    have = {tuple(sorted(e)) for t in out.tets.tolist() for e in
            [(t[i], t[j]) for i, j in MID_EDGES[4]]}  # fmt: skip
    expected = [
        i for i, (a, b) in enumerate(edges.tolist())
        if (a, b) in have and (out.points[[a, b]] == mesh.points[[a, b]]).all()
    ]  # fmt: skip
    assert 0 < len(expected) < len(edges)
    np.testing.assert_array_equal(out.curved_edges.edges, edges[expected])
    np.testing.assert_array_equal(out.curved_edges.points, bent[expected])
    assert any(f"; {len(edges) - len(expected)} dropped" in note for note in result.notes)


def test_gmsh_medit_p2_file_reads_as_its_order_2_mesh(tmp_path):
    """Gmsh writes its order-2 mesh of a ball as a Medit file of P2 sections
    (TetrahedraP2, TrianglesP2) and as .msh: without --linear the Medit file is refused
    with the hint; with it, it reads as the same corners, tets, curved edges and
    boundary faces as the .msh file, compared by coordinates (the node order is
    Medit's, VTK's: a wrong order would make straight edges curved). (Gmsh 4.15
    crashes writing the ball in a box of the tests above as Medit.)"""
    with gmsh_model() as gmsh:
        gmsh.model.occ.addSphere(0.5, 0.5, 0.5, 0.25)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.1)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.setOrder(2)
        gmsh.write(str(tmp_path / "gmsh_p2.msh"))
        gmsh.write(str(tmp_path / "gmsh_p2.mesh"))
    text = (tmp_path / "gmsh_p2.mesh").read_text()
    assert "TetrahedraP2" in text and "TrianglesP2" in text
    with pytest.raises(MeshInputError, match="--linear"):
        jtet.load(tmp_path / "gmsh_p2.mesh")
    medit = _load_linear(tmp_path / "gmsh_p2.mesh")
    msh = _load_linear(tmp_path / "gmsh_p2.msh")

    def rows(a):  # sorted by their coordinates to 8 digits (Gmsh's Medit writer prints 14)
        a = np.asarray(a, np.float64).reshape(len(a), -1)
        return np.lexsort(np.round(a, 8).T[::-1])

    close = {"rtol": 0, "atol": 1e-13}
    mine, theirs = rows(medit.points), rows(msh.points)
    np.testing.assert_allclose(medit.points[mine], msh.points[theirs], **close)
    as_msh = np.empty(medit.n_points, np.int64)  # medit's point ids -> msh's
    as_msh[mine] = theirs

    def same_cells(a, b):
        a, b = np.sort(as_msh[a], axis=1), np.sort(b, axis=1)
        np.testing.assert_array_equal(np.unique(a, axis=0), np.unique(b, axis=0))

    same_cells(medit.tets, msh.tets)
    same_cells(medit.protected_faces, msh.protected_faces)
    same_cells(medit.curved_edges.edges, msh.curved_edges.edges)
    assert len(msh.curved_edges.edges) > 50
    mapped = np.sort(as_msh[medit.curved_edges.edges], axis=1)
    order = np.lexsort(mapped.T[::-1])  # msh's curved edges are sorted so
    np.testing.assert_allclose(medit.curved_edges.points[order], msh.curved_edges.points, **close)


@pytest.mark.parametrize("damage", ["count", "word"])
def test_damaged_medit_p2_section_is_refused(tmp_path, damage):
    """A P2 section whose count does not match its numbers, or with a word among
    them, is a clear MeshFileError, and the temporary copy made for meshio is gone."""
    import tempfile
    from pathlib import Path

    mesh = delaunay_mesh(30, seed=1)
    jtet.save(mesh, tmp_path / "p2.mesh", quadratic=True)
    text = (tmp_path / "p2.mesh").read_text()
    head, rest = text.split("TetrahedraP2\n", 1)
    count, rows = rest.split("\n", 1)
    if damage == "count":
        rest = f"{int(count) + 1}\n{rows}"
    else:
        rest = f"{count}\n{rows.replace(' ', ' x ', 1)}"
    (tmp_path / "p2.mesh").write_text(head + "TetrahedraP2\n" + rest)
    before = set(Path(tempfile.gettempdir()).glob("jtet-medit-*"))
    with pytest.raises(MeshFileError, match="unreadable TetrahedraP2 section"):
        jtet.load(tmp_path / "p2.mesh", linear=True)
    assert set(Path(tempfile.gettempdir()).glob("jtet-medit-*")) == before
