"""Hypothesis strategies for fuzzing jtet: random small tet meshes and random options.

Meshes are drawn as a handful of small choices (kind, size, seed, perturbations) and then
built with a seeded NumPy generator: hypothesis shrinks the choices, and a failure is
reproduced exactly from them (``build_mesh(MeshSpec(...))``), which is how a failure is
turned into an explicit regression test.

Point sets (``KINDS``): uniform and clustered random points, near-coplanar and
near-cospherical sets (slivers), perturbed and exact grids (exact grids are cospherical:
qhull returns zero-volume tets), and points in a cube with points on its flat faces
(removable boundary edges). The tets are scipy's Delaunay simplices as qhull lists them
(both orientations), passed through ``TetMesh.from_arrays``, which reorders tets listed
inside out. Optional damage: interior vertices moved far enough to invert tets. Optional
labels: region labels by random plane splits or random per tet (almost every face becomes
an interface: a test of protection), random protected edges, faces and vertices.

Meshes have 20-200 points, so the padded batches of the kernels (``bucket_capacity``)
take one or two sizes and jitted kernels are compiled once per (ring size, measure).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from hypothesis import strategies as st
from scipy.spatial import Delaunay

import jtet
from jtet._mesh import face_conflicts
from jtet._options import BOUNDARY_MODES

KINDS = ("uniform", "clustered", "coplanar", "cospherical", "grid", "cube")
REGIONS = ("none", "planes", "random")
# Operations the fuzz tests run (all of jtet's) and those run on damaged (inverted) input.
FUZZ_OPS = ("edge", "face", "smooth")
DAMAGE_OPS = FUZZ_OPS


@dataclass(frozen=True)
class MeshSpec:
    """Everything ``build_mesh`` needs to rebuild one fuzz mesh exactly."""

    kind: str = "uniform"
    n_points: int = 40
    seed: int = 0
    scale: float = 1e-6  # thickness / noise of near-degenerate kinds; grid perturbation
    n_moved: int = 0  # interior vertices moved to invert tets
    move: float = 0.0  # how far (relative to the box size)
    regions: str = "none"
    n_regions: int = 2
    protect_edges: float = 0.0  # fraction of edges protected
    protect_faces: float = 0.0  # fraction of interior faces protected
    protect_boundary: float = 0.0  # fraction of boundary faces protected
    face_labels: int = 0  # protected faces get labels 0 .. face_labels - 1 (0: all 0)
    protect_vertices: float = 0.0  # fraction of vertices protected (never moved)
    seam: bool = False  # the tets beyond a random plane get copies of the points they share
    # (or of those beyond a second plane: a crack with a front)


def _points(spec: MeshSpec, rng: np.random.Generator) -> np.ndarray:
    n = spec.n_points
    if spec.kind == "uniform":
        return rng.random((n, 3))
    if spec.kind == "clustered":
        c = rng.random((3, 3))
        p = c[rng.integers(0, 3, n)] + 0.05 * rng.standard_normal((n, 3))
        return np.vstack([p, rng.random((4, 3))])
    if spec.kind == "coplanar":
        p = rng.random((n, 3))
        p[:, 2] = 0.5 + spec.scale * rng.standard_normal(n)
        return np.vstack([p, [[0.5, 0.5, 0.0], [0.5, 0.5, 1.0], [0.1, 0.9, 0.2], [0.9, 0.1, 0.8]]])
    if spec.kind == "cospherical":
        v = rng.standard_normal((n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        v *= 1.0 + spec.scale * rng.standard_normal((n, 1))
        return np.vstack([v, [[0.0, 0.0, 0.0]]])
    if spec.kind == "grid":
        k = max(2, round(n ** (1 / 3)))
        ax = np.arange(k + 1, dtype=float)
        g = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
        # scale 0 keeps the exact grid: cospherical, qhull leaves flat tets
        return g + spec.scale * rng.uniform(-1, 1, g.shape) * (rng.random(len(g)) < 0.5)[:, None]
    if spec.kind == "cube":
        corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
        s = rng.random((n // 2, 3))
        s[np.arange(len(s)), rng.integers(0, 3, len(s))] = rng.integers(0, 2, len(s))
        return np.vstack([corners, s, rng.random((n - n // 2, 3))])
    raise ValueError(spec.kind)


def build_mesh(spec: MeshSpec) -> jtet.TetMesh | None:
    """The mesh of ``spec``, or None when qhull or the reordering cannot make one."""
    rng = np.random.default_rng(spec.seed)
    pts = _points(spec, rng)
    try:
        tets = Delaunay(pts).simplices.astype(np.int64)
    except Exception:  # qhull refuses (e.g. all points coplanar): no mesh
        return None
    if len(tets) == 0:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = jtet.TetMesh.from_arrays(pts, tets)
    if len(face_conflicts(mesh.tets, mesh.n_points)[1]):
        return None  # inconsistent orders that reordering could not fix (flat tets)
    pts = mesh.points.copy()
    if spec.n_moved:
        # move interior vertices (not on the hull): tets around them invert
        hull = np.unique(Delaunay(pts).convex_hull) if spec.kind != "grid" else np.zeros(0, int)
        inner = np.setdiff1d(np.unique(mesh.tets), hull)
        if len(inner):
            k = rng.choice(inner, min(spec.n_moved, len(inner)), replace=False)
            size = np.ptp(pts, axis=0).max()
            pts[k] += spec.move * size * rng.standard_normal((len(k), 3))
    region = None
    if spec.regions == "planes":
        c = pts[mesh.tets].mean(axis=1)
        region = np.zeros(mesh.n_tets, np.int64)
        for _ in range(spec.n_regions - 1):
            normal = rng.standard_normal(3)
            region += (c - pts.mean(axis=0)) @ normal > rng.normal(0, 0.1) * np.ptp(pts)
    elif spec.regions == "random":
        region = rng.integers(0, spec.n_regions, mesh.n_tets)
    pe = pf = None
    if spec.protect_edges:
        e = np.unique(np.sort(mesh.tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]], 2)
                      .reshape(-1, 2), axis=0)  # fmt: skip
        pe = e[rng.random(len(e)) < spec.protect_edges]
    if spec.protect_faces or spec.protect_boundary:
        f, cnt = np.unique(
            np.sort(mesh.tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]], 2).reshape(-1, 3),
            axis=0,
            return_counts=True,
        )
        pf = np.zeros((0, 3), np.int64)
        if spec.protect_faces:
            inner = f[cnt == 2]
            pf = inner[rng.random(len(inner)) < spec.protect_faces]
        if spec.protect_boundary:  # their 2-2 flips must keep them protected
            outer = f[cnt == 1]
            pf = np.concatenate([pf, outer[rng.random(len(outer)) < spec.protect_boundary]])
    labels = None
    if pf is not None and len(pf) and spec.face_labels:
        # labels by position (a slab per label), so labelled patches have borders
        c = pts[pf].mean(axis=1) @ rng.standard_normal(3)
        labels = np.digitize(c, np.quantile(c, np.linspace(0, 1, spec.face_labels + 1)[1:-1]))
    pv = None
    if spec.protect_vertices:
        pv = np.flatnonzero(rng.random(len(pts)) < spec.protect_vertices)
    tets = mesh.tets
    if spec.seam:  # a crack: two coincident surfaces that share no vertex
        assert region is pf is pe is pv is None, "a seam's spec has no labels"
        c = pts[tets].mean(axis=1)
        beyond = (c - c.mean(axis=0)) @ rng.standard_normal(3) > 0
        on = np.zeros((2, len(pts)), bool)
        on[0, tets[~beyond].reshape(-1)] = True
        on[1, tets[beyond].reshape(-1)] = True
        shared = np.flatnonzero(on.all(axis=0))
        if rng.random() < 0.5:  # copy only the points on one side of a second plane: a
            # crack whose front (the points left shared) runs inside the mesh
            shared = shared[(pts[shared] - c.mean(axis=0)) @ rng.standard_normal(3) > 0]
        copy = np.arange(len(pts))
        copy[shared] = len(pts) + np.arange(len(shared))
        pts = np.vstack([pts, pts[shared]])
        tets = np.where(beyond[:, None], copy[tets], tets)
    return jtet.TetMesh(pts, tets, region, pf, pe, labels, pv)


@st.composite
def mesh_specs(
    draw, damage: bool | None = None, labels: bool | None = None, seam: bool | None = False
) -> MeshSpec:
    """Random ``MeshSpec``. ``damage`` / ``labels`` / ``seam``: force inverted tets /
    regions and protection / a seam on (True) or off (False); None draws them. A seam
    needs ``improve``, which pins it (a pass alone may flip one side's triangles), and
    comes without labels."""
    kind = draw(st.sampled_from(KINDS))
    n = draw(st.integers(20, 200))
    seed = draw(st.integers(0, 2**32 - 1))
    scale = {
        "coplanar": draw(st.sampled_from([1e-12, 1e-9, 1e-6, 1e-3, 1e-2])),
        "cospherical": draw(st.sampled_from([0.0, 1e-12, 1e-8, 1e-4])),
        "grid": draw(st.sampled_from([0.0, 0.0, 0.05, 0.2, 0.4])),
    }.get(kind, 0.0)
    if kind == "grid":
        n = min(n, 125)
    moved = draw(st.booleans()) if damage is None else damage
    n_moved = draw(st.integers(1, 6)) if moved else 0
    move = draw(st.sampled_from([0.02, 0.05, 0.1, 0.3])) if moved else 0.0
    lab = draw(st.booleans()) if labels is None else labels
    regions, n_regions, pe, pf, pb = "none", 2, 0.0, 0.0, 0.0
    if lab:
        regions = draw(st.sampled_from(REGIONS))
        n_regions = draw(st.integers(2, 4))
        pe = draw(st.sampled_from([0.0, 0.0, 0.05, 0.3]))
        pf = draw(st.sampled_from([0.0, 0.0, 0.05, 0.2]))
        pb = draw(st.sampled_from([0.0, 0.0, 0.3, 1.0]))
    fl = draw(st.sampled_from([0, 2, 3])) if lab else 0
    pv = draw(st.sampled_from([0.0, 0.0, 0.1, 0.5])) if lab else 0.0
    cut = (draw(st.booleans()) if seam is None else seam) and not lab
    return MeshSpec(
        kind, n, seed, scale, n_moved, move, regions, n_regions, pe, pf, pb, fl, pv, cut
    )


@st.composite
def options(draw, ops: tuple[str, ...] | None = None) -> jtet.Options:
    """Random ``jtet.Options`` with ``check=True`` and few passes (fuzz runs stay short)."""
    if ops is None:
        ops = tuple(o for o in FUZZ_OPS if draw(st.booleans())) or (
            draw(st.sampled_from(FUZZ_OPS)),
        )
    return jtet.Options(
        ops=ops,
        quality=draw(st.sampled_from(sorted(jtet.MEASURES))),
        max_ring=draw(st.integers(3, 12)),
        max_faces=draw(st.sampled_from([4, 16])),
        boundary=draw(st.sampled_from(BOUNDARY_MODES)),
        feature_angle=draw(st.sampled_from([0.0, 0.0, 10.0, 60.0])),
        max_passes=draw(st.integers(1, 3)),
        patience=draw(st.integers(1, 2)),
        perturb=draw(st.sampled_from([0, 0, 0, 2, 2, "auto"])),
        insert=draw(st.sampled_from([True, True, False])),
        seed=draw(st.integers(0, 1000)),
        goal_min_dihedral=draw(st.sampled_from([None, None, None, 5.0, 20.0, 35.0])),
        goal_max_dihedral=draw(st.sampled_from([None, None, None, 170.0, 150.0, 130.0])),
        check=True,
    )
