"""Apply a batch of transformations at once: drop old tets, append new ones."""

from __future__ import annotations

import numpy as np

from ._mesh import TetMesh
from ._topology import match_rows


def replace_tets(
    mesh: TetMesh,
    remove: np.ndarray,
    new_tets: np.ndarray,
    new_region: np.ndarray,
    old_protected: np.ndarray | None = None,
    new_protected: np.ndarray | None = None,
) -> tuple[TetMesh, int]:
    """A new mesh without the tets where ``remove`` (m,) is True, plus ``new_tets`` (k, 4).

    Kept tets keep their order and come first; the new tets follow, so the returned
    ``start`` index marks the tets this step created (the optimizer's "dirty" set).
    User-protected faces a flip replaced (``old_protected`` (p,3)) are swapped for the
    faces that now carry the same surface (``new_protected`` (p,3)).
    """
    kept = mesh.tets[~remove]
    tets = np.concatenate([kept, new_tets.astype(np.int64)])
    region = np.concatenate([mesh.region[~remove], new_region.astype(np.int64)])
    protected = mesh.protected_faces
    if old_protected is not None and len(old_protected) and len(protected):
        idx = match_rows(protected, old_protected, mesh.n_points)
        hit = idx >= 0
        keep = np.ones(len(protected), bool)
        keep[idx[hit]] = False
        protected = np.concatenate([protected[keep], np.sort(new_protected[hit], axis=1)])
    out = TetMesh(mesh.points, tets, region, protected, mesh.protected_edges)
    return out, len(kept)
