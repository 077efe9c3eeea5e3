"""Reproducible generators of input meshes for the experiments (not part of the jtet package).

Every generator is a plain function returning a ``jtet.TetMesh``; ``GENERATORS`` maps the
name used in ``configs/mesh/*.yaml`` (key ``generator``) to the function, and the config's
``params`` are its keyword arguments (``check(generator, params)`` rejects unknown or
missing ones before anything is generated).

- ``gmsh_shape``: Gmsh Delaunay (``Mesh.Algorithm3D = 1``) of an analytic / CSG shape with
  uniform size ``h``, one thread, ``Mesh.Optimize = 0`` and ``Mesh.OptimizeNetgen = 0``:
  exactly how the reference meshes of ``shared/meshes`` were made (with the default seed
  the cube, sphere, torus and holeplate are identical to them, tet for tet).
- ``gmsh_two_regions``: a unit cube with a spherical inclusion meshed conformingly: regions
  1 (outside) and 2 (inside) share a curved interface.
- ``tetwild``: fTetWild (``pytetwild``) on the Gmsh surface mesh of a shape, with or
  without fTetWild's own optimization.
- ``perturbed``: a good mesh (Gmsh with its optimizers on) whose interior vertices are
  moved randomly (seeded) by a fraction of the local edge length, never inverting a tet.
- ``file``: a user's mesh file (any format ``jtet.load`` reads).

``gmsh`` and ``pytetwild`` are only imported by the generators that need them.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from pathlib import Path

import numpy as np

import jtet

SHAPES = ("cube", "sphere", "torus", "holeplate", "box_with_hole", "bracket")


# ---------------------------------------------------------------------------------------
# Gmsh helpers


def _gmsh_options(h: float, seed: int, optimize: bool) -> None:
    import gmsh

    gmsh.option.setNumber("General.Terminal", 0)
    # one thread everywhere: Gmsh's parallel meshers are not deterministic
    gmsh.option.setNumber("General.NumThreads", 1)
    for dim in (1, 2, 3):
        gmsh.option.setNumber(f"Mesh.MaxNumThreads{dim}D", 1)
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay
    gmsh.option.setNumber("Mesh.Optimize", int(optimize))
    gmsh.option.setNumber("Mesh.OptimizeNetgen", int(optimize))
    gmsh.option.setNumber("Mesh.MeshSizeMax", float(h))
    gmsh.option.setNumber("Mesh.MeshSizeMin", 0.0)
    # Gmsh seeds its generator with srand(seed); 0 and 1 (the default) give the same mesh
    gmsh.option.setNumber("Mesh.RandomSeed", int(seed))


def _gmsh_add_shape(shape: str) -> list[tuple[int, int]]:
    """Add the OCC solid ``shape`` to the current Gmsh model; returns its volume dimtags."""
    import gmsh

    occ = gmsh.model.occ
    if shape == "cube":  # unit cube
        out = [(3, occ.addBox(0, 0, 0, 1, 1, 1))]
    elif shape == "sphere":  # radius 1 at the origin
        out = [(3, occ.addSphere(0, 0, 0, 1))]
    elif shape == "torus":  # R = 1, r = 0.35, axis z
        out = [(3, occ.addTorus(0, 0, 0, 1, 0.35))]
    elif shape == "holeplate":  # 2 x 1 x 0.5 plate minus two through-cylinders along z
        box = occ.addBox(0, 0, 0, 2, 1, 0.5)
        c1 = occ.addCylinder(0.4, 0.5, -0.1, 0, 0, 0.7, 0.1)
        c2 = occ.addCylinder(1.0, 0.5, -0.1, 0, 0, 0.7, 0.3)
        out, _ = occ.cut([(3, box)], [(3, c1), (3, c2)])
    elif shape == "box_with_hole":  # jtet's demo geometry: 2 x 1 x 1 box minus a ball
        box = occ.addBox(0, 0, 0, 2, 1, 1)
        ball = occ.addSphere(0.7, 0.5, 0.5, 0.3)
        out, _ = occ.cut([(3, box)], [(3, ball)])
    elif shape == "bracket":  # a CAD-like part: _bracket
        out = _bracket()
    else:
        raise ValueError(f"unknown shape {shape!r}; choose from {list(SHAPES)}")
    occ.synchronize()
    return out


def _bracket() -> list[tuple[int, int]]:
    """An L-bracket, the kind of part a CAD export gives: a 2 x 1 x 0.2 base and a
    0.25 x 1 x 1 wall, their inner corner filleted (radius 0.15: curved faces meeting
    flat ones tangentially), two holes through the base (radii 0.15, 0.1) and one
    through the wall (radius 0.2)."""
    import gmsh

    occ = gmsh.model.occ
    fused, _ = occ.fuse(
        [(3, occ.addBox(0, 0, 0, 2, 1, 0.2))], [(3, occ.addBox(0, 0, 0.2, 0.25, 1, 1))]
    )
    occ.synchronize()

    def inner_corner(tag: int) -> bool:  # the edge along y at x = 0.25, z = 0.2
        x0, _, z0, x1, _, z1 = gmsh.model.getBoundingBox(1, tag)
        off = max(abs(x0 - 0.25), abs(x1 - 0.25), abs(z0 - 0.2), abs(z1 - 0.2))
        return off < 1e-6  # OCC pads bounding boxes by ~1e-7

    corner = [t for _, t in gmsh.model.getEntities(1) if inner_corner(t)]
    filleted = occ.fillet([fused[0][1]], corner, [0.15])
    holes = [
        (3, occ.addCylinder(1.0, 0.5, -0.1, 0, 0, 0.5, 0.15)),
        (3, occ.addCylinder(1.6, 0.5, -0.1, 0, 0, 0.5, 0.1)),
        (3, occ.addCylinder(-0.1, 0.5, 0.8, 0.5, 0, 0, 0.2)),
    ]
    out, _ = occ.cut(filleted, holes)
    return out


def _orient(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swap two vertices of the negatively oriented tets (jtet's VTK convention)."""
    p = points[tets]
    vol6 = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets = tets.copy()
    tets[vol6 < 0] = tets[vol6 < 0][:, [1, 0, 2, 3]]
    return tets


