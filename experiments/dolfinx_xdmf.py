"""dolfinx reads jtet's XDMF output: region volumes and boundary-tag areas agree.

jtet improves meshes and writes them as ``.xdmf``; a Python that has dolfinx (Debian's
``python3-dolfinx``: ``apt-get install python3-dolfinx`` puts dolfinx 0.5.2 into
``/usr/bin/python3``; never a jtet dependency) reads each file with
``XDMFFile.read_mesh(name="mesh")`` and ``read_meshtags(mesh, name="cell_tags" /
"facet_tags")`` and integrates 1 over every tagged region and boundary patch. The table
sets those integrals beside jtet's own sums of tet volumes and triangle areas.

    python experiments/dolfinx_xdmf.py                         # demo meshes, /usr/bin/python3
    python experiments/dolfinx_xdmf.py --meshes gmsh_holeplate --dolfinx-python /usr/bin/python3
    /usr/bin/python3 experiments/dolfinx_xdmf.py --write-fixture tests/data   # the test file

``--write-fixture DIR`` (run it with the dolfinx Python) writes ``dolfinx_cube.xdmf`` /
``.h5``, the dolfinx-written file ``tests/test_xdmf.py`` reads: a 4x4x4 unit cube, cell
tags 1 (x < 0.5) and 2, the exterior facets tagged 1-6 by side.

``--quadratic-check H [H ...]``: Gmsh's second-order ball in a box at each size h
(``quadratic_ball.py``), read with ``linear=True``, improved, and written with
``quadratic=True`` as ``.xdmf`` (``Tetrahedron_10``, VTK's node order) and ``.msh``.
dolfinx reads the ``.xdmf`` as a degree-2 mesh and integrates 1 over each region on its
curved geometry; Gmsh integrates its own Jacobians over the ``.msh``. A wrong node order
would bend the tets elsewhere: the two volumes would differ, and differ from the linear
tets' by more than the curved boundary does.

    python experiments/dolfinx_xdmf.py --quadratic-check 0.2 0.12 0.08
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# run by the dolfinx Python: one JSON line of the integrals over the file's tags
_READ_WITH_DOLFINX = r"""
import json, sys
from mpi4py import MPI
import numpy as np
import dolfinx, dolfinx.io, ufl
from dolfinx.fem import Constant, assemble_scalar, form
with dolfinx.io.XDMFFile(MPI.COMM_WORLD, sys.argv[1], "r") as f:
    mesh = f.read_mesh(name="mesh")
    cells = f.read_meshtags(mesh, name="cell_tags")
    mesh.topology.create_entities(2)
    facets = f.read_meshtags(mesh, name="facet_tags") if sys.argv[2] == "1" else None
one = Constant(mesh, 1.0)
dx = ufl.Measure("dx", domain=mesh, subdomain_data=cells)
out = {"version": dolfinx.__version__, "tets": mesh.topology.index_map(3).size_local,
       "volume": {int(v): assemble_scalar(form(one * dx(int(v)))) for v in np.unique(cells.values)},
       "area": {}}
if facets is not None:
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=facets)
    out["area"] = {int(v): assemble_scalar(form(one * ds(int(v)))) for v in np.unique(facets.values)}
