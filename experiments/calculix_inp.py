"""CalculiX solves on jtet's .inp output: the surfaces carry the loads they should.

For each mesh (a unit cube: random Delaunay points with its faces, or a Gmsh reference
mesh scaled into one), jtet improves it and writes it as an Abaqus input file whose
protected faces are the cube's x = 0 and x = 1 faces (surfaces ``XMIN`` / ``XMAX`` with
their node sets). A CalculiX deck includes that file, fixes the nodes of one face (its
node set of the surface's own name, as in Gmsh's exports), puts
a pressure of 1 on the other (``*DSLOAD``) and prints the total reaction force: by
equilibrium it is the pressure times the area (1) along x, whichever of the element
faces S1-S4 the surface names. ``ccx`` (Debian's ``calculix-ccx``) must be on PATH; it
is never a jtet dependency.

    python experiments/calculix_inp.py
    python experiments/calculix_inp.py --meshes delaunay:2000,gmsh_cube
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import jtet

DECK = """*INCLUDE, INPUT={mesh}
*MATERIAL, NAME=STEEL
*ELASTIC
210000, 0.3
{sections}*STEP
*STATIC
*BOUNDARY
{fixed}, 1, 3, 0
*DSLOAD
{loaded}, P, 1.0
*NODE PRINT, NSET={fixed}_NODES, TOTALS=ONLY
RF
*END STEP
"""


def _mesh(name: str) -> jtet.TetMesh:
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_improve import load_mesh

    mesh = load_mesh(name)
    lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    mesh = mesh.replace(points=(mesh.points - lo) / (hi - lo))  # into the unit cube
    T = mesh.topology
    faces = T.faces[T.boundary_face]
    x = mesh.points[faces][:, :, 0]
    labels = np.where((x == 0).all(axis=1), 1, np.where((x == 1).all(axis=1), 2, 0))
    keep = labels > 0
    return mesh.replace(
        protected_faces=faces[keep],
        protected_face_labels=labels[keep],
        label_names={(2, 1): "XMIN", (2, 2): "XMAX"},
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", default="delaunay:400,gmsh_cube")
    args = ap.parse_args()
    if shutil.which("ccx") is None:
        sys.exit("ccx (CalculiX) is not on PATH: apt-get install calculix-ccx")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.meshes.split(","):
            mesh = jtet.improve(_mesh(name), perturb=0).mesh
            path = Path(tmp) / "mesh.inp"
            jtet.save(mesh, path)
            text = path.read_text()
            sides = sorted(set(re.findall(r"X(?:MIN|MAX)_S(\d)", text)))
            # one section on the set of every element, as cgx's and PrePoMax's decks do
            sections = "*SOLID SECTION, ELSET=Eall, MATERIAL=STEEL\n"
            for fixed, loaded, expected in (("XMIN", "XMAX", 1.0), ("XMAX", "XMIN", -1.0)):
                deck = Path(tmp) / "deck.inp"
                deck.write_text(
                    DECK.format(mesh=path.name, sections=sections, fixed=fixed, loaded=loaded)
                )
                t0 = time.perf_counter()
                run = subprocess.run(["ccx", "deck"], cwd=tmp, capture_output=True, text=True)
                seconds = time.perf_counter() - t0
                errors = [line for line in run.stdout.splitlines() if "ERROR" in line]
                total = (Path(tmp) / "deck.dat").read_text().strip().splitlines()[-1].split()
                force = np.array(total, float) if not errors else np.full(3, np.nan)
                rows.append(
                    (
                        name,
                        mesh.n_tets,
                        " ".join(sides),
                        loaded,
                        expected,
                        force,
                        len(errors),
                        seconds,
                    )  # fmt: skip
                )
    print(
        "| mesh | tets | faces used | loaded | expected fx | ccx fx, fy, fz | ccx errors | ccx s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, n, sides, loaded, expected, f, errors, s in rows:
        print(
            f"| {name} | {n} | S{sides.replace(' ', ', S')} | {loaded} | {expected:+.1f} | "
            f"{f[0]:+.9f}, {f[1]:+.1e}, {f[2]:+.1e} | {errors} | {s:.1f} |"
        )


if __name__ == "__main__":
    main()
