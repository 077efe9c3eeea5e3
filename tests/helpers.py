"""Tiny canonical meshes and seeded random meshes shared by the tests."""

import contextlib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import Delaunay

import jtet

# A regular tet; as listed it is negatively oriented (VTK sign), swap rows 0 and 1 for +.
REGULAR_TET = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]])


def orient_positive(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swap two vertices of every negatively oriented tet (VTK convention)."""
    p = points[tets]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets = tets.copy()
    neg = vol < 0
    tets[neg] = tets[neg][:, [1, 0, 2, 3]]
    return tets


def delaunay_mesh(
    n_points: int = 200, seed: int = 0, clustered: bool = False, surface_points: int = 0
) -> "jtet.TetMesh":
    """Delaunay tetrahedralization of seeded random points in the unit cube (scipy).

    Cube corners are included so the boundary is the cube; ``surface_points`` more lie
    exactly on its faces. Zero-volume tets qhull leaves on the flat faces are dropped.
    """
    rng = np.random.default_rng(seed)
    pts = rng.random((n_points, 3))
    if clustered:
        pts = 0.5 + 0.15 * rng.standard_normal((n_points, 3))
        pts = np.clip(pts, 0.01, 0.99)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    # points exactly on the cube's faces: flat boundary facets with removable edges
    surf = rng.random((surface_points, 3))
    axis = rng.integers(0, 3, surface_points)
    surf[np.arange(surface_points), axis] = rng.integers(0, 2, surface_points)
    pts = np.vstack([corners, surf, pts])
    tri = Delaunay(pts)
    tets = orient_positive(pts, tri.simplices.astype(np.int64))
    p = pts[tets]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets = tets[vol > 1e-14]
    return jtet.TetMesh(pts, tets)


def grid_mesh(
    n: int = 3, perturb: float = 0.0, seed: int = 0, two_regions: bool = False
) -> "jtet.TetMesh":
    """Structured n^3 cube grid, each cube cut into 6 tets (Kuhn/Freudenthal), perturbed.

    ``two_regions`` (n even): tets with centroid x > 0.5 get region 1, the rest 0; points on
    the interface plane x = 0.5 move only within it, so the interface stays flat.
    """
    ax = np.linspace(0.0, 1.0, n + 1)
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    c = [
        idx[i : i + n, j : j + n, k : k + n].ravel() for i in (0, 1) for j in (0, 1) for k in (0, 1)
    ]
    # corners: c[0]=000 c[1]=001 c[2]=010 c[3]=011 c[4]=100 c[5]=101 c[6]=110 c[7]=111
    paths = [(4, 6), (4, 5), (2, 6), (2, 3), (1, 5), (1, 3)]
    tets = np.concatenate([np.stack([c[0], c[a], c[b], c[7]], axis=1) for a, b in paths])
    tets = orient_positive(pts, tets)
    if perturb:
        # interior points move by up to perturb * h; halve the move until no tet inverts,
        # so the mesh stays a valid (conforming, positively oriented) tetrahedralization
        rng = np.random.default_rng(seed)
        interior = ((pts > 0) & (pts < 1)).all(axis=1)
        step = rng.uniform(-1, 1, (interior.sum(), 3)) * perturb / n
        if two_regions:
            step[np.isclose(pts[interior, 0], 0.5), 0] = 0.0
        for _ in range(30):
            moved = pts.copy()
            moved[interior] += step
            p = moved[tets]
            vol = np.einsum(
                "ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])
            )
            if (vol > 0).all():
                pts = moved
                break
            step = step / 2
    region = None
    if two_regions:
        region = (pts[tets].mean(axis=1)[:, 0] > 0.5).astype(np.int64)
    return jtet.TetMesh(pts, tets, region)


def shifted(mesh: "jtet.TetMesh", offset: int = 70_000) -> "jtet.TetMesh":
    """``mesh`` with ``offset`` unreferenced points listed before its own, so every vertex
    id grows by ``offset``. Above 2**16 a product of two vertex ids (a key a * n + b)
    no longer fits in int32: a key computed in the topology's int32 ids would wrap."""
    far = mesh.points.max(axis=0) + 1.0 + np.arange(offset)[:, None] * np.array([1.0, 0, 0])
    return jtet.TetMesh(
        np.concatenate([far, mesh.points]),
        mesh.tets + offset,
        mesh.region,
        protected_faces=mesh.protected_faces + offset,
        protected_edges=mesh.protected_edges + offset,
    )


def unit_tet10() -> tuple[np.ndarray, np.ndarray]:
    """(corners (4, 3), nodes (10, 3)) of the unit corner tet as a 10-node tet: its
    corners first, then the midpoints of edges 01, 12, 02, 03, 13, 23 (VTK's, Abaqus'
    and Exodus' order of a quadratic tet's mid-edge nodes)."""
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    edges = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]
    return corners, np.vstack([corners, [(corners[a] + corners[b]) / 2 for a, b in edges]])


