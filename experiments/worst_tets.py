"""Where the worst dihedral angle stops, and why: the worst tets after ``jtet.improve``.

For each mesh and boundary mode this runs ``jtet.improve`` (defaults otherwise) and lists
the tets with the smallest dihedral angle: the angle, the edge it sits at (the kinds of its
two end vertices: free, surface, segment, corner; whether it is a boundary edge or a
subsegment, and then the domain angle there, i.e. the sum of the ring's angles, split among
how many tets), and how many of the tet's four vertices may move. A tet whose four vertices
are all fixed can only change by a flip; an angle at a subsegment is a share of a fixed
domain angle (Theta over k tets), which only flips that change k can raise.

    python experiments/worst_tets.py                           # the four reference meshes
    python experiments/worst_tets.py --meshes gmsh:cube:0.03 --boundary fixed --worst 8

Mesh names as in bench_improve.py. Results: experiments/results/worst_tets.md.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from bench_improve import MESHES, load_mesh

import jtet
from jtet._quality import tet_dihedrals
from jtet._topology import FREE, TET_EDGES

KIND = "FSGC"  # vertex kinds FREE, SURFACE, SEGMENT, CORNER as one letter each


def edge_ids(topo, pairs: np.ndarray) -> np.ndarray:
    """(k,) ids in ``topo.edges`` of the vertex pairs (k, 2)."""
    from jtet._topology import match_rows

    return match_rows(topo.edges, np.sort(pairs, axis=1), int(topo.vertex_kind.shape[0]))


def ring_angle(mesh, angles: np.ndarray, edge: int) -> tuple[float, int]:
    """(sum of the dihedral angles at ``edge`` over its tets in degrees, number of tets)."""
    topo = mesh.topology
    ring = topo.edge_tets[topo.edge_tets_ptr[edge] : topo.edge_tets_ptr[edge + 1]]
    a, b = topo.edges[edge]
    t = mesh.tets[ring]
    # local edge index of (a, b) in each ring tet
    ia = np.argmax(t == a, axis=1)
    ib = np.argmax(t == b, axis=1)
    lo, hi = np.minimum(ia, ib), np.maximum(ia, ib)
    is_ab = (TET_EDGES[None, :, 0] == lo[:, None]) & (TET_EDGES[None, :, 1] == hi[:, None])
    which = np.argmax(is_ab, axis=1)
    return float(angles[ring, which].sum()), len(ring)


def report(mesh, worst: int, boundary: str) -> list[str]:
    """Lines describing the ``worst`` tets of ``mesh`` by smallest dihedral angle."""
    topo = mesh.topology
    angles, lo, _ = tet_dihedrals(mesh.points, mesh.tets)
    order = np.argsort(lo, kind="stable")[:worst]
    local = np.argmin(angles[order], axis=1)
    pairs = mesh.tets[order][np.arange(len(order))[:, None], TET_EDGES[local]]
    edges = edge_ids(topo, pairs)
    lines = []
    for i, t in enumerate(order):
        kinds = topo.vertex_kind[mesh.tets[t]]
        free = int((kinds == FREE).sum()) if boundary == "fixed" else 4
        e = int(edges[i])
        ends = "".join(KIND[k] for k in topo.vertex_kind[pairs[i]])
        where = "subsegment" if topo.subsegment[e] else "boundary" if topo.edge_boundary[e] else ""
        total, k = ring_angle(mesh, angles, e)
        lines.append(
            f"  {lo[t]:6.2f}  edge {ends:2s} {where:10s}  ring {total:6.1f} deg / {k} tets"
            f"  vertices {''.join(KIND[v] for v in kinds)}"
            + (f"  movable {free}" if boundary == "fixed" else "")
        )
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", default=",".join(MESHES))
    ap.add_argument("--boundary", default="fixed,slide", help="comma list of boundary modes")
    ap.add_argument("--worst", type=int, default=5, help="tets listed per run")
    args = ap.parse_args()
    for name in args.meshes.split(","):
        mesh = load_mesh(name)
        for boundary in args.boundary.split(","):
            t0 = time.perf_counter()
            res = jtet.improve(mesh, boundary=boundary)
            s = res.stats_after
            print(
                f"{name} ({mesh.n_tets} tets), boundary {boundary}: "
                f"{s.min_dihedral:.2f} / {s.max_dihedral:.2f} deg, {res.status}, "
                f"{time.perf_counter() - t0:.1f} s"
            )
            print("\n".join(report(res.mesh, args.worst, boundary)), flush=True)


if __name__ == "__main__":
    main()