def _gmsh_extract(labels: dict[int, int] | None = None) -> jtet.TetMesh:
    """The current Gmsh model's linear tets; ``labels`` maps a volume tag to a region."""
    import gmsh

    tags, coords, _ = gmsh.model.mesh.getNodes()
    coords = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    blocks, region = [], []
    for _, vol in gmsh.model.getEntities(3):
        types, _, nodes = gmsh.model.mesh.getElements(3, vol)
        for t, n in zip(types, nodes, strict=True):
            if t != 4:
                raise RuntimeError(f"unexpected Gmsh element type {t} (want 4-node tets)")
            blocks.append(index[np.asarray(n, np.int64).reshape(-1, 4)])
            region.append(np.full(len(blocks[-1]), (labels or {}).get(vol, 0), np.int64))
    used, tets = np.unique(np.concatenate(blocks), return_inverse=True)
    points = coords[used]
    tets = _orient(points, tets.reshape(-1, 4))
    return jtet.TetMesh(points, tets, np.concatenate(region))


def _gmsh_surface(shape: str, h: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3), triangles (k, 3) int32) of Gmsh's surface mesh of ``shape``."""
    import gmsh

    gmsh.initialize()
    try:
        _gmsh_options(h, seed, optimize=False)
        _gmsh_add_shape(shape)
        gmsh.model.mesh.generate(2)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        coords = np.asarray(coords, np.float64).reshape(-1, 3)
        index = np.full(int(tags.max()) + 1, -1, np.int64)
        index[tags.astype(np.int64)] = np.arange(len(tags))
        _, _, nodes = gmsh.model.mesh.getElements(2)
        tris = index[np.concatenate([np.asarray(n, np.int64) for n in nodes]).reshape(-1, 3)]
    finally:
        gmsh.finalize()
    used, tris = np.unique(tris, return_inverse=True)
    return coords[used], tris.reshape(-1, 3).astype(np.int32)


# ---------------------------------------------------------------------------------------
# generators


def gmsh_shape(shape: str, h: float, seed: int = 0, optimize: bool = False) -> jtet.TetMesh:
    """Gmsh Delaunay mesh of ``shape`` (see ``SHAPES``) with uniform size ``h``.

    ``optimize=False`` (the default) leaves Gmsh's and Netgen's optimizers off, so the
    mesh keeps the slivers Delaunay produces. Reference sizes: cube 0.08 (10,634 tets),
    sphere 0.12 (12,423), torus 0.08 (23,201), holeplate 0.05 (33,271).
    """
    import gmsh

    gmsh.initialize()
    try:
        _gmsh_options(h, seed, optimize)
        gmsh.model.add(shape)
        _gmsh_add_shape(shape)
        gmsh.model.mesh.generate(3)
        return _gmsh_extract()
    finally:
        gmsh.finalize()


def gmsh_ball_in_box(radius: float) -> tuple[int, int]:
    """(ball, box): the volume tags of a unit cube and a ball of ``radius`` at its centre,
    added to Gmsh's current model and fragmented, so the spherical interface is conforming
    (shared triangles)."""
    import gmsh

    occ = gmsh.model.occ
    box = occ.addBox(0, 0, 0, 1, 1, 1)
    ball = occ.addSphere(0.5, 0.5, 0.5, radius)
    occ.fragment([(3, box)], [(3, ball)])
    occ.synchronize()
    vols = sorted(t for _, t in gmsh.model.getEntities(3))
    ball = min(vols, key=lambda v: occ.getMass(3, v))  # the smaller of the two volumes
    return ball, max(vols, key=lambda v: occ.getMass(3, v))


def gmsh_two_regions(h: float, seed: int = 0, radius: float = 0.3) -> jtet.TetMesh:
    """A unit cube with a ball of ``radius`` at its centre; regions 1 (outside), 2 (ball).

    The two volumes are fragmented so the spherical interface is conforming (shared
    triangles), then meshed by Gmsh Delaunay without optimization, like ``gmsh_shape``.
    """
    import gmsh

    gmsh.initialize()
    try:
        _gmsh_options(h, seed, optimize=False)
        ball, box = gmsh_ball_in_box(radius)
        gmsh.model.mesh.generate(3)
        labels = {box: 1, ball: 2}
        return _gmsh_extract(labels)
    finally:
        gmsh.finalize()


