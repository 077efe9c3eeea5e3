"""The files users bring: one geometry meshed by Gmsh and TetGen with the switches people
use, each read from its file and improved by ``jtet.improve`` (defaults, boundary fixed).

Looks for inputs on which a run does little or nothing for a reason of the file rather
than of the mesh (as TetGen's ``-f`` listing of every face once froze every flip), and
shows what each kind of mesh ends at:

- Gmsh: a unit cube with a ball of radius 0.25 inside (two volumes), h = 0.08, no
  optimizer, 3D algorithms Delaunay, Frontal and HXT; MSH 2.2 and 4.1, ASCII and binary,
  with and without physical groups;
- TetGen (``tetgenpy``, AGPL: experiments only): a ``pyvista`` sphere surface (24 x 24)
  with ``-p`` (no interior point), ``-pY``, ``-pq``, ``-pqY``, ``-pq1.2a``, ``-pq1.1/15``
  and the output switches ``-f`` (every face in the .face file), ``-nn``, ``-z``
  (numbered from 0) and ``-fB`` (no markers).

    python experiments/input_variants.py --out /tmp/variants    # prints a markdown table

Results: ``experiments/results/input_variants.md``.
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path

import numpy as np

import jtet

GMSH_ALGORITHMS = {"Delaunay": 1, "Frontal": 4, "HXT": 10}
TETGEN_SWITCHES = (
    "pQ",
    "pYQ",
    "pqQ",
    "pqYQ",
    "pq1.2a0.002Q",
    "pq1.1/15Q",
    "pqfQ",
    "pqnnQ",
    "pqzQ",
    "pqfBQ",
)


def gmsh_files(out: Path) -> list[tuple[str, Path]]:
    """(label, path) of the Gmsh variants, written into ``out``."""
    import gmsh

    files = []
    variants = itertools.product(GMSH_ALGORITHMS.items(), (2.2, 4.1), (0, 1), (0, 1))
    for (name, algorithm), version, binary, groups in variants:
        label = f"Gmsh {name}, MSH {version} {'binary' if binary else 'ASCII'}" + (
            ", physical groups" if groups else ""
        )
        path = out / f"gmsh_{name}_{version}_{binary}_{groups}.msh"
        gmsh.initialize()
        try:
            gmsh.option.setNumber("General.Terminal", 0)
            occ = gmsh.model.occ
            occ.fragment(
                [(3, occ.addBox(0, 0, 0, 1, 1, 1))], [(3, occ.addSphere(0.5, 0.5, 0.5, 0.25))]
            )
            occ.synchronize()
            for option, value in (
                ("Mesh.MeshSizeMax", 0.08),
                ("Mesh.Algorithm3D", algorithm),
                ("Mesh.Optimize", 0),
                ("Mesh.MshFileVersion", version),
                ("Mesh.Binary", binary),
            ):
                gmsh.option.setNumber(option, value)
            if groups:
                for i, (_, tag) in enumerate(gmsh.model.getEntities(3)):
                    gmsh.model.addPhysicalGroup(3, [tag], 10 + i, name=f"volume{i}")
                walls = [tag for _, tag in gmsh.model.getEntities(2)]
                gmsh.model.addPhysicalGroup(2, walls, 100, name="surfaces")
            gmsh.model.mesh.generate(3)
            gmsh.write(str(path))
        finally:
            gmsh.finalize()
        files.append((label, path))
    return files


def tetgen_files(out: Path) -> list[tuple[str, Path]]:
    """(label, path of the .ele) of the TetGen variants, written into ``out``."""
    import pyvista as pv
    import tetgenpy

    sphere = pv.Sphere(radius=1.0, theta_resolution=24, phi_resolution=24).triangulate().clean()
    points = np.asarray(sphere.points, np.float64)
    triangles = sphere.faces.reshape(-1, 4)[:, 1:].tolist()
    files = []
    for switches in TETGEN_SWITCHES:
        plc = tetgenpy.TetgenIO()
        plc.setup_plc(points, triangles)
        mesh = tetgenpy.tetrahedralize(switches, plc)
        base = out / ("tetgen_" + switches.replace("/", "_").replace(".", "p"))
        mesh.save_nodes(str(base))
        mesh.save_elements(str(base))
        mesh.save_faces(str(base))
        files.append((f"TetGen -{switches.removesuffix('Q')}", base.with_suffix(".ele")))
    return files


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="directory for the input files")
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    files = gmsh_files(args.out) + tetgen_files(args.out)
    jtet.improve(jtet.load(files[0][1]), max_passes=1, perturb=0)  # compile / load kernels
    print(
        "| input | tets | protected faces | before (min / max) | after the climb (min) "
        "| after (min / max) | rounds kept / tried | s | notes |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for label, path in files:
        mesh = jtet.load(path)
        t0 = time.perf_counter()
        result = jtet.improve(mesh)
        seconds = time.perf_counter() - t0
        b, a, history = result.stats_before, result.stats_after, result.history
        kicks = [e for e in history if e["op"] == "perturb"]
        climb = history[: len(history) - len(kicks)] or [{"min_dihedral": b.min_dihedral}]
        kept = sum(e["successes"] > 0 for e in kicks)
        print(
            f"| {label} | {mesh.n_tets} | {len(mesh.protected_faces)} | "
            f"{b.min_dihedral:.2f} / {b.max_dihedral:.2f} | {climb[-1]['min_dihedral']:.2f} | "
            f"{a.min_dihedral:.2f} / {a.max_dihedral:.2f} | {kept} / {len(kicks)} | "
            f"{seconds:.1f} | {len(result.notes)} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
