"""One batched pass of optimal edge removal (Shewchuk, Section 2).

gather -> Klincsek kernels (one compiled kernel per polygon size) -> select -> apply.

Every candidate edge ab becomes one or two polygons ("chains") that Klincsek's dynamic
program triangulates:
- an interior edge: its closed ring v_1..v_m (final 3-2 flip);
- an edge on the exterior boundary whose two boundary faces are coplanar: the open chain
  from one boundary vertex to the other (final 2-2 flip);
- an edge on an interior bounding surface (region interface or user-protected faces):
  the ring split at the two subfacets into chains C1 and C2 (final 4-4 flip).
Subsegments are never candidates.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._apply import (
    FlipPlan,
    apply_plans,
    nonconforming_owners,
    recreating_owners,
    worse_orientation_owners,
)
from ._curved_guard import worse_owners
from ._kernels.klincsek import prefetch as prefetch_rings
from ._kernels.klincsek import solve_rings
from ._mesh import TetMesh
from ._select import select_conflict_free
from ._topology import csr_rows


@dataclass
class PassStats:
    """Counts of one pass of a topological operation."""

    op: str
    attempts: int = 0
    successes: int = 0
    by_size: dict = field(default_factory=dict)  # ring / tree size -> successes
    by_kind: dict = field(default_factory=dict)  # e.g. interior / boundary / surface -> successes
    overflow: int = 0  # candidates skipped because they exceed the configured capacity
    # (edge removal: rings / chains larger than max_ring)

    def as_dict(self) -> dict:
        return {
            "op": self.op,
            "attempts": self.attempts,
            "successes": self.successes,
            "by_size": {str(k): v for k, v in sorted(self.by_size.items())},
            "by_kind": dict(self.by_kind),
            "overflow": self.overflow,
        }


@dataclass
class _Chains:
    """Polygons to triangulate, flattened: chain c has vertices verts[ptr[c]:ptr[c+1]]."""

    cand: np.ndarray  # (C,) candidate index of each chain
    ptr: np.ndarray  # (C+1,)
    verts: np.ndarray  # ring vertex ids
    region: np.ndarray  # (C,) region of the tets on this chain's side


def _segments(ptr: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row id, offset) of every entry of the CSR segments ``rows``."""
    lens = ptr[rows + 1] - ptr[rows]
    owner = np.repeat(np.arange(len(rows)), lens)
    start = np.repeat(np.cumsum(lens) - lens, lens)
    return owner, np.arange(lens.sum()) - start


def _worst_around(q: np.ndarray, T, edges: np.ndarray) -> np.ndarray:
    """(k,) smallest ``q`` (m,) among the tets of each edge in ``edges`` (k >= 1 ids)."""
    tp = T.edge_tets_ptr
    if 2 * len(edges) > len(T.edges):  # most edges: one sequential pass over all
        return np.minimum.reduceat(q[T.edge_tets], tp[:-1])[edges]
    # few edges (late in a run): only their tets (~100 ms -> ~4 ms at 983k tets)
    pos, starts = csr_rows(tp, edges)
    return np.minimum.reduceat(q[T.edge_tets[pos]], starts)


def edge_candidates(
    mesh: TetMesh, max_ring: int, dirty: np.ndarray | None, *, with_skipped: bool = False
):
    """Edge ids worth trying: removable, manifold, small enough, neighbourhood changed.

    ``with_skipped=True`` also returns the number of edges left out only because their
    ring is larger than ``max_ring`` (reported as ``overflow`` in the pass statistics).
    """
    T = mesh.topology
    size = np.diff(T.edge_ring_ptr)  # polygon size: ring (closed) or chain (open)
    ok = ~T.subsegment & T.edge_manifold & (size >= 3)
    if dirty is not None:
        # the edges of the dirty tets (rows of tet_edges): late in a run a few hundred
        # tets, where a gather of every edge's tets cost ~50 ms at 983k tets
        near = np.zeros(len(ok), bool)
        near[T.tet_edges[np.asarray(dirty, bool)].reshape(-1)] = True
        ok &= near
    # interior-surface edges split their ring in two chains, each <= max_ring; the
    # whole ring may be up to 2 * max_ring - 2
    surface = (T.edge_n_subfacets == 2) & ~T.edge_boundary
    small = np.where(surface, size <= 2 * max_ring - 2, size <= max_ring)
    if with_skipped:
        return np.flatnonzero(ok & small), int((ok & ~small).sum())
    return np.flatnonzero(ok & small)


