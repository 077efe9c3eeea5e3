"""Curved edges between coplanar faces: Gmsh's second-order extruded cylinder through
improve.

Gmsh meshes a disk (radius 0.5) with triangles of size ``h``, extrudes it into ``layers``
layers of prisms along z (each cut into three tets: the curved side's quadrilaterals are
split in two planar triangles) and makes the mesh quadratic (``SetOrder 2``: the nodes
of the side's edges on the cylinder). jtet loads it with ``linear=True``: the side's
circumferential edges and the quadrilaterals' diagonals are curved, and the two
triangles at a diagonal are coplanar, so a 2-2 flip could replace the diagonal by the
other one, straight across the curved surface.

Each mesh is improved twice: as loaded (its curved edges on the surface are protected
for the run when their node is off the plane of their faces,
``_curved_guard.surface_curved_edges``) and without its curved edges (a
linear mesh: the flips are free). The table counts the curved edges each output still
has (the linear run's: those of its edges that are the input's curved ones), the worst
and largest dihedral angles, and the time of each run and of ``surface_curved_edges``.

    python experiments/quadratic_cylinder.py                   # h = 0.08 and 0.04
    python experiments/quadratic_cylinder.py --h 0.1 --layers 8
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import jtet
from jtet._curved_guard import surface_curved_edges
from jtet._quadratic import curved_edges_kept


def gmsh_cylinder(path: Path, h: float, layers: int) -> None:
    """Write Gmsh's second-order mesh of the extruded unit-height cylinder to ``path``."""
    import gmsh

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.model.occ.addDisk(0, 0, 0, 0.5, 0.5)
        gmsh.model.occ.extrude([(2, 1)], 0, 0, 1, numElements=[layers])
        gmsh.model.occ.synchronize()
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.setOrder(2)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--h", type=float, nargs="+", default=[0.08, 0.04])
    parser.add_argument("--layers", type=int, default=0, help="0: 1 / h")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    warnings.simplefilter("ignore")  # the --linear read's note on the dropped nodes
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for h in args.h:
            layers = args.layers or round(1 / h)
            path = Path(tmp) / f"cylinder_{h}.msh"
            gmsh_cylinder(path, h, layers)
            mesh = jtet.load(path, linear=True)
            t0 = time.perf_counter()
            on_surface = surface_curved_edges(mesh)
            t_find = time.perf_counter() - t0
            before = jtet.stats(mesh)
            n_curved = len(mesh.curved_edges.edges)
            t0 = time.perf_counter()
            kept = jtet.improve(mesh, seed=args.seed)
            t_kept = time.perf_counter() - t0
            t0 = time.perf_counter()
            plain = jtet.improve(mesh.replace(curved_edges=None), seed=args.seed)
            t_plain = time.perf_counter() - t0
            still = plain.mesh.topology.edge_ids(mesh.curved_edges.edges) >= 0
            name = f"{h} ({layers} layers)"
            rows.append(
                (
                    name,
                    "input",
                    mesh.n_tets,
                    before,
                    f"{n_curved} ({len(on_surface)} bending a surface)",
                    f"find {t_find:.3f}",
                )
            )
            n_kept = int(curved_edges_kept(mesh, kept.mesh).sum())
            rows.append((name, "improve", kept.mesh.n_tets, kept.stats_after, n_kept, t_kept))
            rows.append(
                (
                    name,
                    "improve, linear",
                    plain.mesh.n_tets,
                    plain.stats_after,
                    int(still.sum()),
                    t_plain,
                )
            )
    print("| h | run | tets | min / max dihedral | curved edges kept | s |")
    print("|---|---|---|---|---|---|")
    for name, run, tets, stats, curved, seconds in rows:
        secs = seconds if isinstance(seconds, str) else f"{seconds:.1f}"
        print(
            f"| {name} | {run} | {tets} | {stats.min_dihedral:.2f} / {stats.max_dihedral:.2f} "
            f"| {curved} | {secs} |"
        )


if __name__ == "__main__":
    main()
