"""Benchmark: from-scratch Topology.build vs the incremental update after a flip step.

For each mesh, runs one edge-removal and one multi-face pass (the first steps of an
optimization change most of an unoptimized mesh, so the update falls back to a full
build there), then times a second real edge-removal step and a second real multi-face
step: ``Topology.build(new)`` against ``update_topology(old.topology, old, new, keep)``,
both in this process, best of ``--repeat``. Prints a markdown table.

    python experiments/bench_topology.py                      # demo, holeplate, cube 182k
    python experiments/bench_topology.py --meshes gmsh:cube:0.018 --out results/x.md
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_improve import load_mesh  # noqa: E402

from jtet._edge_removal import edge_removal_pass  # noqa: E402
from jtet._multiface import multiface_removal_pass  # noqa: E402
from jtet._topology import Topology  # noqa: E402
from jtet._topology_update import _update, update_topology  # noqa: E402

PASSES = {"edge": edge_removal_pass, "face": multiface_removal_pass}


def best_of(fn, repeat: int) -> tuple[float, object]:
    """(minimum wall time over ``repeat`` calls, last result)."""
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def bench_step(mesh, name: str, repeat: int):
    """One real step of pass ``name`` on ``mesh``: (row dict or None, the new mesh)."""
    out, _, keep = PASSES[name](mesh)
    if keep is None:
        return None, mesh
    old = mesh.topology
    t_build, want = best_of(lambda: Topology.build(out), repeat)
    t_upd, got = best_of(lambda: update_topology(old, mesh, out, keep), repeat)
    # the incremental path itself, even above the size threshold (for the record)
    t_inc, inc = best_of(lambda: _update(old, mesh, out, keep, 0.0), repeat)
    same = all(np.array_equal(getattr(inc, f), getattr(want, f)) for f in want.__dataclass_fields__)
    changed = int((~keep).sum() + out.n_tets - keep.sum())
    row = dict(
        step=name,
        tets=out.n_tets,
        changed=f"{changed} ({100 * changed / mesh.n_tets:.1f} %)",
        build=t_build,
        update=t_upd,
        incremental=t_inc,
        ratio=t_build / t_inc,
        same=same and got is not None,
    )
    return row, out


def bench_mesh(name: str, repeat: int) -> list[dict]:
    mesh = load_mesh(name)
    for p in ("edge", "face"):  # first steps: large changes (full build territory)
        _, mesh = bench_step(mesh, p, 1)
    rows = []
    for p in ("edge", "face"):
        row, mesh = bench_step(mesh, p, repeat)
        if row is not None:
            rows.append(dict(mesh=name, **row))
    return rows


def table(rows: list[dict]) -> str:
    lines = [
        "| mesh | step | tets | tets changed | build (s) | update (s) | incremental only (s) "
        "| build / incremental | identical |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['mesh']} | {r['step']} | {r['tets']} | {r['changed']} | {r['build']:.3f} "
            f"| {r['update']:.3f} | {r['incremental']:.3f} | {r['ratio']:.1f}x | {r['same']} |"
        )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", default="demo,gmsh_holeplate,gmsh:cube:0.03")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None, help="also write the table to this file")
    args = ap.parse_args(argv)
    rows = []
    for name in args.meshes.split(","):
        rows += bench_mesh(name, args.repeat)
        print(table(rows[-2:]).splitlines()[-1] if rows else "", file=sys.stderr, flush=True)
    text = table(rows)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
