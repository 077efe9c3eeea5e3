"""NGSolve reads jtet's Netgen ``.vol`` output: material volumes, boundary areas and the
flux of the position through each boundary agree with NGSolve's own file.

A Python that has NGSolve (``pip install ngsolve`` into a virtual environment of its own;
LGPL, never a jtet dependency) meshes a unit cube holding a ball of radius 0.25 with
Netgen (materials "matrix" and "inclusion", boundaries "left", "right", "wall",
"interface") and saves it; jtet reads that file, improves it and writes ``.vol``;
NGSolve loads both and integrates, per material and per boundary name, 1 and, over each
boundary, n_x and (x, y, z) . n: the last two test that the surface elements' normals
point from ``domin`` to ``domout`` as Netgen's own do (on the interface: into the ball).

    python experiments/ngsolve_vol.py --ngsolve-python /tmp/ngvenv/bin/python
    /tmp/ngvenv/bin/python experiments/ngsolve_vol.py --write-fixture tests/data
    python experiments/ngsolve_vol.py --ngsolve-python /tmp/ngvenv/bin/python --quadratic-check

``--write-fixture DIR`` (run it with the NGSolve Python) writes ``netgen_ball.vol.gz``,
the Netgen-written file ``tests/test_netgen.py`` reads (maxh 0.25, and the integrals
NGSolve computes on it into ``netgen_ball.json``), ``netgen_periodic.vol.gz``: a
unit cube periodic in x and y (two identifications, maxh 0.3), and
``netgen_ball_o2.vol.gz``: the ball in the cube at maxh 0.4, made second order by
Netgen (``Mesh.SecondOrder``: 10-node tets, the ball's edge nodes on the sphere).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# run by the NGSolve Python: one JSON line of the integrals over the file's regions
_INTEGRALS = r"""
import json, sys
import ngsolve
from ngsolve import BND, CF, Integrate, Mesh, specialcf, x, y, z
mesh = Mesh(sys.argv[1])
n = specialcf.normal(3)
out = {"version": ngsolve.__version__, "tets": mesh.ne, "vertices": mesh.nv,
       "volume": {m: Integrate(1, mesh, definedon=mesh.Materials(m)) for m in set(mesh.GetMaterials())},
       "area": {}, "flux_x": {}, "flux_r": {}}
for b in set(mesh.GetBoundaries()):
    on = mesh.Boundaries(b)
    out["area"][b] = Integrate(1, mesh, BND, definedon=on)
    out["flux_x"][b] = Integrate(n[0], mesh, BND, definedon=on)
    out["flux_r"][b] = Integrate(n * CF((x, y, z)), mesh, BND, definedon=on)
print(json.dumps(out, sort_keys=True))
"""


# run by the NGSolve Python: the file's identified vertex pairs, as Netgen reads them
_IDENTIFIED = r"""
import json, sys
from netgen.meshing import Mesh
mesh = Mesh()
mesh.Load(sys.argv[1])
pairs = sorted(sorted((p[0].nr, p[1].nr)) for p in mesh.GetIdentifications())
print(json.dumps({"vertices": len(mesh.Points()), "pairs": pairs}))
"""


def netgen_mesh(maxh: float):
    """Netgen's mesh of the unit cube with a ball inside (run with the NGSolve Python)."""
    from netgen.occ import Box, Glue, OCCGeometry, Pnt, Sphere, X

    box = Box(Pnt(0, 0, 0), Pnt(1, 1, 1))
    box.faces.name = "wall"
    box.faces.Min(X).name = "left"
    box.faces.Max(X).name = "right"
    ball = Sphere(Pnt(0.5, 0.5, 0.5), 0.25)
    ball.faces.name = "interface"
    ball.mat("inclusion")
    outer = box - ball
    outer.mat("matrix")
    return OCCGeometry(Glue([outer, ball])).GenerateMesh(maxh=maxh)


