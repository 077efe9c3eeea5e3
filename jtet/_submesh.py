"""A part of a mesh as a mesh of its own, and the mesh with that part replaced.

Perturbation rounds work on the neighbourhood of the worst tets (``_perturb``) and a run
with ``Options.regions`` or protected tets on the tets it may change (``_driver``): both
improve a ``Submesh`` and ``splice`` it back. The submesh's boundary is the mesh's
boundary there plus the cut faces (shared with a tet outside), so nothing outside it
changes as long as the cut faces stay.
"""

from __future__ import annotations

import numpy as np

from ._apply import kept_then_new
from ._topology import TET_FACES, corner_counts, match_rows, row_keys

_TRIANGLE_EDGES = np.array([[0, 1], [0, 2], [1, 2]])


class Submesh:
    """The tets ``sel`` (m,) of ``mesh`` as a mesh of their own (``.mesh``); ``verts``
    maps its vertex ids to the mesh's, ``cut`` (k, 3) holds its faces that a tet outside
    it shares (sorted local vertex triples)."""

    def __init__(self, mesh, sel: np.ndarray):
        self.sel = sel
        n = mesh.n_points
        # ``pf_in``: the protected faces of these tets (the rest are kept as they are)
        self.mesh, self.verts, self.pf_in = mesh._part(sel)
        # the cut faces: faces of a tet outside with its three vertices in the submesh
        # that are faces of a submesh tet too (from the tets, not the mesh's topology:
        # after a kept round the mesh has none, and a build per round cost ~2 s at 983k
        # tets; a face lies in at most two tets, so each such face is a boundary face of
        # the submesh)
        local = np.full(n, -1, np.int64)
        local[self.verts] = np.arange(len(self.verts))
        near = ~sel & (corner_counts(local >= 0, mesh.tets) >= 3)
        outer = local[mesh.tets[near][:, TET_FACES].reshape(-1, 3)]
        outer = np.sort(outer[(outer >= 0).all(axis=1)], axis=1)
        inner = self.mesh.tets[:, TET_FACES].reshape(-1, 3)
        shared = match_rows(inner, outer, len(self.verts)) >= 0
        self.cut = outer[shared]
        # faces of outside tets whose three vertices are in the submesh but that no
        # submesh tet has: a run on the submesh must not create one (in a mesh without
        # inverted or degenerate tets it cannot: the new tets fill the old ones' space)
        self.ghosts = outer[~shared]

    def pinned_cut(self):
        """``.mesh`` with the edges and vertices of the cut faces pinned (protected):
        no flip changes a cut face (a 2-2 or 4-4 flip removes one of its edges) and no
        vertex on one moves, so any run on it splices back (``splice`` keeps the
        mesh's own protected edges and vertices, not these)."""
        edges = self.cut[:, _TRIANGLE_EDGES].reshape(-1, 2)
        return self.mesh._with_pinned(edges, self.cut.reshape(-1))

    def fits(self, sub) -> bool:
        """Whether ``sub`` (this submesh changed) splices back: it keeps every cut face
        as a boundary face (a face of exactly one of its tets) and makes no face that a
        tet outside has (``splice``). From ``sub``'s face keys, not its topology: a
        build of that topology, used for nothing else, was ~12 ms per call on the 182k
        cube's rounds (7 % of the run)."""
        faces = np.sort(sub.tets[:, TET_FACES].reshape(-1, 3), axis=1)
        # one call: ``row_keys`` of a huge mesh ranks the rows it is given
        keys = row_keys(np.concatenate([faces, self.cut, self.ghosts]), sub.n_points)
        cut = keys[len(faces) : len(faces) + len(self.cut)]
        ghosts = keys[len(faces) + len(self.cut) :]
        keys = np.sort(keys[: len(faces)])
        if (np.searchsorted(keys, cut, "right") - np.searchsorted(keys, cut) != 1).any():
            return False
        return not (np.searchsorted(keys, ghosts, "right") > np.searchsorted(keys, ghosts)).any()

    def splice(self, mesh, sub):
        """(new mesh, keep (m,)): ``mesh`` with these tets replaced by ``sub``'s, its
        moved vertices moved and its new vertices appended, or None if ``sub`` changed a
        cut face (a flip of two coplanar cut faces would not fit the mesh around) or
        made a face that a tet outside has (``ghosts``: it would lie in three tets). The
        new mesh keeps ``mesh``'s protected edges and vertices (those of ``sub`` are
        theirs, never removed nor moved, or ``pinned_cut``'s).

        Flips of the mesh's own boundary faces (2-2 flips of coplanar ones, which the
        climb makes on the whole mesh too) are kept: a perturbation around a boundary
        vertex often needs one (holeplate: the hole's top seam)."""
        if not self.fits(sub):
            return None
        n_old = len(self.verts)
        to_global = np.concatenate([self.verts, mesh.n_points + np.arange(sub.n_points - n_old)])
        points = np.concatenate([mesh.points, sub.points[n_old:]])
        points[self.verts] = sub.points[:n_old]
        keep = ~self.sel
        protected = np.concatenate(
            [mesh.protected_faces[~self.pf_in], to_global[sub.protected_faces]]
        )
        labels = np.concatenate(
            [mesh.protected_face_labels[~self.pf_in], sub.protected_face_labels]
        )
        out = mesh._derive(
            points=points,
            tets=kept_then_new(mesh.tets, keep, to_global[sub.tets]),
            tets_checked=int(keep.sum()),
            region=kept_then_new(mesh.region, keep, sub.region),
            protected_faces=protected,
            protected_face_labels=labels,
        )
        return out, keep