def tetwild(shape: str, h: float, optimize: bool = False, seed: int = 0) -> jtet.TetMesh:
    """fTetWild (``jtet.tetrahedralize``: ``pytetwild`` in a child process, one thread)
    on the Gmsh surface mesh of ``shape``.

    ``h`` is both the size of the input surface mesh and fTetWild's absolute target edge
    length. ``optimize=False`` skips fTetWild's AMIPS optimization (very poor tets);
    ``optimize=True`` is fTetWild's normal output. ``seed`` seeds the surface mesh.
    """
    surface = _gmsh_surface(shape, h, seed)
    return jtet.tetrahedralize(surface, edge_length=float(h), optimize=bool(optimize), threads=1)


def perturbed(
    shape: str, h: float, amplitude: float = 0.3, seed: int = 0, optimize: bool = True
) -> jtet.TetMesh:
    """A good Gmsh mesh of ``shape`` (optimizers on) with randomly moved interior vertices.

    Every interior vertex moves in a random direction by ``amplitude`` times the length of
    its shortest incident edge; the moves of vertices of tets that would invert are halved
    (up to 30 times, then cancelled), so the result is valid and the boundary unchanged.
    """
    mesh = gmsh_shape(shape, h, seed=seed, optimize=optimize)
    points, tets = mesh.points, mesh.tets
    rng = np.random.default_rng(seed)
    edges = tets[:, [0, 0, 0, 1, 1, 2, 1, 2, 3, 2, 3, 3]].reshape(-1, 2, order="F")
    length = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
    shortest = np.full(len(points), np.inf)
    np.minimum.at(shortest, edges[:, 0], length)
    np.minimum.at(shortest, edges[:, 1], length)
    faces = np.sort(tets[:, [1, 2, 3, 0, 3, 2, 0, 1, 3, 0, 2, 1]].reshape(-1, 3), axis=1)
    uniq, count = np.unique(faces, axis=0, return_counts=True)
    interior = np.ones(len(points), bool)
    interior[uniq[count == 1].reshape(-1)] = False
    direction = rng.standard_normal((len(points), 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    move = direction * (amplitude * np.where(np.isfinite(shortest), shortest, 0.0))[:, None]
    move[~interior] = 0.0
    for _ in range(31):
        moved = points + move
        p = moved[tets]
        vol6 = np.einsum(
            "ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])
        )
        bad = np.unique(tets[vol6 <= 0].reshape(-1))
        if len(bad) == 0:
            break
        move[bad] *= 0.5
    else:
        move[bad] = 0.0
        moved = points + move
    return jtet.TetMesh(moved, tets, mesh.region)


def file(path: str) -> jtet.TetMesh:
    """A mesh read from ``path`` with ``jtet.load`` (relative paths: to the caller's cwd)."""
    return jtet.load(Path(path))


def surface(
    path: str,
    edge_length: float | None = None,
    edge_length_fac: float = 0.05,
    epsilon: float = 1e-3,
    optimize: bool = True,
    threads: int = 1,
) -> jtet.TetMesh:
    """fTetWild's mesh of the volume the surface file ``path`` bounds
    (``jtet.tetrahedralize``; relative paths: to the caller's cwd). fTetWild's output
    varies from run to run: a run's ``save_input=true`` keeps the mesh it improved."""
    return jtet.tetrahedralize(
        Path(path),
        edge_length=edge_length,
        edge_length_fac=edge_length_fac,
        epsilon=epsilon,
        optimize=optimize,
        threads=threads,
    )


GENERATORS: dict[str, Callable[..., jtet.TetMesh]] = {
    "gmsh_shape": gmsh_shape,
    "gmsh_two_regions": gmsh_two_regions,
    "tetwild": tetwild,
    "perturbed": perturbed,
    "file": file,
    "surface": surface,
}


def check(generator: str, params: dict) -> Callable[..., jtet.TetMesh]:
    """The generator function, after checking that ``params`` fit its signature.

    Raises ``ValueError`` on an unknown generator, unknown / missing parameters or an
    unknown shape, so a typo in a config fails before any mesh is made.
    """
    if generator not in GENERATORS:
        raise ValueError(f"unknown mesh generator {generator!r}; choose from {list(GENERATORS)}")
    fn = GENERATORS[generator]
    try:
        inspect.signature(fn).bind(**params)
    except TypeError as e:
        raise ValueError(f"mesh generator {generator!r}: {e}") from None
    if "shape" in params and params["shape"] not in SHAPES:
        raise ValueError(f"unknown shape {params['shape']!r}; choose from {list(SHAPES)}")
    return fn


def generate(generator: str, params: dict) -> jtet.TetMesh:
    """``GENERATORS[generator](**params)``, checked first (see ``check``)."""
    return check(generator, params)(**params)
