"""Side-by-side comparison of jtet with the optimizers users would pick instead.

    python experiments/peers.py --meshes cube sphere two_regions --out experiments/results/peers

On the same input meshes (``configs/mesh/<name>.yaml`` generators, or ``file:PATH``), runs

- ``jtet``: ``jtet.improve`` with ``--ops`` (default edge,face,smooth);
- ``gmsh``: Gmsh's own optimizer, ``gmsh.model.mesh.optimize("", force=True)``;
- ``netgen``: Gmsh's Netgen optimizer, ``gmsh.model.mesh.optimize("Netgen", force=True)``;
- ``mmg3d``: ``mmg3d -optim -nosurf`` (the binary shipped by the ``pymmg`` package);
- ``tetgen``: TetGen's optimizer on the reconstructed input (``tetgenpy``: ``-r``
  reconstruct, ``-q100/0`` so that no point is inserted, ``-O10/7`` all optimization
  schemes at the highest level, ``-o/140`` target max dihedral angle);

and scores every output with jtet's own statistics (``jtet.stats``): worst / max dihedral
angle, tets whose smallest dihedral angle is below 10 / 20 / 30 degrees, time, whether
the boundary and region interfaces were preserved (``same faces``: identical triangles;
``same surface``: other triangles covering the same surface, e.g. flipped coplanar
faces; ``changed``), and validity (``mesh.is_valid()``). Writes ``<out>.csv`` and
``<out>.md`` (the command line at the top).

The Gmsh and Netgen optimizers run on a discrete Gmsh model built from the mesh: one
discrete surface per boundary / interface patch (its nodes classified on it, so they
never move) and one discrete volume per region. Every peer is optional: a tool whose
package is missing is reported as such, never an error. TetGen (AGPL) and the others
are experiment-only dependencies; jtet never imports them.
"""

from __future__ import annotations

import argparse
import importlib.util
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import meshgen  # noqa: E402

import jtet  # noqa: E402

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
TETGEN_SWITCHES = "rQq100/0O10/7o/140"
MMG_ARGS = ("-optim", "-nosurf")


# ---------------------------------------------------------------------------------------
# boundary and interface faces


