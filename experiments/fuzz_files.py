"""Damaged-file fuzzing: jtet.load on mutated mesh files (and jtet.read_surface on mutated
surface files) must return a mesh or raise a JtetError, never another exception, a hang
or a crash.

    python experiments/fuzz_files.py --tries 300 --seed 0
    python experiments/fuzz_files.py --formats vtk,vtu --tries 2000
    python experiments/fuzz_files.py --quadratic --formats vtu,vtk,msh,inp,med

``--quadratic`` saves the mesh with 10-node tets (``save(..., quadratic=True)``, a
curved edge among them) and loads each try with ``linear=True``.

A small labelled mesh (regions, protected faces with labels, edges and vertices, node sets) is saved
in every format (its boundary as a surface in the surface formats); each try mutates one of its files (flips 1-3 bytes, truncates it,
deletes a line, or replaces a line's start with a bad number) and loads it. Each format
runs in a child process, so a reader that crashes the process (as VTK's did before its
reads moved to a forked child) is reported with its signal and the try that did it; the
mutated file is kept under --keep. Prints a table: tries, loaded, refused (JtetError),
other exceptions, crash.

Exit code: 0 when every try loaded or was refused with a JtetError.
"""

from __future__ import annotations

import argparse
import collections
import os
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path

# surface files (``jtet tetrahedralize``'s input) are read and checked, not loaded
SURFACES = ("stl", "obj", "ply", "off", "vtp")
FORMATS = (
    "vtu",
    "vtk",
    "msh",
    "mesh",
    "meshb",
    "node",
    "xdmf",
    "inp",
    "vol",
    "exo",
    "med",
    *SURFACES,
)
BAD_TOKENS = (b"-1", b"0", b"99999999", b"nan", b"1e308", b"abc", b"")


