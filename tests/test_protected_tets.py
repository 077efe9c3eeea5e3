"""TetMesh.protected_tets: tets improve leaves exactly as they are (MMG's
RequiredTetrahedra), read and written by the Medit and VTK savers."""

import numpy as np
import pytest

import jtet
from jtet._invariants import InvariantChecker
from jtet._medit import _medit_required
from jtet.cli import main


@pytest.fixture(scope="module")
def mesh():
    # the demo's two regions with its 12 worst tets protected (the run may not fix them)
    m = jtet.demo_mesh("two_regions")
    worst = np.argsort(m.quality("biased_min_sine"))[:12]
    return m.replace(protected_tets=m.tets[worst])


def _rows(tets) -> set:
    return {tuple(t) for t in np.sort(tets, axis=1).tolist()}


def _assert_kept(before, after):
    protected = before.protected_tet_mask()
    assert _rows(before.tets[protected]) <= _rows(after.tets)
    verts = np.unique(before.tets[protected])
    assert np.array_equal(after.points[verts], before.points[verts])
    assert np.array_equal(after.protected_tets, before.protected_tets)


@pytest.mark.parametrize("boundary", ["fixed", "slide"])
def test_protected_tets_stay(mesh, boundary):
    r = jtet.improve(mesh, boundary=boundary, check=True)
    assert r.status == "converged"
    _assert_kept(mesh, r.mesh)
    InvariantChecker(mesh).check(r.mesh, 0, "protected tets")
    # the others improved; the worst tet is a protected one, and a note says so
    before, after = r.selected_stats
    assert after.min_dihedral > 30 > before.min_dihedral
    assert r.stats_after.min_dihedral == pytest.approx(r.stats_before.min_dihedral)
    assert any("a protected tet" in n for n in r.notes)
    assert "after (unprotected)" in r.summary().splitlines()[0]


def test_protected_tets_with_regions(mesh):
    r = jtet.improve(mesh, regions=[2], ops=("edge", "face"), check=True)
    _assert_kept(mesh, r.mesh)
    frozen = mesh.region == 1
    assert _rows(mesh.tets[frozen]) <= _rows(r.mesh.tets)
    assert "after (regions 2, unprotected)" in r.summary().splitlines()[0]


def test_bad_protected_tets(mesh):
    with pytest.raises(jtet.MeshInputError, match="no tets of the mesh"):
        jtet.improve(mesh.replace(protected_tets=[[0, 1, 2, 3]]))
    with pytest.raises(jtet.MeshInputError, match="every tet"):
        jtet.improve(mesh.replace(protected_tets=mesh.tets))
    with pytest.raises(jtet.MeshInputError, match="nothing to improve"):
        jtet.improve(mesh.replace(protected_tets=mesh.tets[mesh.region == 1]), regions=[1])
    with pytest.raises(jtet.MeshInputError, match="repeats a vertex"):
        mesh.replace(protected_tets=[[0, 0, 1, 2]])


@pytest.mark.parametrize("ext", [".vtu", ".vtk", ".mesh"])
def test_protected_tets_round_trip(tmp_path, mesh, ext):
    path = tmp_path / f"m{ext}"
    jtet.save(mesh, path)
    back = jtet.load(path)
    assert np.array_equal(back.protected_tets, mesh.protected_tets)
    out = tmp_path / f"out{ext}"
    assert main(["improve", str(path), str(out), "--ops", "edge,face", "-q"]) == 0
    _assert_kept(back, jtet.load(out))


def test_mmg_required_sections_are_read(tmp_path, mesh):
    # meshio 5.3 refuses RequiredTetrahedra, RequiredTriangles and RequiredEdges
    # ("Unknown keyword"): MMG files holding them were unreadable
    T = mesh.topology
    faces = np.sort(T.faces[T.boundary_face][:3], axis=1)
    edges = T.edges[~T.edge_boundary][:2]
    path = tmp_path / "m.mesh"
    jtet.save(mesh.replace(protected_tets=None, protected_faces=faces, protected_edges=edges), path)
    text = path.read_text().replace(
        "\nEnd\n",
        "\nRequiredTriangles\n1\n2\n\nRequiredEdges\n1\n1\nRequiredTetrahedra\n2\n3 5\n\nEnd\n",
    )
    path.write_text(text)
    got = jtet.load(path)
    assert _rows(got.protected_tets) == _rows(mesh.tets[[2, 4]])
    # a required triangle keeps its edges and vertices too (a protected face alone may be
    # flipped within a flat patch), a required edge its vertices
    tri = np.sort(got.protected_faces, axis=1)
    second = tri[np.flatnonzero((tri == np.sort(faces[1])).all(axis=1))[0]]
    sides = {tuple(sorted(e)) for e in second[[[0, 1], [1, 2], [0, 2]]].tolist()}
    assert sides <= {tuple(e) for e in np.sort(got.protected_edges, axis=1).tolist()}
    assert set(second.tolist()) | set(edges[0].tolist()) == set(got.protected_vertices.tolist())
    for bad, match in (
        ("RequiredTetrahedra\n2\n3 99999", "RequiredTetrahedra lists tet 99999"),
        ("RequiredTetrahedra\n3\n3 5", "unreadable RequiredTetrahedra"),
    ):
        path.write_text(text.replace("RequiredTetrahedra\n2\n3 5", bad))
        with pytest.raises(jtet.MeshInputError, match=match):
            jtet.load(path)
    path.write_text(text.replace("RequiredTriangles\n1\n2", "RequiredTriangles\n1\n4"))
    with pytest.raises(jtet.MeshInputError, match="RequiredTriangles lists triangle 4 of 3"):
        jtet.load(path)


