"""MEDCoupling (Salome's MED library) checks jtet's .med output against its input.

Gmsh meshes a ball inside a box (physical volumes ``ball`` and ``box``, the box's six
walls the physical surface ``walls``, the ball's surface ``sphere``) and writes it as a
MED file through the MED library. jtet loads it, gives it a nodal field f = 1 + 2x - y
+ 3z, improves it and writes the result as MED. MEDCoupling then reads both files and
measures, per group: the volume (signed: a negative one would be a tet in the wrong MED
order) or the area, whether every triangle of a face group is a face of the tets, and
the integral of f, which linear interpolation carries exactly (f is linear), so it
must be the same on both meshes. medcoupling is in the experiments extra (LGPL), never
a jtet dependency.

    python experiments/medcoupling_med.py
    python experiments/medcoupling_med.py --h 0.05 --seed 1
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import jtet
from jtet._report import quality_cell_data  # the per-tet arrays jtet improve writes

sys.path.insert(0, str(Path(__file__).parent))
from meshgen import gmsh_ball_in_box  # noqa: E402


def write_gmsh_med(path: Path, h: float) -> None:
    """Write Gmsh's mesh of a ball in a box, with its four physical groups, to ``path``."""
    import gmsh

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        inner, outer = gmsh_ball_in_box(0.25)
        gmsh.model.addPhysicalGroup(3, [inner], 1, "ball")
        gmsh.model.addPhysicalGroup(3, [outer], 2, "box")
        sphere = [t for _, t in gmsh.model.getBoundary([(3, inner)], oriented=False)]
        walls = [
            t for _, t in gmsh.model.getBoundary([(3, outer)], oriented=False) if t not in sphere
        ]
        gmsh.model.addPhysicalGroup(2, walls, 10, "walls")
        gmsh.model.addPhysicalGroup(2, sphere, 11, "sphere")
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()


def measure(path: Path) -> dict:
    """{(group, level): (size, volume or area, min signed volume or nan, faces of the
    tets?, integral of the field "f")} of a MED file, by MEDCoupling."""
    import medcoupling as mc

    mm = mc.MEDFileUMesh.New(str(path))
    vol = mm.getMeshAtLevel(0)
    faces_of_tets = vol.buildDescendingConnectivity()[0]
    field = mc.MEDFileField1TS.New(str(path), "f").field(mm) if "f" in _fields(path) else None
    out = {}
    for level in (0, -1):
        for name in mm.getGroupsOnSpecifiedLev(level):
            part = mm.getGroup(level, name)
            measures = part.getMeasureField(False).getArray().toNumPyArray()
            included = True
            integral = np.nan
            if level == -1:
                included, _ = faces_of_tets.areCellsIncludedIn(part, 2)
            elif field is not None:
                ids = mm.getGroupArr(0, name)
                integral = field.buildSubPart(ids).integral(0, False)
            smallest = float(measures.min()) if level == 0 else np.nan
            out[(name, level)] = (
                len(measures),
                float(measures.sum()),
                smallest,
                bool(included),
                integral,
            )
    return out


def _fields(path: Path) -> tuple:
    import medcoupling as mc

    return tuple(mc.MEDFileFields.New(str(path)).getFieldsNames())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=0.08, help="Gmsh's largest mesh size")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="jtet-med-"))
    src, mid, out = work / "gmsh.med", work / "with_f.med", work / "improved.med"
    write_gmsh_med(src, args.h)
    mesh = jtet.load(src)
    x, y, z = mesh.points.T
    mesh = mesh.replace(point_data={"f": 1 + 2 * x - y + 3 * z})
    jtet.save(mesh, mid)
    t = time.perf_counter()
    result = jtet.improve(mesh, seed=args.seed)
    seconds = time.perf_counter() - t
    jtet.save(result.mesh, out, cell_data=quality_cell_data(result.mesh))
    before, after = measure(mid), measure(out)
    s0, s1 = result.stats_before, result.stats_after
    print(
        f"Gmsh ball in box, h = {args.h}: {mesh.n_tets} -> {result.mesh.n_tets} tets, "
        f"min / max dihedral {s0.min_dihedral:.2f} / {s0.max_dihedral:.2f} -> "
        f"{s1.min_dihedral:.2f} / {s1.max_dihedral:.2f} deg in {seconds:.1f} s\n"
    )
    print(
        "| group | cells in / out | volume or area in | out | rel. diff | min signed volume out | faces of the tets | integral of f in | out |"
    )
    print("|---|---|---|---|---|---|---|---|---|")  # fmt: skip
    worst = 0.0
    for key in sorted(before, key=lambda k: (-k[1], k[0])):
        n0, m0, _, _, i0 = before[key]
        n1, m1, v1, inc1, i1 = after[key]
        rel = abs(m1 - m0) / m0
        worst = max(worst, rel, 0.0 if np.isnan(i0) else abs(i1 - i0) / abs(i0))
        lo = "" if np.isnan(v1) else f"{v1:.3e}"
        ints = ("", "") if np.isnan(i0) else (f"{i0:.15f}", f"{i1:.15f}")
        print(
            f"| {key[0]} | {n0} / {n1} | {m0:.15f} | {m1:.15f} | {rel:.1e} | {lo} | "
            f"{inc1} | {ints[0]} | {ints[1]} |"
        )
    print(f"\nlargest relative difference: {worst:.1e} (files in {work})")
    return 0 if worst < 1e-12 else 1


if __name__ == "__main__":
    raise SystemExit(main())
