"""What reading Gmsh views as point and cell data costs, per MSH version and encoding.

For a mesh (default: the ~1M-tet Gmsh cube of ``bench_improve.py``), Gmsh itself (the
``gmsh`` module, experiments extra) writes the file in MSH 2.2 and 4.1, ASCII and binary,
with a node view (x) and an element view over the tets (their element numbers), as Gmsh
saves views with a mesh. For each file this prints, in this process, the best of
``--repeat`` loads:

* ``meshio``: ``meshio.read`` of the file without its views (meshio 5.3 refuses the
  views; the baseline jtet's Gmsh reading mends);
* ``jtet, no views``: ``jtet.load`` of the same file;
* ``jtet, views``: ``jtet.load`` of the file with its views (point and cell data read,
  the tets' element numbers read again from ``$Elements``), and the ratio to the line
  before;

and checks that every tet's value is the element number of the tet at its place. Then
``jtet.save`` to ``.msh`` with and without point and cell data.

    python experiments/bench_gmsh_views.py                       # ~1M tets
    python experiments/bench_gmsh_views.py --mesh gmsh:cube:0.05 --repeat 3

Results: ``experiments/results/gmsh_views.md``.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import warnings
from pathlib import Path

import meshio
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_improve import load_mesh  # noqa: E402
from bench_topology import best_of  # noqa: E402

import jtet  # noqa: E402


def _gmsh_files(mesh: jtet.TetMesh, out: Path) -> list[tuple[str, Path, Path]]:
    """(label, file with views, the same file without them) per version and encoding."""
    import gmsh

    plain = out / "plain.msh"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # region 0: no physical volume
        jtet.save(mesh, plain)
    files = []
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(plain))
        model = gmsh.model.getCurrent()
        nodes, coords, _ = gmsh.model.mesh.getNodes()
        _, (tets,), _ = gmsh.model.mesh.getElements(3)
        x = gmsh.view.add("x")
        gmsh.view.addModelData(x, 0, model, "NodeData", nodes, coords.reshape(-1, 3)[:, :1])
        number = gmsh.view.add("number")
        gmsh.view.addModelData(number, 0, model, "ElementData", tets, tets[:, None] * 1.0)
        for version in (2.2, 4.1):
            for binary in (0, 1):
                label = f"MSH {version} {'binary' if binary else 'ASCII'}"
                bare = out / f"bare_{version}_{binary}.msh"
                views = out / f"views_{version}_{binary}.msh"
                gmsh.option.setNumber("Mesh.MshFileVersion", version)
                gmsh.option.setNumber("Mesh.Binary", binary)
                gmsh.option.setNumber("PostProcessing.SaveMesh", 1)
                gmsh.write(str(bare))
                gmsh.write(str(views))
                gmsh.option.setNumber("PostProcessing.SaveMesh", 0)
                for view in (x, number):
                    gmsh.view.write(view, str(views), append=True)
                files.append((label, views, bare))
    finally:
        gmsh.finalize()
    return files


def _element_centroids(path: Path) -> dict:
    """{element number: centroid} of the tets of ``path``, as Gmsh reads them."""
    import gmsh

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(path))
        nodes, coords, _ = gmsh.model.mesh.getNodes()
        _, (tets,), (corners,) = gmsh.model.mesh.getElements(3)
    finally:
        gmsh.finalize()
    xyz = np.empty((int(nodes.max()) + 1, 3))
    xyz[nodes] = coords.reshape(-1, 3)
    return tets, xyz[corners.reshape(-1, 4)].mean(axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh", default="gmsh:cube:0.0167")
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    mesh = load_mesh(args.mesh)
    print(f"{args.mesh}: {mesh.n_tets} tets, {mesh.n_points} points\n")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        files = _gmsh_files(mesh, Path(tmp))
        numbers, centroids = _element_centroids(files[0][1])
        order = np.argsort(numbers)
        for label, views, bare in files:
            t_meshio, _ = best_of(lambda bare=bare: meshio.read(bare), args.repeat)
            t_bare, _ = best_of(lambda bare=bare: jtet.load(bare), args.repeat)
            t_views, m = best_of(lambda views=views: jtet.load(views), args.repeat)
            at = order[np.searchsorted(numbers[order], m.cell_data["number"].astype(np.int64))]
            err = np.abs(m.points[m.tets].mean(axis=1) - centroids[at]).max()
            ok = err < 1e-12 and np.array_equal(m.point_data["x"], m.points[:, 0])
            size = views.stat().st_size / 1e6
            rows.append((label, size, t_meshio, t_bare, t_views, t_views / t_bare, ok))
        data = mesh.replace(
            point_data={"T": mesh.points[:, 0].copy(), "u": mesh.points.copy()},
            cell_data={"s": np.arange(mesh.n_tets, dtype=np.float64)},
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t_plain, _ = best_of(lambda: jtet.save(mesh, Path(tmp) / "a.msh"), args.repeat)
            t_data, _ = best_of(lambda: jtet.save(data, Path(tmp) / "b.msh"), args.repeat)
    head = "| file | MB | meshio (no views) s | jtet, no views s | jtet, views s | ratio | values at the right places |"
    print(head)
    print("|" + "---|" * 7)
    for label, size, a, b, c, r, ok in rows:
        print(f"| {label} | {size:.0f} | {a:.2f} | {b:.2f} | {c:.2f} | {r:.2f} | {ok} |")
    print(
        f"\njtet.save .msh: {t_plain:.2f} s plain, {t_data:.2f} s with point data T, u and "
        f"cell data s ({t_data / t_plain:.2f}x)"
    )
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(f"peak RSS of the process: {peak:.2f} GB")


if __name__ == "__main__":
    main()