def _mesh():
    import numpy as np
    from scipy.spatial import Delaunay

    import jtet

    rng = np.random.default_rng(1)
    points = rng.random((30, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # qhull's vertex orders
        mesh = jtet.TetMesh.from_arrays(points, Delaunay(points).simplices)
    T = mesh.topology
    faces = np.sort(T.faces[T.boundary_face], axis=1)[:6]
    return mesh.replace(
        region=np.arange(mesh.n_tets) % 2,
        protected_faces=faces,
        protected_face_labels=np.arange(len(faces)) + 1,
        protected_edges=T.edges[~T.edge_boundary][:3],
        protected_vertices=[1, 5],
        label_names={(3, 1): "odd tets", (2, 1): "first face", (2, 2): "second"},
        periodic=[(2, (2, 1), None, np.unique(faces)[:4].reshape(-1, 2))],
        protected_tets=mesh.tets[:3],
        node_sets=[("probe", [2, 3]), ("tip", [3, 4], 9)],
        point_data={"T": points[:, 0], "u": points, "marker": np.arange(len(points)) % 3},
        cell_data={"material": np.arange(mesh.n_tets) % 3, "s": np.ones((mesh.n_tets, 2))},
    )


def _save_surface(mesh, path: Path) -> None:
    """The boundary of ``mesh`` as a surface file (OFF through meshio, the rest pyvista)."""
    import meshio
    import numpy as np
    import pyvista as pv

    T = mesh.topology
    faces = T.faces[T.boundary_face]
    if path.suffix == ".off":
        meshio.write(str(path), meshio.Mesh(mesh.points, [("triangle", faces)]))
        return
    cells = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
    pv.PolyData(np.asarray(mesh.points), cells).save(str(path))


def _read_surface(path: Path) -> None:
    import jtet
    from jtet._tetrahedralize import check_surface

    check_surface(*jtet.read_surface(path), str(path))


def _mutate(data: bytes, rng) -> bytes:
    data = bytearray(data)
    kind = rng.integers(4)
    if kind == 0:  # flip bytes
        for _ in range(rng.integers(1, 4)):
            data[rng.integers(len(data))] = rng.integers(256)
    elif kind == 1:  # cut short
        data = data[: rng.integers(len(data))]
    else:
        lines = bytes(data).split(b"\n")
        i = rng.integers(len(lines))
        if kind == 2:  # a line lost
            del lines[i]
        else:  # a line's start replaced by a bad number
            lines[i] = BAD_TOKENS[rng.integers(len(BAD_TOKENS))] + b" " + lines[i][-5:]
        data = bytearray(b"\n".join(lines))
    return bytes(data)


def run_format(fmt: str, tries: int, seed: int, keep: Path, quadratic: bool = False) -> dict:
    """Mutate and load one format's file ``tries`` times in this process (``quadratic``:
    a file of 10-node tets, loaded with ``linear=True``)."""
    import numpy as np

    import jtet

    rng = np.random.default_rng([seed, FORMATS.index(fmt)])
    work = Path(tempfile.mkdtemp(prefix=f"jtet-fuzz-{fmt}-"))
    warnings.simplefilter("ignore")
    src = work / f"src.{fmt}"
    if fmt in SURFACES:
        _save_surface(_mesh(), src)
        load = _read_surface
    else:
        mesh = _mesh()
        if quadratic:  # one edge's node off its midpoint
            a, b = mesh.tets[0, :2]
            bent = (mesh.points[a] + mesh.points[b]) / 2 + 0.01
            mesh = mesh.replace(curved_edges=([[a, b]], [bent]))
        jtet.save(mesh, src, quadratic=quadratic)

        def load(path):
            jtet.load(path, linear=quadratic).is_valid()

    # TetGen: the .node, the .ele and the .face of the protected faces; XDMF: the .xdmf
    # and its heavy data, the .h5 it names (renamed: the mutated copy's); Medit: the mesh
    # and the .sol of its point data
    names = {
        "node": ["src.node", "src.ele", "src.face"],
        "xdmf": ["src.xdmf", "src.h5"],
        "mesh": ["src.mesh", "src.sol"],
        "meshb": ["src.meshb", "src.sol"],
    }
    names = names.get(fmt, [f"src.{fmt}"])
    originals = {n: (work / n).read_bytes() for n in names}
    if fmt == "xdmf":
        originals["src.xdmf"] = originals["src.xdmf"].replace(b"src.h5:", b"mut.h5:")
    counts = collections.Counter()
    others = collections.Counter()
    for t in range(tries):
        target = names[rng.integers(len(names))]
        for n in names:
            data = _mutate(originals[n], rng) if n == target else originals[n]
            (work / n.replace("src", "mut")).write_bytes(data)
        # the try about to run, for the parent to report if this process dies
        for n in names:
            shutil.copy(work / n.replace("src", "mut"), keep / n.replace("src", "last"))
        try:
            load(work / f"mut.{fmt}")
            counts["loaded"] += 1
        except jtet.JtetError:
            counts["refused"] += 1
        except Exception as e:
            counts["other"] += 1
            where = traceback.extract_tb(e.__traceback__)[-1]
            others[f"{type(e).__name__} at {Path(where.filename).name}:{where.lineno}: {e}"] += 1
            for n in names:  # kept for a regression test
                shutil.copy(work / n.replace("src", "mut"), keep / n.replace("src", f"other{t}"))
    shutil.rmtree(work, ignore_errors=True)
    return {"counts": dict(counts), "others": dict(others)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tries", type=int, default=300, help="tries per format (default 300)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--formats", default=",".join(FORMATS), help="comma-separated")
    ap.add_argument("--keep", default="fuzz-files-last", help="directory for the last try")
    ap.add_argument(
        "--quadratic", action="store_true", help="10-node tets, loaded with linear=True"
    )
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    keep = Path(args.keep)
    keep.mkdir(parents=True, exist_ok=True)
    if args.child:
        import json

        print(json.dumps(run_format(args.child, args.tries, args.seed, keep, args.quadratic)))
        return 0

    import json

    rows, failed = [], False
    for fmt in args.formats.split(","):
        t0 = time.perf_counter()
        cmd = [sys.executable, __file__, "--child", fmt, "--tries", str(args.tries)]
        cmd += ["--seed", str(args.seed), "--keep", str(keep)]
        cmd += ["--quadratic"] if args.quadratic else []
        proc = subprocess.run(cmd, capture_output=True, text=True)
        seconds = time.perf_counter() - t0
        if proc.returncode == 0:
            out = json.loads(proc.stdout.strip().splitlines()[-1])
            c, crash = out["counts"], ""
            for what, n in out["others"].items():
                print(f"{fmt}: {n} x {what}")
        else:
            c = {}
            crash = f"exit {proc.returncode} (files in {keep}/last.*)"
        bad = bool(crash) or c.get("other", 0) > 0
        failed |= bad
        rows.append(
            (fmt, c.get("loaded", 0), c.get("refused", 0), c.get("other", 0), crash, seconds)
        )
    print(f"\n{'format':8} {'loaded':>7} {'refused':>8} {'other':>6} {'seconds':>8}  crash")
    for fmt, loaded, refused, other, crash, seconds in rows:
        print(f"{fmt:8} {loaded:7d} {refused:8d} {other:6d} {seconds:8.1f}  {crash}")
    return 1 if failed else 0


if __name__ == "__main__":
    os.environ.setdefault("JTET_HELPER", "0")
    sys.exit(main())
