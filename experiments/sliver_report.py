"""Worst dihedral angles of a TetGen-style sliver mesh after each topological operation.

TetGen's quality switch ``-q`` bounds the radius-edge ratio, which does not remove
slivers; its ``-pq`` output is the classic test case for flips. This script makes such a
mesh of a sphere with tetgenpy (AGPL: experiments only), then reports the worst and the
worst-five dihedral angles (smallest min and largest max over all tets), before and after
edge removal alone, multi-face removal alone, and both (``jtet.improve`` with those ops,
boundary fixed, no smoothing), plus success counts by ring size / number of faces removed.

    python experiments/sliver_report.py                 # ~50k-80k tets
    python experiments/sliver_report.py --area 0.0004   # smaller mesh
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np

import jtet
from jtet._quality import tet_dihedrals


def tetgen_sphere(resolution: int, max_volume: float) -> jtet.TetMesh:
    import pyvista as pv
    import tetgenpy

    s = pv.Sphere(radius=1.0, theta_resolution=resolution, phi_resolution=resolution)
    s = s.triangulate().clean()
    tio = tetgenpy.TetgenIO()
    tio.setup_plc(np.asarray(s.points, float), s.faces.reshape(-1, 4)[:, 1:].tolist())
    out = tetgenpy.tetrahedralize(f"pq1.5a{max_volume}Q", tio)
    pts = np.asarray(out.points(), np.float64)
    tets = np.asarray(out.tetrahedra(), np.int64)
    return jtet.TetMesh.from_arrays(pts, tets, source="tetgen -pq sphere")


def worst_five(mesh: jtet.TetMesh) -> tuple[np.ndarray, np.ndarray]:
    _, lo, hi = tet_dihedrals(mesh.points, mesh.tets)
    return np.sort(lo)[:5], np.sort(hi)[::-1][:5]


def fmt(a: np.ndarray) -> str:
    return " ".join(f"{x:6.2f}" for x in a)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, default=48, help="sphere surface resolution")
    p.add_argument("--area", type=float, default=1e-4, help="TetGen max tet volume (-a)")
    p.add_argument("--quality", default="min_sine")
    args = p.parse_args()
    mesh = tetgen_sphere(args.resolution, args.area)
    lo, hi = worst_five(mesh)
    print(f"TetGen -pq1.5a{args.area} sphere: {mesh.n_tets:,} tets, quality {args.quality}")
    print(
        f"{'ops':<12}{'tets':>8}  {'worst five min dihedral':<36}{'worst five max dihedral':<36}{'s':>6}"
    )
    print(f"{'input':<12}{mesh.n_tets:>8}  {fmt(lo):<36}{fmt(hi):<36}{'':>6}")
    jtet.improve(mesh, ops=("edge", "face"), max_passes=1)  # compile outside the timings
    for ops in (("edge",), ("face",), ("edge", "face")):
        t0 = time.perf_counter()
        r = jtet.improve(mesh, ops=ops, quality=args.quality)
        dt = time.perf_counter() - t0
        lo, hi = worst_five(r.mesh)
        print(f"{'+'.join(ops):<12}{r.mesh.n_tets:>8}  {fmt(lo):<36}{fmt(hi):<36}{dt:>6.1f}")
        for op in ops:
            sizes = Counter()
            for h in r.history:
                if h["op"] == op:
                    sizes.update({int(k): v for k, v in h["by_size"].items()})
            what = "ring size" if op == "edge" else "faces removed"
            total = sum(sizes.values())
            print(f"    {op}: {total} successes by {what}: {dict(sorted(sizes.items()))}")


if __name__ == "__main__":
    main()