def test_mmg_required_triangles_stay_exactly(tmp_path):
    """A flat-faced cube whose boundary triangles are all protected faces: improve
    flips some of them within their facets (coplanar 2-2 flips), unless the file says
    they are required (MMG's RequiredTriangles), when each stays a face, unmoved."""
    from helpers import delaunay_mesh

    mesh = delaunay_mesh(150, seed=4, surface_points=120)
    T = mesh.topology
    faces = np.sort(T.faces[T.boundary_face], axis=1)
    path = tmp_path / "cube.mesh"
    jtet.save(mesh.replace(protected_faces=faces), path)
    text = path.read_text()
    ids = "\n".join(str(i + 1) for i in range(len(faces)))
    required = f"RequiredTriangles\n{len(faces)}\n{ids}\n\nEnd\n"
    kept = {}
    for name, body in (("plain", text), ("required", text.replace("\nEnd\n", "\n" + required))):
        path.write_text(body)
        before = jtet.load(path)
        after = jtet.improve(before, ops=("edge", "face"), check=True).mesh
        Ta = after.topology
        now = {tuple(f) for f in np.sort(Ta.faces[Ta.boundary_face], axis=1).tolist()}
        kept[name] = sum(tuple(f) in now for f in faces.tolist())
    assert kept["required"] == len(faces)
    assert kept["plain"] < len(faces)  # the reference: without the section they flip
    # jtet's own .mesh output says they are required again (and their edges), so MMG
    # run on it keeps them as well; without the section it lists none
    out = tmp_path / "out.mesh"
    jtet.save(after, out)
    ids = _medit_required(out, ("RequiredTriangles", "RequiredEdges"))
    written = np.sort(jtet.load(out).protected_faces, axis=1)[ids["RequiredTriangles"]]
    assert {tuple(f) for f in written.tolist()} == {tuple(f) for f in faces.tolist()}
    assert len(ids["RequiredEdges"]) == len(after.protected_edges) > 0
    plain = jtet.load(path).replace(protected_edges=None, protected_vertices=None)
    jtet.save(plain, out)
    assert _medit_required(out, ("RequiredTriangles", "RequiredEdges")) == {
        "RequiredTriangles": None,
        "RequiredEdges": None,
    }


@pytest.mark.parametrize("name", ["m.msh", "m.node", "m.inp"])
def test_formats_without_protected_tets_warn(tmp_path, mesh, name):
    with pytest.warns(UserWarning, match="protected tet"):
        jtet.save(mesh, tmp_path / name)


def test_mmg3d_keeps_the_required_triangles_jtet_writes(tmp_path):
    """MMG itself is the reference for what RequiredTriangles means: mmg3d remeshing
    jtet's .mesh output (refined to twice as many tets and more) keeps every triangle
    jtet wrote as required, while it splits most of the other boundary triangles (the
    sign that it would have changed them). mmg3d is the binary of the pymmg package
    (experiments extra; the test is skipped without it)."""
    from helpers import delaunay_mesh, run_mmg3d

    mesh = delaunay_mesh(150, seed=4, surface_points=120)
    T = mesh.topology
    faces = np.sort(T.faces[T.boundary_face], axis=1)
    required = faces[::2]
    sides = np.sort(required[:, [[0, 1], [1, 2], [0, 2]]].reshape(-1, 2), axis=1)
    mesh = mesh.replace(
        protected_faces=faces,
        protected_edges=np.unique(sides, axis=0),
        protected_vertices=np.unique(required),
    )
    remeshed = run_mmg3d(mesh, tmp_path / "in.mesh", tmp_path / "out.mesh", "-hmax", "0.08")
    assert remeshed.n_tets > 2 * mesh.n_tets

    def corners(points, tris):
        # a triangle by its corner coordinates, rounded: mmg3d prints them in ASCII with
        # fewer digits than float64 holds (the mesh spans 1; its vertices are >= 0.014 apart)
        return {tuple(sorted(map(tuple, points[t].round(9).tolist()))) for t in tris}

    To = remeshed.topology
    now = corners(remeshed.points, To.faces[To.boundary_face])
    assert corners(mesh.points, required) <= now
    others = corners(mesh.points, faces[1::2])
    assert len(others & now) < len(others) / 2
