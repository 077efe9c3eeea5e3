"""A curved boundary through improve: Gmsh's second-order ball in a box, read with
``--linear``, improved, written back with ``--quadratic``, measured by Gmsh.

Gmsh meshes a ball (radius 0.25) inside the unit cube, makes the mesh quadratic
(``SetOrder 2``: the nodes of the sphere's edges on the sphere) and writes it as
``.msh``. jtet loads it with ``linear=True`` (the sphere's curved nodes kept as
``TetMesh.curved_edges``), improves it, and writes it with ``quadratic=True`` as
``.msh`` and ``.med``. Gmsh then opens each file and integrates its own Jacobian
determinants over the 10-node tets (4th-order Gauss rule, exact for their cubic
determinants): the volume of the ball against the sphere's 4/3 pi r^3; and Gmsh's
smallest scaled Jacobian (``minSJ``, <= 0 for a folded tet). jtet's nodal check counts
the tets whose determinant is not positive at one of their 10 nodes. Each h is improved
without the guard on curved tets and with it (``--floors``: ``min_scaled_jacobian``).
The second table times ``save`` of the improved mesh, linear and quadratic, in each
format that writes both (the sizes of all the files written), and ``load`` of the
quadratic file with ``linear=True``.

    python experiments/quadratic_ball.py                 # h = 0.08 and 0.04
    python experiments/quadratic_ball.py --h 0.2 0.12 --timing-h 0 --floors none 0 0.3 0.5
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import jtet
from jtet._io import written_files
from jtet._quadratic import folded_tets, quadratic_mesh

sys.path.insert(0, str(Path(__file__).parent))
from meshgen import gmsh_ball_in_box  # noqa: E402

RADIUS = 0.25


def write_second_order(path: Path, h: float) -> None:
    """Gmsh's order-2 mesh of the ball (physical volume 1 "ball") in the box (2 "box")."""
    import gmsh

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        inner, outer = gmsh_ball_in_box(RADIUS)
        gmsh.model.addPhysicalGroup(3, [inner], 1, "ball")
        gmsh.model.addPhysicalGroup(3, [outer], 2, "box")
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.setOrder(2)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()


def gmsh_measures(path: Path) -> dict:
    """{physical volume name: (volume, smallest scaled Jacobian)} by Gmsh: the volume
    integrates Gmsh's Jacobian determinants (4th-order Gauss rule, exact for a 10-node
    tet's cubic determinant); the scaled Jacobian is Gmsh's ``minSJ`` element quality
    (its bound of det J over the element, scaled by the edges: <= 0 for a folded tet)."""
    import gmsh

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(path))
        out = {}
        for _, tag in gmsh.model.getPhysicalGroups(3):
            total, smallest = 0.0, np.inf
            for entity in gmsh.model.getEntitiesForPhysicalGroup(3, tag):
                kinds, elements, _ = gmsh.model.mesh.getElements(3, entity)
                for kind, ids in zip(kinds, elements, strict=True):
                    uvw, weights = gmsh.model.mesh.getIntegrationPoints(int(kind), "Gauss4")
                    _, det, _ = gmsh.model.mesh.getJacobians(int(kind), uvw, entity)
                    total += float((det.reshape(len(ids), -1) * weights).sum())
                    quality = gmsh.model.mesh.getElementQualities(ids, "minSJ")
                    smallest = min(smallest, float(np.min(quality)))
            out[gmsh.model.getPhysicalName(3, tag)] = (total, smallest)
        return out
    finally:
        gmsh.finalize()


def quiet(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args, **kwargs)


def _floor_text(floor: float | None) -> str:
    return "none" if floor is None else f"{floor:g}"


