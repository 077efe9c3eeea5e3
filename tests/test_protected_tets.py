"""TetMesh.protected_tets: tets improve leaves exactly as they are (MMG's
RequiredTetrahedra), read and written by the Medit and VTK savers."""

import numpy as np
import pytest

import jtet
from jtet._invariants import InvariantChecker
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
    path = tmp_path / "m.mesh"
    jtet.save(mesh.replace(protected_tets=None), path)
    text = path.read_text().replace(
        "\nEnd\n",
        "\nRequiredTriangles\n1\n1\n\nRequiredEdges\n1\n1\nRequiredTetrahedra\n2\n3 5\n\nEnd\n",
    )
    path.write_text(text)
    got = jtet.load(path)
    assert _rows(got.protected_tets) == _rows(mesh.tets[[2, 4]])
    path.write_text(text.replace("RequiredTetrahedra\n2\n3 5", "RequiredTetrahedra\n2\n3 99999"))
    with pytest.raises(jtet.MeshInputError, match="RequiredTetrahedra lists tet 99999"):
        jtet.load(path)
    path.write_text(text.replace("RequiredTetrahedra\n2\n3 5", "RequiredTetrahedra\n3\n3 5"))
    with pytest.raises(jtet.MeshInputError, match="unreadable RequiredTetrahedra"):
        jtet.load(path)


@pytest.mark.parametrize("name", ["m.msh", "m.meshb", "m.node"])
def test_formats_without_protected_tets_warn(tmp_path, mesh, name):
    with pytest.warns(UserWarning, match="protected tet"):
        jtet.save(mesh, tmp_path / name)