def _build_chains(mesh: TetMesh, edges: np.ndarray) -> _Chains:
    """Chains (polygons) of the candidate ``edges`` with their region."""
    T = mesh.topology
    rp, tp = T.edge_ring_ptr, T.edge_tets_ptr
    surface = (T.edge_n_subfacets[edges] == 2) & ~T.edge_boundary[edges]
    single = np.flatnonzero(~surface)
    # one chain per interior / exterior-boundary edge: the ring as it is
    e1 = edges[single]
    own1, off1 = _segments(rp, e1)
    verts1 = T.edge_ring[rp[e1][own1] + off1]
    ptr1 = np.concatenate([[0], np.cumsum(rp[e1 + 1] - rp[e1])])
    reg1 = mesh.region[T.edge_tets[tp[e1]]]
    cand1 = single
    # two chains per interior-surface edge: split the closed ring at its two subfacets
    sidx = np.flatnonzero(surface)
    e2 = edges[sidx]
    own2, off2 = _segments(rp, e2)
    ring2 = T.edge_ring[rp[e2][own2] + off2]
    ab = T.edges[e2][own2]
    fid = T.face_ids(np.column_stack([ab, ring2]))
    is_sub = T.subfacet[fid]
    # positions (offsets) of the two subfacet vertices x (first) and y (second) per edge
    sub_off = off2[is_sub].reshape(-1, 2)
    m2 = (rp[e2 + 1] - rp[e2]).astype(np.int64)
    px, py = sub_off[:, 0], sub_off[:, 1]
    len_a = py - px + 1  # chain x -> y
    len_b = m2 - (py - px) + 1  # chain y -> x (wrapping)
    starts = np.concatenate([px, py])
    lens = np.concatenate([len_a, len_b])
    which = np.concatenate([np.arange(len(e2)), np.arange(len(e2))])
    own, off = _segments(np.concatenate([[0], np.cumsum(lens)]), np.arange(len(lens)))
    mm = m2[which][own]
    verts2 = T.edge_ring[rp[e2][which][own] + (starts[own] + off) % mm]
    ptr2 = np.concatenate([[0], np.cumsum(lens)])
    reg2 = mesh.region[T.edge_tets[tp[e2][which] + starts]]
    cand2 = sidx[which]
    return _Chains(
        cand=np.concatenate([cand1, cand2]),
        ptr=np.concatenate([ptr1, ptr1[-1] + ptr2[1:]]),
        verts=np.concatenate([verts1, verts2]),
        region=np.concatenate([reg1, reg2]),
    )


