"""Periodic meshes (Gmsh ``$Periodic``, ``TetMesh.periodic``): improve keeps the periodic
surfaces' triangulations images of each other, and the links are written back."""

import types

import numpy as np
import pytest
from helpers import gmsh_mesh_and_write, gmsh_model

import jtet
from jtet._io import _gmsh_periodic
from jtet.cli import main

gmsh = pytest.importorskip("gmsh")


def _periodic_box(path, version=2.2, h=0.2):
    """The unit cube meshed with its face x = 1 periodic to x = 0 (translation)."""
    with gmsh_model():
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        gmsh.model.occ.synchronize()

        def face_at(x):
            for dim, tag in gmsh.model.getEntities(2):
                box = gmsh.model.getBoundingBox(dim, tag)
                if abs(box[0] - x) < 1e-5 and abs(box[3] - x) < 1e-5:
                    return tag

        shift = [1, 0, 0, 1, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
        gmsh.model.mesh.setPeriodic(2, [face_at(1.0)], [face_at(0.0)], shift)
        gmsh_mesh_and_write(gmsh, path, h, version)


def _boundary_faces(mesh):
    T = mesh.topology
    return np.sort(T.faces[T.boundary_face], axis=1)


def _assert_periodic(mesh):
    """Every link's slave vertices are its master vertices moved by the affine map, and
    (surfaces) the slave surface's boundary triangles are the master's, vertex for vertex."""
    assert mesh.periodic
    faces = _boundary_faces(mesh)
    for link in mesh.periodic:
        slave, master = link.pairs[:, 0], link.pairs[:, 1]
        A = np.array(link.affine).reshape(4, 4)
        image = mesh.points[master] @ A[:3, :3].T + A[:3, 3]
        np.testing.assert_allclose(mesh.points[slave], image, atol=1e-12)
        if link.dim == 2:
            to_master = dict(zip(slave.tolist(), master.tolist(), strict=True))
            on_master = set(master.tolist())
            slave_tris = {
                tuple(sorted(to_master[v] for v in f))
                for f in faces.tolist()
                if all(v in to_master for v in f)
            }
            master_tris = {tuple(f) for f in faces.tolist() if all(v in on_master for v in f)}
            assert slave_tris == master_tris and len(master_tris) > 10


@pytest.mark.parametrize("version", [2.2, 4.1])
@pytest.mark.parametrize("boundary", ["fixed", "slide"])
def test_improve_keeps_periodic_surfaces_matching(tmp_path, version, boundary):
    src = tmp_path / "box.msh"
    _periodic_box(src, version)
    mesh = jtet.load(src)
    _assert_periodic(mesh)
    assert [link.dim for link in mesh.periodic].count(2) == 1
    r = jtet.improve(mesh, boundary=boundary, check=True)
    assert r.status == "converged"
    assert r.stats_after.min_dihedral > r.stats_before.min_dihedral
    out = r.mesh
    _assert_periodic(out)
    assert len(out.periodic) == len(mesh.periodic)
    for a, b in zip(out.periodic, mesh.periodic, strict=True):
        assert a.tags == b.tags and np.array_equal(a.pairs, b.pairs)
    # the run's pins are not left on the output
    assert len(out.protected_edges) == len(mesh.protected_edges)
    assert np.array_equal(out.protected_vertices, mesh.protected_vertices)


def test_without_the_links_sliding_breaks_periodicity(tmp_path):
    # the reference the test above needs: the same run on the mesh without its links
    src = tmp_path / "box.msh"
    _periodic_box(src)
    mesh = jtet.load(src)
    out = jtet.improve(mesh.replace(periodic=()), boundary="slide").mesh
    with pytest.raises(AssertionError):
        _assert_periodic(out.replace(periodic=mesh.periodic))


def test_periodic_links_are_written_back(tmp_path):
    src, out = tmp_path / "box.msh", tmp_path / "out.msh"
    _periodic_box(src)
    assert main(["improve", str(src), str(out), "--boundary", "slide", "-q"]) == 0
    mesh, written = jtet.load(src), jtet.load(out)
    _assert_periodic(written)
    # jtet writes Gmsh 2.2 files, whose $Periodic section lists the links as Gmsh's own
    # 2.2 files do (meshio reads them back above; Gmsh's API shows periodic nodes only
    # for 4.1 files, its own 2.2 files' included)
    text = out.read_bytes()
    assert text.count(b"$Periodic") == 1 and text.count(b"$EndPeriodic") == 1
    links = jtet.load(out).periodic
    assert [(a.dim, a.tags) for a in links] == [(b.dim, b.tags) for b in mesh.periodic]
    assert all(np.array_equal(a.pairs, b.pairs) for a, b in zip(links, mesh.periodic, strict=True))
    # VTK files keep them as field data; Medit files cannot (a warning)
    for ext in (".vtu", ".vtk"):
        jtet.save(written, tmp_path / f"o{ext}")
        _assert_periodic(jtet.load(tmp_path / f"o{ext}"))
    with pytest.warns(UserWarning, match="periodic link"):
        jtet.save(written, tmp_path / "o.mesh")


def test_links_that_do_not_match_the_mesh_are_dropped():
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    shift = np.array([1, 0, 0, 1, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1], float)
    good = [2, (2, 1), shift, np.array([[1, 0], [3, 2]])]
    wrong = [2, (4, 3), shift, np.array([[2, 0]])]  # point 2 is no image of point 0
    out_of_range = [2, (6, 5), None, np.array([[1, 7]])]
    m = types.SimpleNamespace(points=points, gmsh_periodic=[good, wrong, out_of_range])
    with pytest.warns(UserWarning, match="2 periodic link"):
        links = _gmsh_periodic(m, "f.msh")
    assert [link[1] for link in links] == [(2, 1)]


def test_periodic_field_is_checked():
    mesh = jtet.demo_mesh()
    ok = mesh.replace(periodic=[(2, (2, 1), None, [[0, 1]])])
    assert ok.periodic[0].pairs.tolist() == [[0, 1]] and not ok.periodic[0].pairs.flags.writeable
    for bad in ([(3, (2, 1), None, [[0, 1]])], [(2, (2, 1), [1.0] * 3, [[0, 1]])],
                [(2, (2, 1), None, [[0, mesh.n_points]])], [(2, (2, 1), None, [[0.5, 1]])],
                [(2, 1)]):  # fmt: skip
        with pytest.raises(jtet.MeshInputError, match="periodic"):
            mesh.replace(periodic=bad)


def test_periodic_links_with_protected_tets(tmp_path):
    # the periodic pins wrap the protected tets' part run: both hold
    src = tmp_path / "box.msh"
    _periodic_box(src)
    mesh = jtet.load(src)
    kept = mesh.tets[np.argsort(mesh.quality())[:5]]
    r = jtet.improve(mesh.replace(protected_tets=kept), boundary="slide", check=True)
    assert r.status == "converged" and r.selected_stats is not None
    _assert_periodic(r.mesh)
    rows = {tuple(t) for t in np.sort(r.mesh.tets, axis=1).tolist()}
    assert all(tuple(t) in rows for t in np.sort(kept, axis=1).tolist())
    assert np.array_equal(r.mesh.protected_edges, mesh.protected_edges)


def _periodic_rve(path, h):
    """A ball in the unit cube, periodic in x, y and z (every face of the cube tied to its
    opposite: surfaces, and Gmsh adds their curves and points), physical volumes
    "inclusion" (1) and "matrix" (2), MSH 4.1."""
    with gmsh_model():
        box = gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        ball = gmsh.model.occ.addSphere(0.5, 0.5, 0.5, 0.3)
        gmsh.model.occ.fragment([(3, box)], [(3, ball)])
        gmsh.model.occ.synchronize()
        eps = 1e-5
        for axis in range(3):
            hi = [1 + eps] * 3
            hi[axis] = eps
            for _, master in gmsh.model.getEntitiesInBoundingBox(-eps, -eps, -eps, *hi, 2):
                b = list(gmsh.model.getBoundingBox(2, master))
                b[axis] += 1
                b[axis + 3] += 1
                lo_b, hi_b = [v - eps for v in b[:3]], [v + eps for v in b[3:]]
                for _, slave in gmsh.model.getEntitiesInBoundingBox(*lo_b, *hi_b, 2):
                    shift = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
                    shift[4 * axis + 3] = 1
                    gmsh.model.mesh.setPeriodic(2, [slave], [master], shift)
        vols = sorted(gmsh.model.getEntities(3), key=lambda e: gmsh.model.occ.getMass(*e))
        gmsh.model.addPhysicalGroup(3, [vols[0][1]], 1, "inclusion")
        gmsh.model.addPhysicalGroup(3, [vols[1][1]], 2, "matrix")
        gmsh_mesh_and_write(gmsh, path, h, 4.1)


def test_three_way_periodic_rve(tmp_path):
    src, out = tmp_path / "rve.msh", tmp_path / "out.msh"
    _periodic_rve(src, 0.12)
    mesh = jtet.load(src)
    assert [link.dim for link in mesh.periodic].count(2) == 3
    assert main(["improve", str(src), str(out), "--boundary", "slide", "--check", "-q"]) == 0
    written = jtet.load(out)
    _assert_periodic(written)
    assert len(written.periodic) == len(mesh.periodic)
    assert dict(written.label_names) == {(3, 1): "inclusion", (3, 2): "matrix"}
    # measured 29.3 degrees (h = 0.08: 34.5); the pinned periodic faces limit it
    assert jtet.stats(written).min_dihedral > max(25.0, jtet.stats(mesh).min_dihedral + 10)


@pytest.mark.parametrize("seed", range(4))
def test_boundary_edges_between_match_the_topology(seed):
    """The periodic run's pinned edges, found among the tets with two or more corners in
    the vertex set, are the whole-mesh topology's boundary edges with both ends in it;
    the seam's boundary faces with a vertex in the set are the topology's too (rows in
    lexicographic order, as np.unique over rows gives them)."""
    from helpers import delaunay_mesh

    from jtet._driver import _boundary_edges_between, _boundary_faces_at

    mesh = delaunay_mesh(300, seed=seed, surface_points=150)
    rng = np.random.default_rng(seed)
    T = mesh.topology
    boundary_verts = np.unique(T.faces[T.boundary_face])
    # most boundary vertices and some interior ones (interior pairs must not count)
    verts = np.union1d(
        rng.choice(boundary_verts, len(boundary_verts) * 3 // 4, replace=False),
        rng.choice(mesh.n_points, 40, replace=False),
    )
    on = np.zeros(mesh.n_points, bool)
    on[verts] = True
    expected = T.edges[T.edge_boundary & on[T.edges].all(axis=1)]
    expected = np.unique(np.sort(expected, axis=1), axis=0)
    got = _boundary_edges_between(mesh.tets, verts, mesh.n_points)
    assert len(expected) > 20
    np.testing.assert_array_equal(got, expected)
    faces = np.sort(T.faces[T.boundary_face], axis=1)
    for k in (1, 2, 3):
        expected = np.unique(faces[on[faces].sum(axis=1) >= k], axis=0)
        got = _boundary_faces_at(mesh.tets, on, k)
        assert len(expected) > 10
        np.testing.assert_array_equal(got, expected)