print(json.dumps(out))
"""


def write_fixture(folder: Path) -> None:
    """The dolfinx-written test file (run with a Python that has dolfinx)."""
    import dolfinx
    import dolfinx.io
    import dolfinx.mesh
    import numpy as np
    from mpi4py import MPI

    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 4, 4, 4, dolfinx.mesh.CellType.tetrahedron)
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    mid = dolfinx.mesh.compute_midpoints(mesh, tdim - 1, facets)
    sides = [np.isclose(mid[:, a], v) for a in range(3) for v in (0, 1)][:5]
    side = np.select(sides, [1, 2, 3, 4, 5], 6).astype(np.int32)
    facet_tags = dolfinx.mesh.meshtags(mesh, tdim - 1, facets, side)
    facet_tags.name = "facet_tags"
    cells = np.arange(mesh.topology.index_map(tdim).size_local, dtype=np.int32)
    x = dolfinx.mesh.compute_midpoints(mesh, tdim, cells)[:, 0]
    cell_tags = dolfinx.mesh.meshtags(mesh, tdim, cells, np.where(x < 0.5, 1, 2).astype(np.int32))
    cell_tags.name = "cell_tags"
    path = folder / "dolfinx_cube.xdmf"
    with dolfinx.io.XDMFFile(MPI.COMM_WORLD, str(path), "w") as f:
        f.write_mesh(mesh)
        mesh.topology.create_connectivity(tdim - 1, 0)
        f.write_meshtags(facet_tags)
        f.write_meshtags(cell_tags)
    print(f"wrote {path} with dolfinx {dolfinx.__version__}")


def _mesh(name: str):
    import numpy as np

    import jtet

    if name in ("demo", "two_regions"):
        mesh = jtet.demo_mesh(name)
    else:
        sys.path.insert(0, str(Path(__file__).parent))
        from bench_improve import load_mesh

        mesh = load_mesh(name)
    if not len(mesh.protected_faces):  # tag the boundary: one label per axis direction
        T = mesh.topology
        faces = T.faces[T.boundary_face]
        p = mesh.points[faces]
        normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        labels = np.argmax(np.abs(normal), axis=1) + 1
        mesh = mesh.replace(protected_faces=faces, protected_face_labels=labels)
    return mesh


def _read_with_dolfinx(python: str, path: Path, facets: bool) -> tuple[dict, float]:
    """(dolfinx's JSON line for the file at ``path``, seconds)."""
    t0 = time.perf_counter()
    run = subprocess.run(
        [python, "-c", _READ_WITH_DOLFINX, str(path), "1" if facets else "0"],
        capture_output=True,
        text=True,
    )
    seconds = time.perf_counter() - t0
    if run.returncode:
        sys.exit(f"{path.name}: dolfinx failed:\n{run.stderr[-2000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1]), seconds


def quadratic_check(sizes: list[float], python: str) -> None:
    """Print the table of ``--quadratic-check``: each region's volume by jtet's linear
    tets, by Gmsh over jtet's quadratic ``.msh`` and by dolfinx over its ``.xdmf``."""
    import warnings

    import numpy as np

    import jtet

    sys.path.insert(0, str(Path(__file__).parent))
    from quadratic_ball import RADIUS, gmsh_measures, write_second_order

    print(
        "| h | region | tets | linear tets | Gmsh, .msh | dolfinx, .xdmf | dolfinx - Gmsh "
        "| box sides (dolfinx) | max area - 1 |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the --linear read's note on the dropped nodes
        for h in sizes:
            src = Path(tmp) / f"order2_{h}.msh"
            write_second_order(src, h)
            mesh = jtet.improve(jtet.load(src, linear=True), seed=0).mesh
            # the box's sides as facet tags (6-node triangles in the file): each has area 1
            T = mesh.topology
            faces = T.faces[T.boundary_face]
            centre = mesh.points[faces].mean(axis=1)
            axis = np.argmin(np.minimum(centre, 1 - centre), axis=1)
            side = 1 + 2 * axis + (centre[np.arange(len(faces)), axis] > 0.5)
            mesh = mesh.replace(protected_faces=faces, protected_face_labels=side)
            xdmf, msh = Path(tmp) / f"improved_{h}.xdmf", Path(tmp) / f"improved_{h}.msh"
            jtet.save(mesh, xdmf, quadratic=True)
            jtet.save(mesh, msh, quadratic=True)
            found, _ = _read_with_dolfinx(python, xdmf, facets=True)
            sides = found["area"].values()
            area_error = max(abs(a - 1.0) for a in sides) if sides else float("nan")
            by_gmsh = gmsh_measures(msh)
            for (dim, label), name in sorted(mesh.label_names.items()):
                if dim != 3:
                    continue
                linear = mesh.volumes[mesh.region == label].sum()
                gmsh_volume = by_gmsh[name][0]
                dolfinx_volume = found["volume"][str(label)]
                print(
                    f"| {h} | {name} | {found['tets']} | {linear:.9f} | {gmsh_volume:.9f} | "
                    f"{dolfinx_volume:.9f} | {dolfinx_volume - gmsh_volume:+.1e} | "
                    f"{len(found['area'])} | {area_error:.1e} |"
                )
    sphere = 4 / 3 * np.pi * RADIUS**3
    print(f"\ndolfinx {found['version']}; the ball's own volume: {sphere:.9f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", default="demo,two_regions")
    ap.add_argument("--dolfinx-python", default="/usr/bin/python3")
    ap.add_argument("--write-fixture", metavar="DIR")
    ap.add_argument("--quadratic-check", type=float, nargs="+", metavar="H")
    args = ap.parse_args()
    if args.write_fixture:
        write_fixture(Path(args.write_fixture))
        return
    if args.quadratic_check:
        quadratic_check(args.quadratic_check, args.dolfinx_python)
        return
    import numpy as np

    import jtet

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.meshes.split(","):
            mesh = _mesh(name)
            result = jtet.improve(mesh)
            out = Path(tmp) / f"{name.replace(':', '_')}.xdmf"
            jtet.save(result.mesh, out)
            found, seconds = _read_with_dolfinx(args.dolfinx_python, out, facets=True)
            m = result.mesh
            p = m.points[m.protected_faces]
            area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
            vol_err = max(
                abs(v - m.volumes[m.region == int(r)].sum()) for r, v in found["volume"].items()
            )
            area_err = max(
                abs(a - area[m.protected_face_labels == int(k)].sum())
                for k, a in found["area"].items()
            )
            rows.append(
                (
                    name,
                    m.n_tets,
                    found["tets"],
                    len(found["volume"]),
                    len(found["area"]),
                    vol_err,
                    area_err,
                    seconds,
                    found["version"],
                )  # fmt: skip
            )
    head = ("mesh", "tets (jtet)", "tets (dolfinx)", "regions", "facet tags",
            "max volume diff", "max area diff", "dolfinx read s", "dolfinx")  # fmt: skip
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]} | {r[5]:.1e} | {r[6]:.1e} | "
              f"{r[7]:.1f} | {r[8]} |")  # fmt: skip


if __name__ == "__main__":
    main()