def surface_faces(mesh: jtet.TetMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The boundary and region-interface triangles of ``mesh``.

    Returns ``faces`` (k, 3) int64 oriented outward from region ``inside`` (k,), and
    ``outside`` (k,): the region on the other side (-1 for the exterior boundary). Each
    interface triangle appears once (from its lower-labelled region).
    """
    tets, region = mesh.tets, mesh.region
    # outward faces of a positively oriented tet (p0, p1, p2, p3)
    f = np.concatenate(
        [tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]]
    )
    reg = np.tile(region, 4)
    _, inv, cnt = np.unique(np.sort(f, axis=1), axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    order = np.argsort(inv, kind="stable")
    pair = order[(cnt[inv] == 2)[order]].reshape(-1, 2)  # the two sides of interior faces
    other = np.full(len(f), -1, np.int64)
    other[pair[:, 0]] = reg[pair[:, 1]]
    other[pair[:, 1]] = reg[pair[:, 0]]
    keep = (cnt[inv] == 1) | ((other >= 0) & (reg < other))
    return f[keep], reg[keep], other[keep]


def _region_volumes(mesh: jtet.TetMesh) -> dict[int, float]:
    labels, inv = np.unique(mesh.region, return_inverse=True)
    return dict(zip(labels.tolist(), np.bincount(inv, weights=mesh.volumes).tolist(), strict=True))


def boundary_status(before: jtet.TetMesh, after: jtet.TetMesh, rtol: float = 1e-9) -> str:
    """Did ``after`` keep the boundary and interfaces of ``before``?

    ``"same faces"``: the same triangles (vertices matched by position, to 1e-12 of the
    mesh size); ``"same surface"``: other
    triangles, but every vertex of them lies on the old surface, the surface areas and
    every region's volume are unchanged (flips of coplanar faces); ``"changed"``
    otherwise.
    """
    from scipy.spatial import cKDTree

    fb, _, ob = surface_faces(before)
    fa, _, oa = surface_faces(after)
    scale = float(np.ptp(before.points, axis=0).max())
    # match vertices by position: tools that write text files round coordinates by an ulp
    vb, va = np.unique(fb), np.unique(fa)
    dist, nearest = cKDTree(before.points[vb]).query(after.points[va])
    if len(fa) == len(fb) and dist.max() <= 1e-12 * scale:
        to_before = np.full(after.n_points, -1, np.int64)
        to_before[va] = vb[nearest]
        a = np.unique(np.sort(to_before[fa], axis=1), axis=0)
        b = np.unique(np.sort(fb, axis=1), axis=0)
        if a.shape == b.shape and np.array_equal(a, b):
            return "same faces"
    volb, vola = _region_volumes(before), _region_volumes(after)
    if volb.keys() != vola.keys() or any(
        abs(volb[r] - vola[r]) > rtol * max(abs(volb[r]), scale**3) for r in volb
    ):
        return "changed"

    def areas(points, faces, other):
        p = points[faces]
        a = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        return a[other < 0].sum(), a[other >= 0].sum()

    if not np.allclose(areas(before.points, fb, ob), areas(after.points, fa, oa), rtol=rtol):
        return "changed"
    import pyvista as pv

    cells = np.hstack([np.full((len(fb), 1), 3), fb]).reshape(-1)
    old = pv.PolyData(before.points, cells)
    verts = after.points[np.unique(fa)]
    _, closest = old.find_closest_cell(verts, return_closest_point=True)
    if np.linalg.norm(verts - closest, axis=1).max() > 1e-9 * scale:
        return "changed"
    return "same surface"


# ---------------------------------------------------------------------------------------
# the tools


@dataclass
class Outcome:
    """What a tool produced: a mesh (None if it failed) and the wall time it took."""

    mesh: jtet.TetMesh | None
    seconds: float
    note: str = ""


def run_jtet(mesh: jtet.TetMesh, ops: tuple[str, ...]) -> Outcome:
    result = jtet.improve(mesh, ops=ops)
    return Outcome(result.mesh, result.seconds, f"{result.status}, {len(result.history)} steps")


def _gmsh_model(mesh: jtet.TetMesh) -> dict[int, int]:
    """Load ``mesh`` into a fresh Gmsh model as discrete entities; returns region -> volume tag.

    Boundary / interface nodes are classified on discrete surfaces (one per pair of
    regions), so Gmsh's and Netgen's volume optimizers keep them fixed.
    """
    import gmsh

    gmsh.model.add("peer")
    faces, inside, outside = surface_faces(mesh)
    patches = sorted(set(zip(inside.tolist(), outside.tolist(), strict=True)))
    surf = {p: gmsh.model.addDiscreteEntity(2) for p in patches}
    volume = {}
    for r in np.unique(mesh.region).tolist():
        bounding = [s for (a, b), s in surf.items() if r in (a, b)]
        volume[r] = gmsh.model.addDiscreteEntity(3, -1, bounding)
    placed = np.zeros(mesh.n_points, bool)
    for (a, b), s in surf.items():
        sel = faces[(inside == a) & (outside == b)]
        nodes = np.unique(sel)
        nodes = nodes[~placed[nodes]]
        placed[nodes] = True
        gmsh.model.mesh.addNodes(2, s, nodes + 1, mesh.points[nodes].reshape(-1))
        gmsh.model.mesh.addElementsByType(s, 2, [], (sel + 1).reshape(-1))
    for r, v in volume.items():
        tets = mesh.tets[mesh.region == r]
        nodes = np.unique(tets)
        nodes = nodes[~placed[nodes]]
        placed[nodes] = True
        gmsh.model.mesh.addNodes(3, v, nodes + 1, mesh.points[nodes].reshape(-1))
        gmsh.model.mesh.addElementsByType(v, 4, [], (tets + 1).reshape(-1))
    return volume


def _gmsh_extract(volume: dict[int, int], skip: dict[int, int]) -> jtet.TetMesh:
    """The tets of the model's volumes, dropping the first ``skip[region]`` of each."""
    import gmsh

    tags, coords, _ = gmsh.model.mesh.getNodes()
    coords = np.asarray(coords, np.float64).reshape(-1, 3)
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    blocks, labels = [], []
    for r, v in volume.items():
        _, _, nodes = gmsh.model.mesh.getElements(3, v)
        tets = index[np.concatenate([np.asarray(n, np.int64) for n in nodes]).reshape(-1, 4)]
        tets = tets[skip.get(r, 0) :]
        blocks.append(tets)
        labels.append(np.full(len(tets), r, np.int64))
    tets = np.concatenate(blocks)
    used, tets = np.unique(tets, return_inverse=True)
    return jtet.TetMesh.from_arrays(coords[used], tets.reshape(-1, 4), np.concatenate(labels))


def run_gmsh(mesh: jtet.TetMesh, method: str) -> Outcome:
    import gmsh

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        volume = _gmsh_model(mesh)
        t0 = time.perf_counter()
        gmsh.model.mesh.optimize(method, force=True)
        seconds = time.perf_counter() - t0
        # Gmsh's Netgen bridge does not delete the old tets of a *discrete* volume (its
        # de-meshing skips discrete entities): it appends the optimized ones after them
        skip = {}
        if method == "Netgen":
            skip = {r: int((mesh.region == r).sum()) for r in volume}
        return Outcome(_gmsh_extract(volume, skip), seconds)
    finally:
        gmsh.finalize()


def mmg3d_binary() -> str | None:
    """Path of the mmg3d executable: the one in the ``pymmg`` package, else on PATH."""
    spec = importlib.util.find_spec("mmg3d")  # pymmg installs top-level module "mmg3d"
    if spec is not None and spec.origin:
        exe = Path(spec.origin).parent / "mmg3d_O3"
        if exe.is_file():
            return str(exe)
    return shutil.which("mmg3d_O3") or shutil.which("mmg3d")


def run_mmg3d(mesh: jtet.TetMesh, args: tuple[str, ...] = MMG_ARGS) -> Outcome:
    import meshio

    exe = mmg3d_binary()
    if exe is None:
        return Outcome(None, float("nan"), "mmg3d not found (pip install pymmg)")
    faces, inside, outside = surface_faces(mesh)
    # one reference per boundary / interface patch, so MMG keeps them as separate surfaces
    _, patch = np.unique(np.stack([inside, outside], axis=1), axis=0, return_inverse=True)
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.mesh", Path(tmp) / "out.mesh"
        m = meshio.Mesh(
            mesh.points,
            [("triangle", faces), ("tetra", mesh.tets)],
            cell_data={"medit:ref": [patch.reshape(-1) + 1, mesh.region]},
        )
        meshio.write(src, m, file_format="medit")
        t0 = time.perf_counter()
        proc = subprocess.run(
            [exe, *args, "-v", "-1", "-in", str(src), "-out", str(dst)],
            capture_output=True,
            text=True,
            timeout=1800,
        )
        seconds = time.perf_counter() - t0
        if proc.returncode != 0 or not dst.exists():
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
            return Outcome(None, seconds, f"mmg3d failed: {tail[0]}")
        out = meshio.read(dst, file_format="medit")
    tets = np.concatenate([c.data for c in out.cells if c.type == "tetra"])
    region = np.concatenate(
        [r for c, r in zip(out.cells, out.cell_data["medit:ref"], strict=True) if c.type == "tetra"]
    )
    used, tets = np.unique(tets, return_inverse=True)
    return Outcome(
        jtet.TetMesh.from_arrays(out.points[used], tets.reshape(-1, 4), region.astype(np.int64)),
        seconds,
    )


def run_tetgen(mesh: jtet.TetMesh, switches: str = TETGEN_SWITCHES) -> Outcome:
    try:
        import tetgenpy
    except ImportError:
        return Outcome(None, float("nan"), "tetgenpy not installed")
    faces, inside, outside = surface_faces(mesh)
    _, patch = np.unique(np.stack([inside, outside], axis=1), axis=0, return_inverse=True)
    tio = tetgenpy.TetgenIO()
    tio.setup_tetmesh(
        mesh.points,
        mesh.tets.astype(np.int32),
        tetrahedron_attributes=mesh.region.astype(np.float64)[:, None],
        trifaces=faces.astype(np.int32),
        triface_markers=(patch.reshape(-1, 1) + 1).astype(np.int32),
    )
    t0 = time.perf_counter()
    out = tetgenpy.tetrahedralize(switches, tio)
    seconds = time.perf_counter() - t0
    points = np.asarray(out.points(), np.float64)
    tets = np.asarray(out.tetrahedra(), np.int64)
    attr = np.asarray(out.tetrahedronattributes())
    region = attr[:, 0].astype(np.int64) if attr.size else None
    used, tets = np.unique(tets, return_inverse=True)
    return Outcome(jtet.TetMesh.from_arrays(points[used], tets.reshape(-1, 4), region), seconds)


def tools(
    ops: tuple[str, ...], tetgen_switches: str
) -> dict[str, Callable[[jtet.TetMesh], Outcome]]:
    return {
        "jtet": lambda m: run_jtet(m, ops),
        "gmsh": lambda m: run_gmsh(m, ""),
        "netgen": lambda m: run_gmsh(m, "Netgen"),
        "mmg3d": run_mmg3d,
        "tetgen": lambda m: run_tetgen(m, tetgen_switches),
    }


# ---------------------------------------------------------------------------------------
# meshes and the table


def load_mesh(name: str) -> jtet.TetMesh:
    """``file:PATH`` or a ``configs/mesh/<name>.yaml`` generator (same seeds as run.py)."""
    if name.startswith("file:"):
        return jtet.load(name[5:])
    from omegaconf import OmegaConf

    path = CONFIGS / "mesh" / f"{name}.yaml"
    if not path.exists():
        names = sorted(p.stem for p in (CONFIGS / "mesh").glob("*.yaml"))
        raise SystemExit(f"peers: unknown mesh {name!r}; choose from {names} or file:PATH")
    cfg = OmegaConf.load(path)
    return meshgen.generate(cfg.generator, OmegaConf.to_container(cfg.params, resolve=True))


def score(mesh_name: str, tool: str, before: jtet.TetMesh, out: Outcome) -> dict:
    row = {"mesh": mesh_name, "tool": tool}
    if out.mesh is None:
        return row | {"seconds": out.seconds, "boundary": "-", "valid": False, "note": out.note}
    s = jtet.stats(out.mesh)
    return row | {
        "tets": s.n_tets,
        "points": s.n_points,
        "min_dihedral": s.min_dihedral,
        "max_dihedral": s.max_dihedral,
        "below_10": s.small_dihedral[10],
        "below_20": s.small_dihedral[20],
        "below_30": s.small_dihedral[30],
        "worst_min_sine": s.quality_min["min_sine"],
        "seconds": out.seconds,
        "boundary": "input" if tool == "input" else boundary_status(before, out.mesh),
        "valid": bool(out.mesh.is_valid().ok),
        "note": out.note,
    }


def markdown(rows: list[dict], header: list[str]) -> str:
    cols = [
        ("mesh", "mesh", "{}"),
        ("tool", "tool", "{}"),
        ("tets", "tets", "{:d}"),
        ("worst dihedral", "min_dihedral", "{:.2f}"),
        ("max dihedral", "max_dihedral", "{:.2f}"),
        ("< 10", "below_10", "{:d}"),
        ("< 20", "below_20", "{:d}"),
        ("< 30", "below_30", "{:d}"),
        ("seconds", "seconds", "{:.2f}"),
        ("boundary", "boundary", "{}"),
        ("valid", "valid", "{}"),
    ]
    lines = [*header, "", "| " + " | ".join(c[0] for c in cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        for _, key, fmt in cols:
            v = r.get(key)
            ok = v is not None and not (isinstance(v, float) and np.isnan(v))
            cells.append(fmt.format(int(v) if fmt == "{:d}" else v) if ok else "-")
        lines.append("| " + " | ".join(cells) + " |")
    notes = [f"- {r['mesh']} / {r['tool']}: {r['note']}" for r in rows if r.get("note")]
    return "\n".join(lines + ([""] + notes if notes else [])) + "\n"


def _revision() -> str:
    """The git revision of the checkout (``-dirty`` with uncommitted changes), or "?"."""
    try:
        out = subprocess.run(
            ["git", "describe", "--always", "--dirty"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=30,
        )
    except OSError:
        return "?"
    return out.stdout.strip() or "?"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["cube", "sphere", "two_regions"])
    ap.add_argument("--tools", default="jtet,gmsh,netgen,mmg3d,tetgen")
    ap.add_argument("--ops", default="edge,face,smooth", help="jtet operations")
    ap.add_argument("--tetgen-switches", default=TETGEN_SWITCHES)
    ap.add_argument(
        "--warmup",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="compile jtet's kernels on each mesh once before timing it",
    )
    ap.add_argument(
        "--out",
        type=Path,
        default=Path("experiments/results/peers"),
        help="output prefix: writes OUT.csv and OUT.md",
    )
    args = ap.parse_args(argv)
    ops = tuple(o for o in args.ops.split(",") if o)
    table = tools(ops, args.tetgen_switches)
    chosen = [t.strip() for t in args.tools.split(",") if t.strip()]
    unknown = [t for t in chosen if t not in table]
    if unknown:
        raise SystemExit(f"peers: unknown tool(s) {unknown}; choose from {list(table)}")
    rows = []
    for name in args.meshes:
        mesh = load_mesh(name)
        print(f"{name}: {mesh.n_tets} tets", flush=True)
        rows.append(score(name, "input", mesh, Outcome(mesh, float("nan"))))
        for tool in chosen:
            try:
                if tool == "jtet" and args.warmup:
                    jtet.improve(mesh, ops=ops, max_passes=1)  # JIT compilation, not timed
                out = table[tool](mesh)
            except Exception as e:  # a peer that crashes is a row, not the end of the table
                out = Outcome(None, float("nan"), f"failed: {type(e).__name__}: {e}")
            rows.append(score(name, tool, mesh, out))
            r = rows[-1]
            print(
                f"  {tool:7s} {r.get('min_dihedral', float('nan')):6.2f} / "
                f"{r.get('max_dihedral', float('nan')):6.2f} deg  {r['seconds']:7.2f} s  "
                f"{r['boundary']}  valid={r['valid']}  {r.get('note', '')}",
                flush=True,
            )
    import pandas as pd

    args.out.parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(rows).to_csv(args.out.with_suffix(".csv"), index=False)
    command = "python experiments/peers.py " + " ".join(
        shlex.quote(a) for a in (argv or sys.argv[1:])
    )
    header = [
        "# jtet vs. other tetrahedral mesh optimizers",
        "",
        "Made by:",
        "",
        f"    {command}",
        "",
        f"jtet ops: {','.join(ops)} (jtet {jtet.__version__} at {_revision()}, defaults "
        "otherwise); Gmsh "
        f'`optimize("")` and `optimize("Netgen")` on the loaded mesh (boundary fixed); '
        f"MMG3D `{' '.join(MMG_ARGS)}`; TetGen (tetgenpy) `-{args.tetgen_switches}`. All "
        "scores by `jtet.stats`: dihedral angles in degrees; `< 10` etc. count tets whose "
        "smallest dihedral angle is below that; seconds are the wall time of the "
        "optimization alone"
        + (
            " (jtet: after an untimed one-pass JIT warm-up on the same mesh)."
            if args.warmup
            else "."
        ),
    ]
    args.out.with_suffix(".md").write_text(markdown(rows, header))
    print(f"wrote {args.out.with_suffix('.csv')} and {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
