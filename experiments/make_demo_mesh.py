"""Generate the demo meshes shipped in ``jtet/data`` (needs the ``gmsh`` Python package).

    python experiments/make_demo_mesh.py   # -> jtet/data/demo.vtu, demo_two_regions.vtu

Both are unoptimized Gmsh Delaunay meshes (Mesh.Algorithm3D = 1, no Gmsh / Netgen
optimization, one thread, so the output is reproducible), i.e. the kind of mesh jtet is
meant to improve: it still holds the slivers Delaunay leaves behind.

- ``demo``: a 2 x 1 x 1 box with a spherical hole, one region (label 0).
- ``two_regions``: a unit box split by the plane z = 0.45 into two volumes with physical
  tags 1 (below) and 2 (above); the interface is a conforming internal surface.

``gmsh`` is an experiments extra only; jtet itself never imports it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gmsh
import numpy as np

import jtet
from jtet._io import save
from jtet._quality import tet_dihedrals

DATA = Path(__file__).resolve().parents[1] / "jtet" / "data"


def _setup(size: float) -> None:
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.NumThreads", 1)
    gmsh.option.setNumber("Mesh.MaxNumThreads1D", 1)
    gmsh.option.setNumber("Mesh.MaxNumThreads2D", 1)
    gmsh.option.setNumber("Mesh.MaxNumThreads3D", 1)
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay
    gmsh.option.setNumber("Mesh.Optimize", 0)
    gmsh.option.setNumber("Mesh.OptimizeNetgen", 0)
    gmsh.option.setNumber("Mesh.MeshSizeMax", size)
    gmsh.option.setNumber("Mesh.MeshSizeMin", 0.0)


def _extract(physical: dict[int, int] | None = None) -> jtet.TetMesh:
    """The current Gmsh model's linear tets as a positively oriented TetMesh.

    ``physical`` maps a volume entity tag to its region label (default: all 0).
    """
    tags, coords, _ = gmsh.model.mesh.getNodes()
    coords = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    blocks, labels = [], []
    for _, vol in gmsh.model.getEntities(3):
        types, _, nodes = gmsh.model.mesh.getElements(3, vol)
        for t, n in zip(types, nodes, strict=True):
            assert t == 4, f"unexpected Gmsh element type {t} (want 4-node tets)"
            tets = index[np.asarray(n, np.int64).reshape(-1, 4)]
            blocks.append(tets)
            labels.append(np.full(len(tets), (physical or {}).get(vol, 0), np.int64))
    tets = np.concatenate(blocks)
    region = np.concatenate(labels)
    # Drop nodes no tet uses (none expected) and renumber compactly.
    used, tets = np.unique(tets, return_inverse=True)
    tets = tets.reshape(-1, 4)
    points = coords[used]
    p = points[tets]
    vol6 = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    assert (vol6 != 0).all(), "degenerate tet in the Gmsh output"
    neg = vol6 < 0
    tets[neg] = tets[neg][:, [1, 0, 2, 3]]
    return jtet.TetMesh(points, tets, region)


def box_with_hole(size: float = 0.12) -> jtet.TetMesh:
    """A 2 x 1 x 1 box minus a ball of radius 0.3 at (0.7, 0.5, 0.5), one region."""
    gmsh.initialize()
    try:
        _setup(size)
        gmsh.model.add("demo")
        box = gmsh.model.occ.addBox(0, 0, 0, 2, 1, 1)
        ball = gmsh.model.occ.addSphere(0.7, 0.5, 0.5, 0.3)
        gmsh.model.occ.cut([(3, box)], [(3, ball)])
        gmsh.model.occ.synchronize()
        gmsh.model.mesh.generate(3)
        return _extract()
    finally:
        gmsh.finalize()


def two_regions(size: float = 0.15) -> jtet.TetMesh:
    """A unit box split by the plane z = 0.45 into regions 1 (below) and 2 (above)."""
    gmsh.initialize()
    try:
        _setup(size)
        gmsh.model.add("two_regions")
        lo = gmsh.model.occ.addBox(0, 0, 0, 1, 1, 0.45)
        hi = gmsh.model.occ.addBox(0, 0, 0.45, 1, 1, 0.55)
        gmsh.model.occ.fragment([(3, lo)], [(3, hi)])  # conforming shared interface
        gmsh.model.occ.synchronize()
        label = {}
        for _, vol in gmsh.model.getEntities(3):
            z = gmsh.model.occ.getCenterOfMass(3, vol)[2]
            label[vol] = 1 if z < 0.45 else 2
            gmsh.model.addPhysicalGroup(3, [vol], label[vol])
        gmsh.model.mesh.generate(3)
        return _extract(label)
    finally:
        gmsh.finalize()


def stats(name: str, mesh: jtet.TetMesh, path: Path) -> str:
    _, lo, hi = tet_dihedrals(mesh.points, mesh.tets)
    labels, counts = np.unique(mesh.region, return_counts=True)
    regions = dict(zip(labels.tolist(), counts.tolist(), strict=True))
    return (
        f"{name}: {mesh.n_points} points, {mesh.n_tets} tets, regions {regions}, "
        f"dihedral min {lo.min():.3f} deg / max {hi.max():.3f} deg, "
        f"tets < 5 deg: {(lo < 5).sum()}, min volume {mesh.volumes.min():.3e}, "
        f"file {path.stat().st_size / 1024:.1f} KiB"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DATA, help="output directory")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name, make, file in (
        ("demo", box_with_hole, "demo.vtu"),
        ("two_regions", two_regions, "demo_two_regions.vtu"),
    ):
        mesh = make()
        assert (mesh.volumes > 0).all()
        path = save(mesh, args.out / file)
        print(stats(name, mesh, path))


if __name__ == "__main__":
    main()