def periodic_mesh(maxh: float):
    """Netgen's mesh of the unit cube, periodic in x and y (run with the NGSolve Python)."""
    from netgen.occ import Box, IdentificationType, OCCGeometry, Pnt, X, Y

    box = Box(Pnt(0, 0, 0), Pnt(1, 1, 1))
    box.faces.Min(X).Identify(box.faces.Max(X), "px", IdentificationType.PERIODIC)
    box.faces.Min(Y).Identify(box.faces.Max(Y), "py", IdentificationType.PERIODIC)
    box.mat("cell")
    return OCCGeometry(box).GenerateMesh(maxh=maxh)


def write_fixture(folder: Path) -> None:
    """The Netgen-written test files and NGSolve's integrals on the first."""
    folder.mkdir(parents=True, exist_ok=True)
    periodic_mesh(0.3).Save(str(folder / "netgen_periodic.vol.gz"))
    path = folder / "netgen_ball.vol.gz"
    netgen_mesh(0.25).Save(str(path))
    out = subprocess.run(
        [sys.executable, "-c", _INTEGRALS, str(path)], capture_output=True, text=True, check=True
    )
    (folder / "netgen_ball.json").write_text(out.stdout)
    print(f"wrote {path} and {folder / 'netgen_ball.json'}")
    second = netgen_mesh(0.4)
    second.SecondOrder()  # curved: the nodes of the sphere's edges on the sphere
    second.Save(str(folder / "netgen_ball_o2.vol.gz"))
    print(f"wrote {folder / 'netgen_ball_o2.vol.gz'}")


