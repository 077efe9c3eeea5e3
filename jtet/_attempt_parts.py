"""The parts of a perturbation attempt that can be kept on their own.

A round's batched kick changes the mesh around every worst tet at once, and the climb
after it repairs each place. On a large mesh the worst tets are many and far apart (the
983k-tet cube's late rounds: 30-60 seeds in 5-12 places), and an attempt is judged as a
whole (``_perturb.better``): one place left worse than the round's worst fails the
attempt, and the places it fixed are lost with it. The rounds then end on single-site
kicks at the end of their ladder, one place per round.

Here an attempt's change is split into parts that do not touch: the tets it removed and
the tets it made, grouped by shared vertices (a moved vertex changes every tet around it,
an inserted one is a vertex of its new tets only). A part whose removed and new tets have
the same boundary faces fills the same space, so any set of parts can be applied to the
round's start alone, and each part is judged on its own: kept when it lowers none of its
tets below the round's worst and leaves no more tets near that worst than before.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ._topology import TET_FACES, match_rows, row_keys


def _changed(
    start_tets: Int[np.ndarray, "m 4"],
    end_tets: Int[np.ndarray, "k 4"],
    moved: Bool[np.ndarray, " n"],
    n: int,
) -> tuple[np.ndarray, np.ndarray]:
    """((m,), (k,)) bool: the start tets the attempt removed or moved, the end tets it
    made or moved (a tet of both meshes whose vertices all stayed is unchanged)."""
    found = match_rows(end_tets, start_tets, n)
    still = np.zeros(len(end_tets), bool)
    still[found[found >= 0]] = True
    end_changed = ~still | moved[end_tets].any(axis=1)
    start_changed = (found < 0) | moved[start_tets].any(axis=1)
    return start_changed, end_changed


def _labels(tets: Int[np.ndarray, "c 4"], n: int) -> np.ndarray:
    """(n,) label of each vertex: vertices of a common tet of ``tets`` share one."""
    rows = np.repeat(tets[:, :1], 3, axis=1).reshape(-1)
    cols = tets[:, 1:].reshape(-1)
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _boundary_faces(tets: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(keys (b,), first vertices (b,)) of the faces that lie in one of ``tets`` only."""
    faces = np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1)
    keys, first, counts = np.unique(row_keys(faces, n), return_index=True, return_counts=True)
    once = counts == 1
    return keys[once], faces[first[once], 0]


class Parts:
    """Parts of a round's attempts kept on their own, gathered over the round's ladder.

    Every attempt starts from the round's start ``start`` (qualities ``start_q``);
    ``add`` judges the parts of one attempt's end and keeps the good ones that share no
    vertex with a part kept before (parts of different attempts then combine: each fills
    the space it emptied); ``result`` is the start with every kept part applied.
    """

    def __init__(self, start, start_q: Float[np.ndarray, " m"]):
        self.start, self.start_q = start, start_q
        self.kept = self.seen = 0  # parts kept, parts judged
        self.taken = np.zeros(start.n_points, bool)  # start vertices of the kept parts
        self.removed = np.zeros(start.n_tets, bool)  # start tets the kept parts replace
        self.moved: list[tuple[np.ndarray, np.ndarray]] = []  # (ids, positions)
        self.points: list[np.ndarray] = []  # new vertices, numbered after the start's
        self.n_new_points = 0
        self.tets: list[np.ndarray] = []  # new tets in the result's vertex ids
        self.region: list[np.ndarray] = []
        self.q: list[np.ndarray] = []

    def add(self, end, end_q: Float[np.ndarray, " k"], worst: float, limit: float) -> int:
        """Keep the good parts of the attempt that ended at ``end`` (qualities
        ``end_q``); returns how many. A part is good when its new tets' worst quality is
        at least ``worst`` (the round's worst), it has no more tets below ``limit`` (the
        round's near-worst bound) than its removed ones, and it fills the space it
        emptied. Vertex ids below ``start.n_points`` are the same in both meshes; the
        end's other vertices are new (insertions) and are kept with their parts only."""
        start, start_q = self.start, self.start_q
        n_start, n_end = start.n_points, end.n_points
        moved = np.ones(n_end, bool)  # new vertices count as moved: their tets are new
        moved[:n_start] = (end.points[:n_start] != start.points).any(axis=1)
        start_changed, end_changed = _changed(start.tets, end.tets, moved, n_end)
        old, new = start.tets[start_changed], end.tets[end_changed]
        if not len(old) or not len(new):
            return 0
        label = _labels(np.concatenate([old, new]), n_end)
        old_part, new_part = label[old[:, 0]], label[new[:, 0]]
        # a part fills the space it emptied when its two sets of tets have the same
        # boundary faces (both are positively oriented and do not overlap): then it fits
        # the start without the other parts. Faces of one side only mark the part as not
        # separable (a flip of the mesh's boundary faces, or parts that met in the climb)
        old_keys, old_first = _boundary_faces(old, n_end)
        new_keys, new_first = _boundary_faces(new, n_end)
        good = np.ones(n_end, bool)
        good[label[old_first[~np.isin(old_keys, new_keys, assume_unique=True)]]] = False
        good[label[new_first[~np.isin(new_keys, old_keys, assume_unique=True)]]] = False
        good[label[:n_start][self.taken]] = False  # touches a part kept before
        old_q, new_q = start_q[start_changed], end_q[end_changed]
        new_worst = np.full(n_end, np.inf)
        np.minimum.at(new_worst, new_part, new_q)
        near_old = np.bincount(old_part, old_q < limit, n_end)
        near_new = np.bincount(new_part, new_q < limit, n_end)
        good &= (new_worst >= worst) & (near_new <= near_old)
        self.seen += len(np.unique(np.concatenate([old_part, new_part])))
        parts = np.unique(new_part[good[new_part]])
        if not len(parts):
            return 0
        take = good[new_part]
        self.removed[np.flatnonzero(start_changed)[good[old_part]]] = True
        in_part = np.zeros(n_end, bool)
        in_part[old.reshape(-1)] = in_part[new.reshape(-1)] = True
        self.taken |= (in_part & good[label])[:n_start]
        back = np.flatnonzero(moved[:n_start] & good[label[:n_start]])
        self.moved.append((back, end.points[back]))
        # the kept parts' new vertices, numbered after the start's and earlier ones
        used = np.zeros(n_end, bool)
        used[new[take].reshape(-1)] = True
        used[:n_start] = False
        ids = np.arange(n_end)
        ids[used] = n_start + self.n_new_points + np.arange(int(used.sum()))
        self.n_new_points += int(used.sum())
        self.points.append(end.points[used])
        self.tets.append(ids[new[take]])
        self.region.append(end.region[end_changed][take])
        self.q.append(new_q[take])
        self.kept += len(parts)
        return len(parts)

    def qualities(self) -> np.ndarray:
        """(r,) the qualities of ``result``'s tets."""
        return np.concatenate([self.start_q[~self.removed], *self.q])

    def result(self):
        """The start with every kept part applied (a TetMesh; tets in ``qualities``'
        order: the start's kept ones, then the parts' new ones)."""
        start = self.start
        points = np.concatenate([start.points, *self.points])
        for ids, positions in self.moved:
            points[ids] = positions
        kept = ~self.removed
        # the start's rows are checked rows over the same points (no moved vertex is theirs)
        return start._derive(
            points=points,
            tets=np.concatenate([start.tets[kept], *self.tets]),
            region=np.concatenate([start.region[kept], *self.region]),
            tets_checked=int(kept.sum()),
        )