def _edge_claims(T, ce: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(claims, own): the tets around each edge of ``ce`` (c,), one edge after the
    other, and the position in ``ce`` of the edge each one is around."""
    own, off = _segments(T.edge_tets_ptr, ce)
    return T.edge_tets[T.edge_tets_ptr[ce][own] + off], own


class _Flips:
    """The new tets of the candidates' flips, from the rings' optimal triangulations
    (``tris_of``: ring size -> (chain rows, ring vertex ids, triangles))."""

    def __init__(self, tris_of, ch, a_all, b_all, edges, e_open):
        self.tris_of, self.ch, self.a_all, self.b_all = tris_of, ch, a_all, b_all
        self.edges, self.e_open = edges, e_open

    def tets(self, chosen: np.ndarray):
        """(new tets (N, 4), their regions (N,), owners (N,), hinges) of the candidates
        ``chosen`` (len(edges),) bool. ``hinges``: [(owner, a, b, x, y, apex) rows] of
        every open chain (boundary and surface flips; ``_changes_surface``)."""
        tris_of, ch, a_all, b_all = self.tris_of, self.ch, self.a_all, self.b_all
        edges, e_open = self.edges, self.e_open
        new_tets, new_region, new_owner = [], [], []
        hinge = []
        for k, (sel, ring_ids, tris) in tris_of.items():
            w = chosen[ch.cand[sel]]
            if not w.any():
                continue
            rid = ring_ids[w]  # (W, k)
            tri = np.take_along_axis(rid[:, None, :], tris[w].reshape(w.sum(), -1)[:, None, :], 2)
            tri = tri.reshape(-1, 3)  # (W*(k-2), 3) global (v_i, v_k, v_j)
            nper = tris.shape[1]
            a = np.repeat(a_all[sel][w], nper)
            b = np.repeat(b_all[sel][w], nper)
            top = np.column_stack([tri[:, 0], tri[:, 1], tri[:, 2], a])
            bot = np.column_stack([tri[:, 0], tri[:, 2], tri[:, 1], b])
            new_tets += [top, bot]
            reg = np.repeat(ch.region[sel][w], nper)
            new_region += [reg, reg]
            owner = np.repeat(ch.cand[sel][w], nper)
            new_owner += [owner, owner]
            # the surface triangles (a, x, y), (b, x, y) replacing (a, b, x), (a, b, y) are
            # those of the triangle on the chain's closing side (v_0, v_{k-1})
            op = e_open[edges[ch.cand[sel][w]]]
            if op.any():
                root = (tris[w][op][:, :, 0] == 0) & (tris[w][op][:, :, 2] == k - 1)  # (W', k-2)
                apex = rid[op][np.arange(op.sum()), tris[w][op][:, :, 1][root]]
                hinge.append(
                    np.column_stack(
                        [
                            ch.cand[sel][w][op],
                            a_all[sel][w][op],
                            b_all[sel][w][op],
                            rid[op][:, 0],
                            rid[op][:, -1],
                            apex,
                        ]
                    )  # fmt: skip
                )
        if not new_tets:
            empty = np.zeros(0, np.int64)
            return np.zeros((0, 4), np.int64), empty, empty, hinge
        return (
            np.concatenate(new_tets),
            np.concatenate(new_region),
            np.concatenate(new_owner),
            hinge,
        )


def edge_removal_pass(mesh: TetMesh, **options) -> tuple[TetMesh, PassStats, np.ndarray | None]:
    """One pass: try every candidate edge at once, apply a conflict-free set of winners
    (``plan_edge_removal``'s, with the same options).

    Returns:
        (new mesh, stats, keep): ``keep`` (m,) marks the old tets that survive, in order,
        at the front of the new mesh; the new tets follow. ``keep`` is None (and the
        mesh returned unchanged) when nothing improved.
    """
    plan, stats = plan_edge_removal(mesh, **options)
    out, keep = apply_plans(mesh, [plan])
    return out, stats, keep


def plan_edge_removal(
    mesh: TetMesh,
    *,
    measure: str = "min_sine",
    max_ring: int = 7,
    quality: np.ndarray | None = None,
    dirty: np.ndarray | None = None,
    min_improvement: float = 1e-9,
    prune: bool = True,
    sites: np.ndarray | None = None,
    forbidden: np.ndarray | None = None,
    min_scaled_jacobian: float | None = None,
) -> tuple[FlipPlan | None, PassStats]:
    """Try every candidate edge at once and choose a conflict-free set of winners.

    Args:
        mesh: input mesh.
        measure: quality measure name.
        max_ring: largest polygon (ring or chain) size tried.
        quality: (m,) quality of ``mesh``'s tets under ``measure`` if already known.
        dirty: (m,) bool; only edges touching a dirty tet are tried (None: all edges).
        min_improvement: a winner must raise its worst tet by more than this (guards
            against flipping back and forth between configurations equal to round-off).
        prune: let the kernels skip triangulations that cannot beat the old worst tet.
        sites: (k,) edge ids from ``edge_candidates`` to try instead (``dirty`` unused).
        forbidden: (f, 4) tets no winner may create again (as vertex sets): the tets a
            perturbation kick removed, so that the climb after it does not undo it.
        min_scaled_jacobian: floor of the guard on curved tets (``_curved_guard``;
            None: no guard; a mesh without curved edges has none to guard).

    Returns:
        (plan, stats): the winners' ``FlipPlan`` (None when nothing improved), not
        applied.
    """
    stats = PassStats("edge")
    T = mesh.topology
    q = mesh.quality(measure) if quality is None else quality
    if sites is None:
        edges, too_big = edge_candidates(mesh, max_ring, dirty, with_skipped=True)
    else:
        edges, too_big = np.asarray(sites, np.int64), 0
    stats.overflow = too_big
    if len(edges) == 0:
        return None, stats
    ch = _build_chains(mesh, edges)
    clen = np.diff(ch.ptr)
    tp = T.edge_tets_ptr
    q_old = _worst_around(q, T, edges)
    valid = np.ones(len(edges), bool)
    np.logical_and.at(valid, ch.cand, (clen >= 3) & (clen <= max_ring))
    stats.attempts = int(valid.sum())
    stats.overflow += int((~valid).sum())
    q_new = np.full(len(edges), np.inf)
    tris_of = {}
    a_all = T.edges[edges[ch.cand], 0]
    b_all = T.edges[edges[ch.cand], 1]
    pts = mesh.points
    solve = np.flatnonzero(valid[ch.cand])  # every chain of a valid candidate, all sizes
    if len(solve):
        sizes = clen[solve]
        # the distinct ring sizes, by a count (small ints): no hash or sort of every ring
        present = np.flatnonzero(np.bincount(sizes)).tolist()
        prefetch_rings(present, measure, prune)
        width = int(sizes.max())
        # (S, width) vertex ids; slots past a chain's end repeat its last vertex
        ring_all = ch.verts[
            ch.ptr[solve][:, None] + np.minimum(np.arange(width), sizes[:, None] - 1)
        ]
        qn, tris_all = solve_rings(  # (np.take: faster than indexing for row gathers)
            np.take(pts, a_all[solve], axis=0),
            np.take(pts, b_all[solve], axis=0),
            np.take(pts, ring_all, axis=0),
            q_old[ch.cand[solve]],
            measure=measure,
            prune=prune,
            sizes=sizes,
        )
        np.minimum.at(q_new, ch.cand[solve], qn)
        for k in present:
            of_k = sizes == k
            tris_of[k] = (solve[of_k], ring_all[of_k, :k], tris_all[of_k, : k - 2])
    q_new[~valid] = -np.inf
    improves = q_new > q_old + min_improvement
    e_open = T.edge_boundary | ((T.edge_n_subfacets == 2) & ~T.edge_boundary)
    flips = _Flips(tris_of, ch, a_all, b_all, edges, e_open)
    if min_scaled_jacobian is not None and mesh.has_curved_edges:
        # before the conflict-free selection: a candidate the guard rejects leaves its
        # tets to the others (rejected after it, it would keep them from its losers,
        # which are not tried again while nothing around them changes)
        cand = np.flatnonzero(improves)
        claims, own = _edge_claims(T, edges[cand])
        new_tets, _, new_owner, _ = flips.tets(improves)
        improves &= ~worse_owners(
            mesh,
            min_scaled_jacobian,
            (mesh.points, mesh.tets[claims], cand[own]),
            (mesh.points, new_tets, new_owner),
            len(edges),
        )
    cand = np.flatnonzero(improves)
    ce = edges[cand]
    claim_ptr = np.concatenate([[0], np.cumsum(tp[ce + 1] - tp[ce])])
    claims, own = _edge_claims(T, ce)
    win_local = select_conflict_free(claim_ptr, claims, q_old[cand], mesh.n_tets)
    winners = np.zeros(len(edges), bool)
    winners[cand[win_local]] = True
    if not winners.any():
        return None, stats
    remove = np.zeros(mesh.n_tets, bool)
    remove[claims[win_local[own]]] = True
    new_tets, new_region, new_owner, hinge = flips.tets(winners)
    # Guard for inverted / degenerate input: there a cavity need not be star-shaped, and
    # an "improving" flip can still raise the number of non-positive tets or create a
    # face that already exists elsewhere (a non-conforming mesh). Reject such winners.
    reject = worse_orientation_owners(mesh, new_tets, new_owner, claims, cand[own], len(edges))
    # (new tets are built for the winners only: a winner that would undo a perturbation
    # kick is dropped here, and its tets wait for the next pass)
    reject |= recreating_owners(new_tets, new_owner, forbidden, len(edges))
    if hinge:
        reject |= _changes_surface(mesh, np.concatenate(hinge), len(edges))
    while True:
        if reject.any():
            remove[claims[reject[cand[own]] & winners[cand[own]]]] = False
            winners &= ~reject
            ok = ~reject[new_owner]
            new_tets, new_region, new_owner = new_tets[ok], new_region[ok], new_owner[ok]
        if not winners.any():
            return None, stats
        reject = nonconforming_owners(mesh, remove, new_tets, new_owner, len(edges))
        if not reject.any():
            break
    sizes = np.diff(T.edge_tets_ptr)[edges[winners]]
    stats.successes = int(winners.sum())
    stats.by_size = {int(s): int(c) for s, c in zip(*np.unique(sizes, return_counts=True))}
    we = edges[winners]
    kind = np.where(T.edge_boundary[we], 0, np.where(T.edge_n_subfacets[we] == 2, 2, 1))
    counts = np.bincount(kind, minlength=3)
    stats.by_kind = {
        "boundary": int(counts[0]),
        "interior": int(counts[1]),
        "surface": int(counts[2]),
    }
    old_p, new_p = _protected_updates(mesh, we)
    return FlipPlan(remove, new_tets, new_region, old_p, new_p), stats


def _changes_surface(mesh, hinge: np.ndarray, n_cand) -> np.ndarray:
    """(n_cand,) bool: 2-2 / 4-4 flips whose quadrilateral a, x, b, y is not strictly convex.

    ``hinge`` (h, 6): owner, a, b, x, y and the apex of the new tets on edge xy. Flipping
    the coplanar triangles (a, b, x), (a, b, y) to (a, x, y), (b, x, y) covers the same
    surface iff segments ab and xy cross: x, y strictly on both sides of the plane
    through a, b and the (off-surface) apex, and a, b on both sides of the plane through
    x, y and the apex. Positive new tets guarantee this; around inverted tets it must be
    checked (exactly, with orient3d; an apex on the surface plane fails the test).
    """
    from ._predicates import orient3d_tets

    o, a, b, x, y, v = hinge.T
    p = mesh.points
    s = orient3d_tets(
        p,
        np.column_stack(
            [
                np.concatenate([a, x]),
                np.concatenate([b, y]),
                np.concatenate([v, v]),
                np.concatenate([x, a]),
            ]
        ),
    )
    t = orient3d_tets(
        p,
        np.column_stack(
            [
                np.concatenate([a, x]),
                np.concatenate([b, y]),
                np.concatenate([v, v]),
                np.concatenate([y, b]),
            ]
        ),
    )
    h = len(o)
    crossing = (s.astype(np.int64) * t < 0).reshape(2, h).all(axis=0)
    reject = np.zeros(n_cand, bool)
    reject[o[~crossing]] = True
    return reject


def _protected_updates(mesh: TetMesh, edges: np.ndarray):
    """Old/new user-protected faces of winning surface edges: interior-surface edges
    (4-4 flips) and boundary edges (2-2 flips of two coplanar boundary faces)."""
    T = mesh.topology
    if len(mesh.protected_faces) == 0:
        return None, None
    surf = edges[T.edge_n_subfacets[edges] == 2]
    if len(surf) == 0:
        return None, None
    # the two subfacets at ab: faces (a, b, x) and (a, b, y); after the flip the surface
    # carries (a, x, y) and (b, x, y)
    rp = T.edge_ring_ptr
    own, off = _segments(rp, surf)
    ring = T.edge_ring[rp[surf][own] + off]
    ab = T.edges[surf][own]
    tri = np.sort(np.column_stack([ab, ring]), axis=1)
    fid = T.face_ids(tri)
    xs = ring[T.subfacet[fid]].reshape(-1, 2)
    a, b = T.edges[surf, 0], T.edges[surf, 1]
    old = np.concatenate([np.column_stack([a, b, xs[:, 0]]), np.column_stack([a, b, xs[:, 1]])])
    new = np.concatenate(
        [np.column_stack([a, xs[:, 0], xs[:, 1]]), np.column_stack([b, xs[:, 0], xs[:, 1]])]
    )
    return old, new
