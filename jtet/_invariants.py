"""Invariants every operation must keep, checked against the mesh the run started from."""

from __future__ import annotations

import numpy as np

from ._errors import InvariantError
from ._mesh import TetMesh
from ._validity import coincident_points, seam_triangles

# Volumes are sums of O(m) float64 terms of both signs; a flip regroups them, so the sums
# differ by round-off ~ m * eps * max|term|. 1e-12 relative leaves 3-4 digits of margin
# on million-tet meshes and still catches any lost or doubled tet.
VOLUME_RTOL = 1e-12


# faces of tet (v0, v1, v2, v3) opposite v0..v3, outward for a positively oriented tet
_OUT_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def _surface_signature(mesh: TetMesh, which: str) -> tuple[np.ndarray, np.ndarray]:
    """Per surface label: (vertex ids, [area, vector area x3]) of boundary / interface faces.

    A flip of coplanar subfacets changes the triangles but not the surface, so the
    vertex set, the total area and the vector area per surface stay the same.
    """
    T = mesh.topology
    mask = T.boundary_face if which == "boundary" else T.interface_face
    t0 = T.face_tets[mask, 0]
    # orient every face as its first tet's vertex order induces it (outward for a positive
    # tet): combinatorial, so well defined next to inverted and degenerate tets too, and
    # kept by every flip (the new tets induce the same orientation on the cavity's faces)
    local = np.argmax(mesh.tets[t0] == T.face_apex[mask, 0][:, None], axis=1)
    faces = np.take_along_axis(mesh.tets[t0], _OUT_FACES[local], 1)
    p = mesh.points
    n = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    r0 = mesh.region[t0]
    t1 = T.face_tets[mask, 1]
    r1 = np.where(t1 >= 0, mesh.region[np.maximum(t1, 0)], -1)
    # label by region pair; flip the vector area sign so it points from min to max region
    key = np.stack([np.minimum(r0, r1), np.maximum(r0, r1)], 1)
    n[r0 > r1] *= -1
    labels, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    area = np.linalg.norm(n, axis=1) / 2.0
    sig = np.zeros((len(labels), 4))
    np.add.at(sig[:, 0], inv, area)
    np.add.at(sig[:, 1:], inv, n / 2.0)
    return labels, sig, np.unique(faces)


def _volume_roundoff(mesh: TetMesh) -> float:
    """Bound on the float64 error of ``mesh.volumes.sum()``: each volume is a determinant
    of the edge vectors e1, e2, e3 from the tet's first vertex, off by at most a few eps
    times |e1| |e2| |e3| (needles far from their first vertex can exceed their volume by
    orders of magnitude, e.g. around a vertex the smoother moved across inverted tets)."""
    p = mesh.points[mesh.tets]
    e = np.linalg.norm(p[:, 1:] - p[:, :1], axis=2)
    return float(16 * np.finfo(float).eps * e.prod(axis=1).sum() / 6.0)