def read_as_unit_tet(path) -> "jtet.TetMesh":
    """Load the file of ``unit_tet10``'s 10-node tet ``path``: refused with the --linear
    hint, then read with ``linear=True`` as the unit corner tet (its 6 mid-edge nodes
    left out, with a warning); that mesh."""
    from jtet._errors import MeshInputError

    with pytest.raises(MeshInputError, match="--linear"):
        jtet.load(path)
    with pytest.warns(UserWarning, match="6 mid-edge node"):
        mesh = jtet.load(path, linear=True)
    np.testing.assert_array_equal(mesh.points, unit_tet10()[0])
    np.testing.assert_array_equal(mesh.tets, [[0, 1, 2, 3]])
    return mesh


def named_ball_in_box(*paths, save_all_entities=False, names=True, second_order=()):
    """A ball (physical volume 1 "ball") in a box (2 "box"), the box's walls as physical
    surface 10 "walls", meshed once and written to each of ``paths`` (.msh 2.2 / 4.1,
    .inp, ...; the format from the extension); then made quadratic (Gmsh's order 2) and
    written to each of ``second_order`` (a path, or (path, MSH version))."""
    with gmsh_model() as gmsh:
        box = gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        ball = gmsh.model.occ.addSphere(0.5, 0.5, 0.5, 0.25)
        gmsh.model.occ.fragment([(3, box)], [(3, ball)])
        gmsh.model.occ.synchronize()
        vols = sorted(t for _, t in gmsh.model.getEntities(3))
        inner = min(vols, key=lambda v: gmsh.model.occ.getMass(3, v))
        outer = max(vols, key=lambda v: gmsh.model.occ.getMass(3, v))
        if not save_all_entities:
            gmsh.model.addPhysicalGroup(3, [inner], 1, "ball" if names else "")
            gmsh.model.addPhysicalGroup(3, [outer], 2, "box" if names else "")
        walls = [t for _, t in gmsh.model.getBoundary([(3, outer)], oriented=False)]
        walls = [t for t in walls if gmsh.model.occ.getMass(2, t) > 0.9]  # the six squares
        gmsh.model.addPhysicalGroup(2, walls, 10, "walls" if names else "")
        if save_all_entities:
            gmsh.option.setNumber("Mesh.SaveAll", 1)
        gmsh_mesh_and_write(gmsh, paths[0], 0.2)
        for path in paths[1:]:
            gmsh.write(str(path))
        if second_order:
            gmsh.model.mesh.setOrder(2)
        for item in second_order:
            path, version = item if isinstance(item, tuple) else (item, None)
            if version is not None:
                gmsh.option.setNumber("Mesh.MshFileVersion", version)
            gmsh.write(str(path))


def run_mmg3d(mesh: "jtet.TetMesh", src: Path, out: Path, *args: str) -> "jtet.TetMesh":
    """Save ``mesh`` to ``src``, run mmg3d (the binary of the pymmg package, experiments
    extra; the calling test is skipped without it) from ``src`` to ``out`` with
    ``args``, and load ``out``."""
    import importlib.util
    import subprocess

    spec = importlib.util.find_spec("mmg3d")
    exe = None if spec is None else Path(spec.origin).parent / "mmg3d_O3"
    if exe is None or not exe.exists():
        pytest.skip("mmg3d (pymmg) is not installed")
    jtet.save(mesh, src)
    run = subprocess.run(
        [str(exe), "-in", str(src), "-out", str(out), *args, "-v", "-1"],
        capture_output=True,
        timeout=120,
    )
    assert run.returncode == 0, (run.stdout[-500:], run.stderr[-500:])
    return jtet.load(out)


def shared_mesh_path(name: str) -> Path:
    """Path of the reference mesh ``name`` in ``shared/meshes`` next to the checkout; the
    calling test is skipped when that directory is not there."""
    path = Path(__file__).resolve().parents[2] / "shared" / "meshes" / name
    if not path.exists():
        pytest.skip("shared/meshes not next to the checkout")
    return path


@contextlib.contextmanager
def gmsh_model():
    """A quiet Gmsh session (skips the test without the gmsh module), finalized after."""
    gmsh = pytest.importorskip("gmsh")
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        yield gmsh
    finally:
        gmsh.finalize()