def integrals(python: str, path: Path) -> dict:
    out = subprocess.run([python, "-c", _INTEGRALS, str(path)], capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"NGSolve could not read {path}:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


# run by the Netgen Python: load a .vol file and export it as Gmsh 2 (Netgen's own
# mapping of its second-order nodes to Gmsh's order)
_EXPORT_GMSH = r"""
import sys
from netgen.meshing import Mesh
mesh = Mesh()
mesh.Load(sys.argv[1])
mesh.Export(sys.argv[2], "Gmsh2 Format")
"""


def quadratic_check(python: str) -> None:
    """jtet's quadratic .vol output through Netgen: Netgen's second-order fixture read
    with --linear, improved, written with --quadratic; Netgen loads the file and
    exports it as Gmsh 2, and every 10-node tet and 6-node triangle there has, on each
    edge, the node jtet's quadratic mesh has (points matched to Netgen's 6 printed
    digits)."""
    import warnings

    import meshio
    import numpy as np
    from scipy.spatial import cKDTree

    import jtet
    from jtet._quadratic import MID_EDGES, quadratic_mesh

    warnings.simplefilter("ignore")
    fixture = Path(__file__).resolve().parents[1] / "tests" / "data" / "netgen_ball_o2.vol.gz"
    mesh = jtet.improve(jtet.load(fixture, linear=True), seed=0).mesh
    quad = quadratic_mesh(mesh)
    with tempfile.TemporaryDirectory() as tmp:
        out, exported = Path(tmp) / "jtet_o2.vol", Path(tmp) / "netgen_export.msh"
        jtet.save(mesh, out, quadratic=True)
        subprocess.run([python, "-c", _EXPORT_GMSH, str(out), str(exported)], check=True)
        theirs = meshio.read(exported)
    distance, ids = cKDTree(quad.points).query(theirs.points)
    tets, tris = ids[theirs.get_cells_type("tetra10")], ids[theirs.get_cells_type("triangle6")]
    ends = tets[:, MID_EDGES[4]].reshape(-1, 2)
    tets_ok = np.array_equal(quad.cells(ends)[:, 2].reshape(-1, 6), tets[:, 4:])
    tris_ok = np.array_equal(quad.cells(tris[:, :3])[:, 3:], tris[:, 3:])
    print(
        f"Netgen's export of jtet's quadratic .vol ({mesh.n_tets} tets, "
        f"{len(mesh.curved_edges.edges)} curved edges): points within "
        f"{distance.max():.1e} of jtet's; {len(tets)} 10-node tets "
        f"{'all' if tets_ok else 'NOT all'} with jtet's edge nodes, {len(tris)} 6-node "
        f"triangles {'all' if tris_ok else 'NOT all'} with them"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ngsolve-python", default="python3", help="a Python that has NGSolve")
    p.add_argument("--maxh", type=float, default=0.1, help="Netgen's mesh size")
    p.add_argument("--write-fixture", type=Path, help="write the test file into this folder")
    p.add_argument(
        "--quadratic-check",
        action="store_true",
        help="only check jtet's quadratic .vol output through Netgen (netgen-mesher is enough)",
    )
    args = p.parse_args()
    if args.write_fixture:
        write_fixture(args.write_fixture)
        return
    if args.quadratic_check:
        quadratic_check(args.ngsolve_python)
        return
    import jtet

    with tempfile.TemporaryDirectory() as tmp:
        made = Path(tmp) / "netgen.vol"
        script = (
            "import sys; sys.path.insert(0, sys.argv[1]); import ngsolve_vol;"
            "ngsolve_vol.netgen_mesh(float(sys.argv[2])).Save(sys.argv[3])"
        )
        here = str(Path(__file__).resolve().parent)
        subprocess.run(
            [args.ngsolve_python, "-c", script, here, str(args.maxh), str(made)], check=True
        )
        mesh = jtet.load(made)
        t0 = time.perf_counter()
        result = jtet.improve(mesh)
        seconds = time.perf_counter() - t0
        out = Path(tmp) / "jtet.vol"
        jtet.save(result.mesh, out)
        theirs, ours = integrals(args.ngsolve_python, made), integrals(args.ngsolve_python, out)
        script = script.replace("netgen_mesh", "periodic_mesh")
        periodic = Path(tmp) / "periodic.vol"
        subprocess.run([args.ngsolve_python, "-c", script, here, "0.3", str(periodic)], check=True)
        periodic_result = jtet.improve(jtet.load(periodic))
        jtet.save(periodic_result.mesh, Path(tmp) / "periodic_jtet.vol")
        same = [
            json.loads(
                subprocess.run(
                    [args.ngsolve_python, "-c", _IDENTIFIED, str(f)],
                    capture_output=True, text=True, check=True,
                ).stdout
            )
            for f in (periodic, Path(tmp) / "periodic_jtet.vol")
        ]  # fmt: skip
    b, a = result.stats_before, result.stats_after
    print(
        f"Netgen mesh (maxh {args.maxh}, NGSolve {theirs['version']}): {theirs['tets']} tets, "
        f"{b.min_dihedral:.2f} / {b.max_dihedral:.2f} degrees; jtet: {ours['tets']} tets, "
        f"{a.min_dihedral:.2f} / {a.max_dihedral:.2f} in {seconds:.1f} s\n"
    )
    print("| integral (NGSolve) | on | Netgen's file | jtet's file | difference |")
    print("|---|---|---|---|---|")
    for what in ("volume", "area", "flux_x", "flux_r"):
        for name in sorted(theirs[what]):
            x, y = theirs[what][name], ours[what].get(name, float("nan"))
            print(f"| {what} | {name} | {x:.12f} | {y:.12f} | {abs(x - y):.1e} |")
    pb, pa = periodic_result.stats_before, periodic_result.stats_after
    print(
        f"\nPeriodic cube (x and y, maxh 0.3): {pb.min_dihedral:.2f} -> {pa.min_dihedral:.2f} "
        f"degrees; Netgen reads {len(same[0]['pairs'])} identified pairs from its file and "
        f"{len(same[1]['pairs'])} from jtet's, "
        + ("the same pairs." if same[0]["pairs"] == same[1]["pairs"] else "NOT the same pairs.")
    )


if __name__ == "__main__":
    main()
