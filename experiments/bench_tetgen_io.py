"""TetGen files: jtet's own writer against meshio's, and the read back.

For each mesh (with a float point-data field, so the ``.node`` file has an attribute
column) and for linear and quadratic (10-node) output, in this process, alternating:
``jtet.save`` to ``.node`` / ``.ele`` (jtet's writer, one C-level formatting per file);
the baseline, meshio's TetGen writer on the same points, point data and 4-node tets
(what jtet used before; for the quadratic case a lower bound: it wrote the 10-node
``.ele`` file after it); and ``jtet.load`` of jtet's files (``linear=True`` for the
quadratic ones), checked to give the mesh back exactly.

    python experiments/bench_tetgen_io.py                          # demo, gmsh_cube
    python experiments/bench_tetgen_io.py --meshes delaunay:100000 --repeats 2
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_improve import load_mesh  # noqa: E402

import jtet  # noqa: E402
from jtet._quadratic import quadratic_mesh  # noqa: E402


def _meshio_save(mesh: jtet.TetMesh, quadratic: bool, path: Path) -> None:
    """meshio's TetGen writer on what jtet writes (4-node tets only: meshio's writer
    takes no other cells)."""
    import meshio

    points, point_data = mesh.points, mesh.point_data
    if quadratic:
        quad = quadratic_mesh(mesh)
        points, point_data = quad.points, quad.point_data
    columns = {"T": point_data["T"], "tetgen:ref": np.zeros(len(points), np.int64)}
    meshio.tetgen.write(
        str(path),
        meshio.Mesh(
            points,
            [meshio.CellBlock("tetra", mesh.tets)],
            cell_data={"tetgen:ref": [mesh.region]},
            point_data=columns,
        ),
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["demo", "gmsh_cube"])
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")  # the quadratic read's note on the mid-edge nodes
    work = Path(tempfile.mkdtemp(prefix="jtet-bench-tetgen-"))
    print(
        "| mesh | tets | cells | meshio save (s) | jtet save (s) | ratio | jtet load (s) |\n"
        "|---|---|---|---|---|---|---|"
    )
    for name in args.meshes:
        mesh = load_mesh(name)
        mesh = mesh.replace(point_data={"T": mesh.points[:, 0] * 3.0 + 0.1})
        for quadratic in (False, True):
            meshio_s, jtet_s, load_s = [], [], []
            for _ in range(args.repeats):
                t = time.perf_counter()
                _meshio_save(mesh, quadratic, work / "meshio.node")
                meshio_s.append(time.perf_counter() - t)
                t = time.perf_counter()
                jtet.save(mesh, work / "jtet.node", quadratic=quadratic)
                jtet_s.append(time.perf_counter() - t)
                t = time.perf_counter()
                back = jtet.load(work / "jtet.node", linear=quadratic)
                load_s.append(time.perf_counter() - t)
                assert np.array_equal(back.points, mesh.points)
                assert np.array_equal(back.tets, mesh.tets)
                assert np.array_equal(back.point_data["T"], mesh.point_data["T"])
            m, j, r = np.median(meshio_s), np.median(jtet_s), np.median(load_s)
            kind = "10-node" if quadratic else "4-node"
            print(
                f"| {name} | {mesh.n_tets} | {kind} | {m:.2f} | {j:.2f} | {m / j:.1f} | {r:.2f} |"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
