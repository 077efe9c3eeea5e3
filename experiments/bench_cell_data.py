"""What carrying cell data through ``jtet.improve`` costs, and what a label's interfaces
cost the run.

For each mesh, in this process, after a warm-up run that compiles:

* ``plain``: the run without cell data;
* ``float + ids``: with a float64 array (the centroid's x) and an int64 array of
  distinct ids: no interface is kept, so the run is the plain one and the difference is
  the carrying (VTK's locator, exact orientation tests);
* ``material``: with an int32 material that changes value across the plane x = mid
  (a zigzag surface through the mesh, whose faces the run keeps in place).

Prints the median seconds of each (runs alternating), the carrying's own seconds, how
many tets of the output took values from an overlapping input tet, the worst dihedral
angle of each, and the largest change of a material's volume (relative).

    python experiments/bench_cell_data.py                  # the four reference meshes
    python experiments/bench_cell_data.py --meshes demo --repeat 1
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_improve import MESHES, load_mesh  # noqa: E402

import jtet  # noqa: E402
from jtet._cell_data import carried_cell_data  # noqa: E402


def _volumes(mesh: jtet.TetMesh) -> np.ndarray:
    p = mesh.points[mesh.tets]
    return np.linalg.det(p[:, 1:] - p[:, :1]) / 6


def _variants(mesh: jtet.TetMesh) -> dict:
    c = mesh.points[mesh.tets].mean(axis=1)
    mid = 0.5 * (mesh.points[:, 0].min() + mesh.points[:, 0].max())
    ids = np.arange(mesh.n_tets, dtype=np.int64)
    return {
        "plain": mesh,
        "float + ids": mesh.replace(cell_data={"x": c[:, 0], "id": ids}),
        "material": mesh.replace(cell_data={"material": (c[:, 0] > mid).astype(np.int32)}),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", default=",".join(MESHES))
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    rows = []
    for name in args.meshes.split(","):
        mesh = load_mesh(name)
        variants = _variants(mesh)
        jtet.improve(mesh, seed=0)  # compiles
        seconds = {k: [] for k in variants}
        results = {}
        for _ in range(args.repeat):
            for k, m in variants.items():
                t = time.perf_counter()
                results[k] = jtet.improve(m, seed=0)
                seconds[k].append(time.perf_counter() - t)
        t = time.perf_counter()
        _, n_new, _ = carried_cell_data(variants["float + ids"], results["float + ids"].mesh)
        carry = time.perf_counter() - t
        mat_in = variants["material"]
        mat_out = results["material"].mesh
        v0, v1 = _volumes(mat_in), _volumes(mat_out)
        drift = max(
            abs(
                v0[mat_in.cell_data["material"] == k].sum()
                - v1[mat_out.cell_data["material"] == k].sum()
            )
            / abs(v0).sum()
            for k in (0, 1)
        )
        med = {k: float(np.median(v)) for k, v in seconds.items()}
        same = np.array_equal(results["plain"].mesh.tets, results["float + ids"].mesh.tets)
        rows.append([
            name, mesh.n_tets, f"{med['plain']:.2f}", f"{med['float + ids']:.2f}",
            f"{med['float + ids'] / med['plain']:.2f}", f"{carry * 1e3:.0f}", n_new,
            "yes" if same else "no", f"{results['plain'].stats_after.min_dihedral:.2f}",
            f"{med['material']:.2f}", f"{results['material'].stats_after.min_dihedral:.2f}",
            f"{drift:.1e}",
        ])  # fmt: skip
    head = [
        "mesh", "tets", "plain s", "float+ids s", "ratio", "carry ms", "new tets",
        "same mesh", "plain min", "material s", "material min", "volume drift",
    ]  # fmt: skip
    widths = [max(len(str(r[i])) for r in [head, *rows]) for i in range(len(head))]
    for r in [head, ["-" * w for w in widths], *rows]:
        print("  ".join(str(v).rjust(w) for v, w in zip(r, widths, strict=True)))


if __name__ == "__main__":
    main()