class InvariantChecker:
    """Remembers the start mesh; ``check(mesh, pass_no, op)`` raises ``InvariantError``."""

    def __init__(self, mesh: TetMesh):
        self.volume = mesh.volumes.sum()
        self.region_volume = self._region_volumes(mesh)
        self.boundary = _surface_signature(mesh, "boundary")
        self.interface = _surface_signature(mesh, "interface")
        self.n_inverted = self._count_bad(mesh)
        self.labelled = self._label_areas(mesh)
        self.pinned = mesh.protected_vertices.copy()
        self.pinned_at = mesh.points[self.pinned]
        # a seam's two sides match vertex for vertex and triangle for triangle (``improve``
        # pins them): its coincident vertices stay together, its boundary triangles stay
        self.seam = coincident_points(mesh.points, mesh.tets)
        self.seam_faces = self._seam_faces(mesh)
        self.scale = float(np.abs(mesh.volumes).sum())
        # with a feature angle, flips may replace bent subfacets: the surfaces keep their
        # vertices and labels, but their shape and the volumes they enclose change
        self.exact_surfaces = mesh._feature_angle == 0.0

    @staticmethod
    def _region_volumes(mesh: TetMesh) -> dict:
        labels, inv = np.unique(mesh.region, return_inverse=True)
        return dict(zip(labels.tolist(), np.bincount(inv, mesh.volumes).tolist(), strict=True))

    @staticmethod
    def _label_areas(mesh: TetMesh) -> dict:
        """Area of the protected faces of each label: flips re-triangulate a labelled
        patch but never move its border, so each label keeps its area."""
        f = mesh.points[mesh.protected_faces]
        area = np.linalg.norm(np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0]), axis=1) / 2.0
        labels, inv = np.unique(mesh.protected_face_labels, return_inverse=True)
        return dict(zip(labels.tolist(), np.bincount(inv, area).tolist(), strict=True))

    def _seam_faces(self, mesh: TetMesh) -> np.ndarray:
        """(k, 3) sorted rows: the boundary faces of ``mesh`` on a seam of the start
        mesh (``_validity.seam_triangles``)."""
        if len(self.seam) == 0:
            return np.zeros((0, 3), np.int64)
        T = mesh.topology
        return seam_triangles(T.faces[T.boundary_face], self.seam, mesh.n_points)

    @staticmethod
    def _count_bad(mesh: TetMesh) -> int:
        from ._predicates import orient3d_tets

        return int((orient3d_tets(mesh.points, mesh.tets) <= 0).sum())

    def check(self, mesh: TetMesh, pass_no: int, op: str) -> None:
        where = f"pass {pass_no}, operation {op!r}"

        def fail(msg):
            raise InvariantError(f"{where}: {msg}")

        report = mesh.is_valid()
        if not report.conforming:
            fail(f"the mesh is no longer valid:\n{report}")
        rv = self._region_volumes(mesh)
        if rv.keys() != self.region_volume.keys():
            fail(f"region labels changed from {sorted(self.region_volume)} to {sorted(rv)}")
        if self.exact_surfaces:
            tol = max(VOLUME_RTOL * self.scale, _volume_roundoff(mesh))
            if abs(mesh.volumes.sum() - self.volume) > tol:
                fail(f"total volume changed from {self.volume!r} to {mesh.volumes.sum()!r}")
            if any(abs(rv[k] - v) > tol for k, v in self.region_volume.items()):
                fail(f"region volumes changed from {self.region_volume} to {rv}")
        bad = self._count_bad(mesh)
        if bad > self.n_inverted:
            fail(f"{bad - self.n_inverted} new inverted or degenerate tet(s)")
        labelled = self._label_areas(mesh)
        if labelled.keys() != self.labelled.keys():
            fail(
                f"protected face labels changed from {sorted(self.labelled)} to {sorted(labelled)}"
            )
        total = max(sum(self.labelled.values()), 1e-300)
        if self.exact_surfaces and any(
            abs(labelled[k] - a) > 1e-12 * total for k, a in self.labelled.items()
        ):
            fail(
                f"the area of protected faces per label changed from {self.labelled} to {labelled}"
            )
        if not np.array_equal(mesh.protected_vertices, self.pinned):
            fail("the protected vertices changed")
        moved = (mesh.points[self.pinned] != self.pinned_at).any(axis=1)
        if moved.any():
            fail(f"protected vertex {int(self.pinned[moved][0])} moved")
        if len(self.seam):
            first, other = mesh.points[self.seam[:, 0]], mesh.points[self.seam[:, 1]]
            apart = np.flatnonzero((first != other).any(axis=1))
            if len(apart):
                a, b = self.seam[apart[0]]
                fail(f"vertices {a} and {b}, one point at the start (a seam), moved apart")
            # every seam triangle of the start is still there, with its twin
            _, count = np.unique(
                np.vstack([self.seam_faces, self._seam_faces(mesh)]), axis=0, return_counts=True
            )
            if (count == 2).sum() < len(self.seam_faces):
                fail("the boundary triangles of a seam changed")
        for which, ref in (("boundary", self.boundary), ("interface", self.interface)):
            labels, sig, verts = _surface_signature(mesh, which)
            same = np.array_equal(labels, ref[0]) and np.array_equal(verts, ref[2])
            if same and self.exact_surfaces:
                scale = max(ref[1][:, 0].sum(), 1e-300)
                same = np.allclose(sig, ref[1], rtol=1e-12, atol=1e-12 * scale)
            if not same:
                fail(f"the {which} surface changed")
