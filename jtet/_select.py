"""Conflict-free selection of winning transformations (no tet claimed twice)."""

from __future__ import annotations

import numpy as np


def select_conflict_free(
    claim_ptr: np.ndarray, claim_tets: np.ndarray, priority: np.ndarray, n_tets: int
) -> np.ndarray:
    """Greedy-by-priority set of candidates whose claimed tets are pairwise disjoint.

    Args:
        claim_ptr: (c+1,) CSR pointers: candidate i claims ``claim_tets[ptr[i]:ptr[i+1]]``.
        claim_tets: tet ids claimed.
        priority: (c,) lower is preferred (e.g. the worst quality a candidate removes).
        n_tets: number of tets in the mesh.

    Returns:
        (c,) bool mask of selected candidates: exactly the set a sequential greedy scan in
        priority order would pick, computed in vectorized rounds (each round, every
        candidate that ranks first on all of its tets wins; candidates touching a winner
        drop out).
    """
    c = len(priority)
    selected = np.zeros(c, bool)
    if c == 0:
        return selected
    rank = np.empty(c, np.int64)
    rank[np.argsort(priority, kind="stable")] = np.arange(c)
    counts = np.diff(claim_ptr)
    owner = np.repeat(np.arange(c), counts)
    active = counts > 0
    taken = np.zeros(n_tets, bool)
    while active.any():
        live = active[owner]
        best = np.full(n_tets, c, np.int64)
        np.minimum.at(best, claim_tets[live], rank[owner[live]])
        first = best[claim_tets] == rank[owner]
        win = np.logical_and.reduceat(first, claim_ptr[:-1]) & active & (counts > 0)
        selected |= win
        taken[claim_tets[win[owner]]] = True
        blocked = np.logical_or.reduceat(taken[claim_tets], claim_ptr[:-1])
        active &= ~blocked & ~win
    return selected