def gmsh_mesh_and_write(gmsh, path, h: float, version: float | None = None) -> None:
    """Mesh the current Gmsh model in 3-D with sizes up to ``h`` and write it to ``path``
    (MSH ``version``, or Gmsh's default)."""
    gmsh.option.setNumber("Mesh.MeshSizeMax", h)
    if version is not None:
        gmsh.option.setNumber("Mesh.MshFileVersion", version)
    gmsh.model.mesh.generate(3)
    gmsh.write(str(path))


def barycentric_in_every_tet(mesh, where):
    """(q, m, 4): the barycentric weights of each point of ``where`` (q, 3) in every tet
    of ``mesh`` (brute force, a dense linear solve per pair)."""
    p = mesh.points[mesh.tets]  # (m, 4, 3)
    edges = np.transpose(p[:, 1:] - p[:, :1], (0, 2, 1))  # (m, 3, 3) columns p_i - p_0
    rel = where[:, None, :] - p[None, :, 0]  # (q, m, 3)
    lam = np.linalg.solve(edges[None], rel[..., None])[..., 0]  # (q, m, 3)
    return np.concatenate([1 - lam.sum(axis=2, keepdims=True), lam], axis=2)


def brute_force_interpolation(mesh, f, where):
    """f (n,) interpolated linearly at each point of ``where`` (q, 3) in the tet of
    ``mesh`` holding it best (largest smallest barycentric weight); and that smallest
    weight (q,)."""
    weights = barycentric_in_every_tet(mesh, where)
    best = np.argmax(weights.min(axis=2), axis=1)
    w = weights[np.arange(len(where)), best]
    return (w * f[mesh.tets[best]]).sum(axis=1), w.min(axis=1)


# TetGen's order of a 10-node tet's edge nodes, read off its edge tables by hand
# (``edge2ver`` through ``orgpivot`` / ``destpivot``); tests/test_tetgen_o2.py checks
# it on TetGen's own file
TETGEN_EDGES = [(2, 3), (0, 3), (0, 1), (1, 2), (1, 3), (0, 2)]
# and of a 6-node face's (TetGen's ``outfaces`` / ``outsubfaces`` walk the face's edges
# from its origin with ``enext``): ab, bc, ca of the face's corners a, b, c
TETGEN_FACE_EDGES = [(0, 1), (1, 2), (2, 0)]


def _tetgen_rows(path: Path) -> list[list[float]]:
    """The data lines of a TetGen file as numbers (comments dropped), header first."""
    out = []
    for line in path.read_text().splitlines():
        data = line.split("#")[0].split()
        if data:
            out.append([float(v) for v in data])
    return out


def tetgen_file(path: Path):
    """(points (n, 3), 10-node tets (m, 10) 0-based, attributes (m, k)) of a TetGen -o2
    ``.node`` / ``.ele`` pair, parsed line by line (independently of jtet's reader)."""
    nodes = np.array(_tetgen_rows(path.with_suffix(".node"))[1:])
    base = int(nodes[0, 0])
    ele = np.array(_tetgen_rows(path.with_suffix(".ele"))[1:])
    return nodes[:, 1:4], ele[:, 1:11].astype(np.int64) - base, ele[:, 11:]


def tetgen_face_file(path: Path):
    """(6-node faces (k, 6) 0-based, markers (k,)) of the TetGen -o2 ``.face`` file
    beside ``path``, parsed line by line (numbered from the ``.node`` file's first id)."""
    base = int(_tetgen_rows(path.with_suffix(".node"))[1][0])
    rows = np.array(_tetgen_rows(path.with_suffix(".face"))[1:], np.int64)
    return rows[:, 1:7] - base, rows[:, 7]


def gmsh_region_volumes(path) -> tuple[dict, set]:
    """{physical volume name: volume} of a mesh file, by Gmsh: the sum over its elements
    of Gmsh's Jacobian determinants times its Gauss weights (exact for a 10-node tet's
    cubic determinant with the 4th-order rule), and the element types."""
    gmsh = pytest.importorskip("gmsh")
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Verbosity", 1)
        gmsh.open(str(path))
        volumes, types = {}, set()
        for _, tag in gmsh.model.getPhysicalGroups(3):
            name = gmsh.model.getPhysicalName(3, tag)
            total = 0.0
            for entity in gmsh.model.getEntitiesForPhysicalGroup(3, tag):
                kinds, elements, _ = gmsh.model.mesh.getElements(3, entity)
                for kind, ids in zip(kinds, elements, strict=True):
                    types.add(int(kind))
                    uvw, weights = gmsh.model.mesh.getIntegrationPoints(int(kind), "Gauss4")
                    _, det, _ = gmsh.model.mesh.getJacobians(int(kind), uvw, entity)
                    total += (det.reshape(len(ids), -1) * weights).sum()
            volumes[name] = total
        return volumes, types
    finally:
        gmsh.finalize()