def geometry_rows(h: float, seed: int, floors: list[float | None], work: Path) -> list[str]:
    """Rows of the geometry table: the linear read, Gmsh's order-2 input, and jtet's
    improved mesh written quadratic for each guard floor (``min_scaled_jacobian``)."""
    src = work / f"gmsh_order2_{h}.msh"
    write_second_order(src, h)
    mesh = quiet(jtet.load, src, linear=True)
    sphere = 4 / 3 * np.pi * RADIUS**3
    ball_label = next(k for (d, k), v in mesh.label_names.items() if d == 3 and v == "ball")
    s0 = jtet.stats(mesh)
    angles = f"{s0.min_dihedral:.2f} / {s0.max_dihedral:.2f}"
    linear_ball = mesh.volumes[mesh.region == ball_label].sum()
    rows = [
        f"| {h} | jtet's linear read (corners) | {mesh.n_tets} | {angles} | "
        f"{(linear_ball - sphere) / sphere:+.2e} | | | |"
    ]
    files = [("Gmsh's order 2 (input)", src, mesh, angles, "")]
    for floor in floors:
        t = time.perf_counter()
        result = jtet.improve(mesh, seed=seed, min_scaled_jacobian=floor)
        seconds = time.perf_counter() - t
        s1 = result.stats_after
        angles = f"{s1.min_dihedral:.2f} / {s1.max_dihedral:.2f}"
        print(
            f"h = {h}, guard floor {_floor_text(floor)}: {mesh.n_tets} -> "
            f"{result.mesh.n_tets} tets, min / max dihedral {angles} in {seconds:.1f} s; "
            f"curved edges {len(mesh.curved_edges.edges)} -> "
            f"{len(result.mesh.curved_edges.edges)}"
        )
        for ext in ("msh", "med"):
            out = work / f"improved_{h}_{_floor_text(floor)}.{ext}"
            quiet(jtet.save, result.mesh, out, quadratic=True)
            what = f"jtet improve --quadratic, floor {_floor_text(floor)} (.{ext})"
            files.append((what, out, result.mesh, angles, f"{seconds:.1f}"))
    for what, path, linear, angles, seconds in files:
        measures = gmsh_measures(path)
        ball, sj_ball = measures["ball"]
        folded, _ = folded_tets(quadratic_mesh(linear))
        rows.append(
            f"| {h} | {what} | {linear.n_tets} | {angles} | {(ball - sphere) / sphere:+.2e} "
            f"| {min(sj_ball, measures['box'][1]):.3f} | {folded} | {seconds} |"
        )
    return rows


def timing_rows(h: float, seed: int, work: Path) -> list[str]:
    src = work / f"gmsh_order2_{h}.msh"
    write_second_order(src, h)
    t = time.perf_counter()
    mesh = quiet(jtet.load, src, linear=True)
    load_s = time.perf_counter() - t
    out = jtet.improve(mesh, seed=seed).mesh
    t = time.perf_counter()
    quad = quadratic_mesh(out)
    build_s = time.perf_counter() - t
    print(
        f"\ntiming mesh (h = {h}): {out.n_tets} tets, {out.n_points} points; read with "
        f"--linear in {load_s:.2f} s; quadratic cells built in {build_s:.2f} s "
        f"({len(quad.edges)} mid-edge nodes)"
    )
    rows = []
    for ext in ("vtu", "vtk", "msh", "inp", "med", "exo", "xdmf", "node", "vol", "mesh", "meshb"):
        times = []
        for quadratic in (False, True):
            path = work / f"timing_{'q' if quadratic else 'l'}.{ext}"
            t = time.perf_counter()
            quiet(jtet.save, out, path, quadratic=quadratic)
            size = sum(f.stat().st_size for f in written_files(path) if f.exists())
            times.append((time.perf_counter() - t, size / 1e6))
        t = time.perf_counter()
        back = quiet(jtet.load, path, linear=True)  # the quadratic file
        read_s = time.perf_counter() - t
        assert back.n_tets == out.n_tets
        (tl, sl), (tq, sq) = times
        rows.append(
            f"| .{ext} | {tl:.2f} | {tq:.2f} | {tq / tl:.1f} | {sl:.0f} | {sq:.0f} | {read_s:.2f} |"
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, nargs="+", default=[0.08, 0.04])
    ap.add_argument("--timing-h", type=float, default=0.02, help="0: no timing table")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--floors",
        nargs="+",
        default=["none", "0.3"],
        help="min_scaled_jacobian of the improve runs ('none': no guard; 0.3: the default)",
    )
    args = ap.parse_args(argv)
    floors = [None if f == "none" else float(f) for f in args.floors]
    work = Path(tempfile.mkdtemp(prefix="jtet-quadratic-"))
    rows = []
    for h in args.h:
        rows += geometry_rows(h, args.seed, floors, work)
    print(
        "\n| h | mesh | tets | min / max dihedral | ball volume vs sphere | smallest scaled "
        "Jacobian (Gmsh minSJ) | tets folded at a node (jtet) | improve (s) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    if args.timing_h:
        timing = timing_rows(args.timing_h, args.seed, work)
        print(
            "\n| format | save linear (s) | quadratic (s) | ratio | MB linear | quadratic "
            "| read quadratic with --linear (s) |"
        )
        print("|---|---|---|---|---|---|---|")
        print("\n".join(timing))
    print(f"\nfiles in {work}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
