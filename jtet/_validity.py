"""Independent validity check of a tetrahedral mesh: ``check_validity(mesh) -> ValidityReport``.

Deliberately computed from the raw ``points`` / ``tets`` / ``region`` arrays without
``jtet._topology``: the optimizer's own adjacency is what this check is meant to audit, so
it must not share code with it. Everything is vectorized NumPy (sorting, grouping, a
connected-components labelling); there is no Python loop over tets, faces or edges.

What is checked (each problem is counted and up to ``MAX_EXAMPLES`` examples are kept):

* tets repeating a vertex, duplicate tets (same vertex set);
* conformity: every face lies in at most two tets, and two tets sharing a face induce
  opposite orientations on it (otherwise they lie on the same side of it: they overlap);
* the boundary surface (faces of exactly one tet) is a closed 2-manifold: every boundary
  edge lies in exactly two boundary triangles, and the boundary triangles around every
  boundary vertex form a single fan (its link is one cycle, no "pinched" vertex);
* geometric orientation with a robust orient3d: inverted (negative volume) and degenerate
  (zero volume) tets;
* region interfaces (faces between tets of different regions) are closed or end on the
  boundary: an interface edge not on the boundary lies in at least two interface faces;
* protected faces and edges are still faces and edges of the mesh;
* unreferenced points, and points at the same coordinates as another point (a seam:
  two coincident surfaces that share no vertex); reported, but not errors.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ._errors import InvariantError

MAX_EXAMPLES = 5

# Faces of tet (v0, v1, v2, v3) as its boundary chain with signs absorbed:
# d[0123] = [123] - [023] + [013] - [012] = [123] + [032] + [013] + [021].
# Every triple below is therefore oriented the same way relative to the tet (outward for a
# positively oriented tet), and two tets that are consistently oriented induce opposite
# orientations on a face they share.
_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
_EDGES = np.array([[0, 1], [1, 2], [2, 0]])  # edges of an oriented triangle


def orientation_signs(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, bool]:
    """Sign (+1 / 0 / -1, int8 (m,)) of every tet's volume, and whether it is exact
    (always: the robust ``jtet._predicates.orient3d_tets``)."""
    from ._predicates import orient3d_tets

    return np.asarray(orient3d_tets(points, tets), dtype=np.int8), True


class _Groups(NamedTuple):
    """Equal rows of a (k, c) int array, by one sort.

    ``order`` sorts the rows (equal rows contiguous, in no particular order inside a group);
    group g is ``order[starts[g] : starts[g] + counts[g]]``; ``first`` is a row index of
    every group (its representative).
    """

    order: np.ndarray
    starts: np.ndarray
    counts: np.ndarray

    @property
    def first(self) -> np.ndarray:
        return self.order[self.starts]

    def inverse(self) -> np.ndarray:
        """(k,) group id of every row."""
        gid = np.repeat(np.arange(len(self.starts)), self.counts)
        inv = np.empty(len(self.order), np.int64)
        inv[self.order] = gid
        return inv


def _group_rows(rows: np.ndarray, n: int) -> _Groups:
    """Group equal rows of a non-negative int array (k, c) with entries < n."""
    k, c = rows.shape
    if k == 0:
        e = np.zeros(0, np.int64)
        return _Groups(e, e, e)
    n = max(int(n), 1)
    if float(n) ** c < 2.0**62:  # pack each row into one int64 key: a 1-D sort is fastest
        key = rows[:, 0].astype(np.int64)
        for j in range(1, c):
            key = key * n + rows[:, j]
        order = np.argsort(key)
        ks = key[order]
        new = np.empty(k, bool)
        new[0] = True
        np.not_equal(ks[1:], ks[:-1], out=new[1:])
    else:
        order = np.lexsort(rows.T[::-1])
        srt = rows[order]
        new = np.concatenate([[True], (srt[1:] != srt[:-1]).any(axis=1)])
    starts = np.flatnonzero(new)
    counts = np.diff(np.append(starts, k))
    return _Groups(order, starts, counts)


def _examples(a) -> tuple:
    """Up to MAX_EXAMPLES rows of ``a`` as (nested) tuples of Python ints."""
    a = np.asarray(a)[:MAX_EXAMPLES]
    return tuple(tuple(int(v) for v in r) if a.ndim > 1 else int(r) for r in a)


def _rows_present(rows: np.ndarray, table: np.ndarray, n: int) -> np.ndarray:
    """(k,) bool: which (sorted) rows also occur in ``table`` (sorted rows, same width)."""
    if len(rows) == 0:
        return np.zeros(0, bool)
    both = np.concatenate([table, rows])
    inverse = _group_rows(both, n).inverse()
    return np.isin(inverse[len(table) :], inverse[: len(table)])


@dataclass(frozen=True)
class ValidityReport:
    """Result of ``check_validity``: a count and examples for every kind of problem.

    ``ok`` is True iff the mesh is conforming (no face in more than two tets, consistently
    oriented), its boundary is a closed 2-manifold, it has no duplicate tets and no tets
    with a repeated vertex, region interfaces are closed or end on the boundary, protected
    faces and edges are present, **and no tet is inverted or degenerate**. Inverted and
    degenerate tets are also counted separately (``n_inverted``, ``n_degenerate``) so a
    caller whose input already had some can require "no new ones" instead
    (``topologically_ok`` plus a comparison of the counts, or
    ``raise_if_invalid(report, context, baseline=input_report)``). Unreferenced points do
    not make a mesh invalid; they are only reported. ``bool(report) == report.ok``.

    Example fields hold up to ``MAX_EXAMPLES`` items: tet indices, point indices, sorted
    vertex triples (faces) or pairs (edges); ``misoriented_faces`` holds the pairs of tets
    that induce the same orientation on their shared face, ``duplicate_tets`` pairs
    (first tet, later copy).
    """

    n_points: int
    n_tets: int
    n_boundary_faces: int
    n_interface_faces: int
    n_repeated_vertex_tets: int = 0
    repeated_vertex_tets: tuple = ()
    n_duplicate_tets: int = 0
    duplicate_tets: tuple = ()
    n_overshared_faces: int = 0
    overshared_faces: tuple = ()
    n_misoriented_faces: int = 0
    misoriented_faces: tuple = ()
    n_nonmanifold_edges: int = 0
    nonmanifold_edges: tuple = ()
    n_nonmanifold_vertices: int = 0
    nonmanifold_vertices: tuple = ()
    n_open_interface_edges: int = 0
    open_interface_edges: tuple = ()
    n_missing_protected_faces: int = 0
    missing_protected_faces: tuple = ()
    n_missing_protected_edges: int = 0
    missing_protected_edges: tuple = ()
    n_inverted: int = 0
    inverted_tets: tuple = ()
    n_degenerate: int = 0
    degenerate_tets: tuple = ()
    n_unreferenced_points: int = 0
    unreferenced_points: tuple = ()
    n_coincident_points: int = 0
    coincident_points: tuple = ()
    orientation_exact: bool = True

    # (count field, example field, description) in the order __str__ lists them
    _PROBLEMS = (
        ("n_repeated_vertex_tets", "repeated_vertex_tets", "tet(s) repeat a vertex"),
        ("n_duplicate_tets", "duplicate_tets", "duplicate tet(s) (first, copy)"),
        ("n_overshared_faces", "overshared_faces", "face(s) shared by more than 2 tets"),
        (
            "n_misoriented_faces",
            "misoriented_faces",
            "face(s) whose two tets induce the same orientation (tet pairs)",
        ),
        (
            "n_nonmanifold_edges",
            "nonmanifold_edges",
            "boundary edge(s) not in exactly 2 boundary faces",
        ),
        (
            "n_nonmanifold_vertices",
            "nonmanifold_vertices",
            "boundary vertex/vertices whose boundary faces form more than one fan",
        ),
        (
            "n_open_interface_edges",
            "open_interface_edges",
            "region-interface edge(s) ending inside the mesh",
        ),
        (
            "n_missing_protected_faces",
            "missing_protected_faces",
            "protected face(s) missing from the mesh",
        ),
        (
            "n_missing_protected_edges",
            "missing_protected_edges",
            "protected edge(s) missing from the mesh",
        ),
        ("n_inverted", "inverted_tets", "inverted tet(s) (negative volume)"),
        ("n_degenerate", "degenerate_tets", "degenerate tet(s) (zero volume)"),
    )

    @property
    def conforming(self) -> bool:
        """No tet repeats a vertex, no duplicates, faces in <= 2 tets, consistent orientation."""
        return not (
            self.n_repeated_vertex_tets
            or self.n_duplicate_tets
            or self.n_overshared_faces
            or self.n_misoriented_faces
        )

    @property
    def manifold(self) -> bool:
        """The boundary surface is a closed 2-manifold (edges and vertex links)."""
        return not (self.n_nonmanifold_edges or self.n_nonmanifold_vertices)

    @property
    def topologically_ok(self) -> bool:
        """Everything of ``ok`` except the inverted / degenerate tet counts."""
        return (
            self.conforming
            and self.manifold
            and not (
                self.n_open_interface_edges
                or self.n_missing_protected_faces
                or self.n_missing_protected_edges
            )
        )

    @property
    def ok(self) -> bool:
        """Topologically ok and no inverted or degenerate tet."""
        return self.topologically_ok and not (self.n_inverted or self.n_degenerate)

    def __bool__(self) -> bool:
        return self.ok

    def problems(self) -> list[str]:
        """One line per kind of problem present, with examples."""
        out = []
        for count, examples, what in self._PROBLEMS:
            n = getattr(self, count)
            if n:
                ex = ", ".join(str(e) for e in getattr(self, examples))
                more = ", ..." if n > len(getattr(self, examples)) else ""
                out.append(f"{n} {what}: {ex}{more}")
        return out

    def __str__(self) -> str:
        head = (
            f"{'valid' if self.ok else 'INVALID'} mesh: {self.n_tets} tets, {self.n_points} "
            f"points, {self.n_boundary_faces} boundary faces, "
            f"{self.n_interface_faces} region-interface faces"
        )
        lines = [head] + [f"  - {p}" for p in self.problems()]
        return "\n".join(lines + [f"  (note: {note})" for note in self.notes()])

    def notes(self) -> list[str]:
        """One line per remark that does not make the mesh invalid."""
        out = []
        if self.n_unreferenced_points:
            out.append(
                f"{self.n_unreferenced_points} unreferenced point(s), e.g. "
                f"{', '.join(map(str, self.unreferenced_points))}"
            )
        if self.n_coincident_points:
            out.append(
                f"{self.n_coincident_points} point(s) at the same coordinates as another "
                "point of the tets (a seam: surfaces inside the mesh whose sides share no "
                f"vertex), e.g. (first, copy) {', '.join(map(str, self.coincident_points))}"
            )
        if not self.orientation_exact:
            out.append("orientation decided by a non-robust float determinant")
        return out

    def as_dict(self) -> dict:
        """JSON-friendly dict of every field plus ``ok``."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d = {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}
        d["ok"] = self.ok
        return d


def component_roots(n: int, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(n,) connected-component label of every node of the undirected graph with edges
    ``src[i] -- dst[i]``: the smallest node id of its component.

    Hook and shortcut: every edge whose ends have different roots hooks the larger root
    under the smaller (``np.minimum.at``: a root hooked by several edges takes the smallest),
    then pointer jumping makes every node point at its root again. Roots only decrease,
    so no cycle forms; the fans here are paths and cycles of a few dozen nodes, a handful
    of rounds. (scipy.sparse.csgraph did this in one call but cost 0.33 s of import in
    every process that computes statistics.)
    """
    root = np.arange(n)
    src = np.asarray(src, np.int64)
    dst = np.asarray(dst, np.int64)
    while True:
        rs, rd = root[src], root[dst]
        split = rs != rd
        if not split.any():
            return root
        np.minimum.at(root, np.maximum(rs, rd)[split], np.minimum(rs, rd)[split])
        while True:  # pointer jumping until every node points at a root
            up = root[root]
            if np.array_equal(up, root):
                break
            root = up


# Odd 64-bit multipliers mixing a point's three coordinate bit patterns into one sort key
_MIX = np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9], np.uint64)


def coincident_points(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(k, 2) pairs (first, other) of points used by ``tets`` (m, 4) at exactly the same
    coordinates (``points`` (n, 3); -0.0 equals 0.0): every used point that repeats
    another's coordinates, paired with the smallest id at them, sorted by ``other``.

    One sort of a 64-bit mix of the coordinates' bits, not a lexicographic sort of the
    rows (the 983k-tet cube's 167k points: ~22 ms in all, where the lexicographic sort
    alone takes ~80); only points whose mixes collide are compared coordinate by
    coordinate, so a collision of distinct points finds nothing.
    """
    used = np.zeros(len(points), bool)
    used[np.asarray(tets, np.int64).reshape(-1)] = True
    ids = np.flatnonzero(used)
    p = np.ascontiguousarray(points[ids], np.float64) + 0.0  # -0.0 + 0.0 is +0.0
    mixed = np.bitwise_xor.reduce(p.view(np.uint64) * _MIX, axis=1)
    order = np.argsort(mixed)
    same = mixed[order][1:] == mixed[order][:-1]
    if not same.any():
        return np.zeros((0, 2), np.int64)
    member = np.zeros(len(order), bool)
    member[1:] |= same
    member[:-1] |= same
    cand = ids[order[member]]
    cand = cand[np.lexsort((cand, *points[cand].T[::-1] + 0.0))]  # by x, y, z, then id
    c = points[cand] + 0.0
    run_start = np.ones(len(cand), bool)
    run_start[1:] = (c[1:] != c[:-1]).any(axis=1)
    first = cand[np.maximum.accumulate(np.where(run_start, np.arange(len(cand)), 0))]
    pairs = np.column_stack([first, cand])[~run_start]
    return pairs[np.argsort(pairs[:, 1])]


def seam_triangles(faces: np.ndarray, pairs: np.ndarray, n_points: int) -> np.ndarray:
    """(t, 3): the rows of ``faces`` (f, 3), boundary faces of a mesh of ``n_points``,
    that lie on a seam: they have a vertex of the coincident ``pairs`` (k, 2)
    (``coincident_points``), and their twin, the face of the coincident vertices on the
    other side (a crack's front is both sides' own), is among ``faces`` too."""
    first = np.arange(n_points)
    first[pairs[:, 1]] = pairs[:, 0]
    on = np.zeros(n_points, bool)
    on[pairs.reshape(-1)] = True
    faces = faces[on[faces].any(axis=1)]
    _, twin, count = np.unique(
        np.sort(first[faces], axis=1), axis=0, return_inverse=True, return_counts=True
    )
    return faces[count[twin.reshape(-1)] > 1]


def check_validity(mesh) -> ValidityReport:
    """Check ``mesh`` (a ``TetMesh``, or anything with ``points`` (n,3), ``tets`` (m,4),
    optional ``region`` (m,), ``protected_faces`` (k,3), ``protected_edges`` (k,2)).

    Cost: a few sorts of the 4m faces and 3 * (boundary faces) edges; O(m log m).
    """
    points = np.asarray(mesh.points, dtype=np.float64)
    tets = np.asarray(mesh.tets, dtype=np.int64).reshape(-1, 4)
    region = getattr(mesh, "region", None)
    region = np.zeros(len(tets), np.int64) if region is None else np.asarray(region)
    pfaces = getattr(mesh, "protected_faces", None)
    pedges = getattr(mesh, "protected_edges", None)
    n, m = len(points), len(tets)
    r: dict = {}

    # --- tets repeating a vertex: excluded from the face analysis (their "faces" are not
    # triangles), reported on their own
    st = np.sort(tets, axis=1)
    rep = (st[:, 1:] == st[:, :-1]).any(axis=1)
    r["n_repeated_vertex_tets"] = int(rep.sum())
    r["repeated_vertex_tets"] = _examples(np.flatnonzero(rep))
    proper = np.flatnonzero(~rep)

    # --- faces: 4 per proper tet, oriented by the boundary chain of the tet
    t = tets[proper]
    f = t[:, _FACES].reshape(-1, 3)  # (4m', 3), row 4*i + j: face opposite vertex j of tet i
    f_tet = np.repeat(proper, 4)
    fs = np.sort(f, axis=1)
    # orientation bit = parity of the permutation sorting the triple
    parity = ((f[:, 0] > f[:, 1]) ^ (f[:, 0] > f[:, 2]) ^ (f[:, 1] > f[:, 2])).astype(np.int8)
    fg = _group_rows(fs, n)
    faces, fcnt, order, starts = fs[fg.first], fg.counts, fg.order, fg.starts

    # --- duplicate tets (same vertex set, whatever the order): the same face opposite
    # their largest vertex, and that vertex. Grouped by (face group, vertex), one 1-D
    # sort of m keys, not a sort of the (m, 4) sorted rows (983k tets: 0.83 -> ~0.15 s)
    top = np.argmax(t, axis=1)  # local index of each tet's largest vertex
    across = fg.inverse()[4 * np.arange(len(t)) + top]
    key = across * np.int64(n) + t[np.arange(len(t)), top]
    g = _group_rows(key[:, None], int(key.max(initial=0)) + 1)
    r["n_duplicate_tets"] = int((g.counts - 1).sum())
    if r["n_duplicate_tets"]:
        # pair every later copy with the first (smallest index) tet of its group
        members = proper[g.order]
        first = np.minimum.reduceat(members, g.starts)
        gid = np.repeat(np.arange(len(g.starts)), g.counts)
        copies = members != first[gid]
        pairs = np.stack([first[gid][copies], members[copies]], axis=1)
        r["duplicate_tets"] = _examples(pairs[np.lexsort(pairs.T[::-1])])
    r["n_overshared_faces"] = int((fcnt > 2).sum())
    r["overshared_faces"] = _examples(faces[fcnt > 2])

    # faces in exactly two tets: the two incidences
    two = np.flatnonzero(fcnt == 2)
    ia, ib = order[starts[two]], order[starts[two] + 1]
    mis = parity[ia] == parity[ib]
    r["n_misoriented_faces"] = int(mis.sum())
    r["misoriented_faces"] = _examples(
        np.sort(np.stack([f_tet[ia][mis], f_tet[ib][mis]], axis=1), axis=1)
    )

    # region interfaces: faces between two tets of different regions
    iface = region[f_tet[ia]] != region[f_tet[ib]]
    iface_faces = faces[two[iface]]
    r["n_interface_faces"] = len(iface_faces)

    # --- boundary surface: faces in exactly one tet, with the tet's orientation
    one = np.flatnonzero(fcnt == 1)
    bfaces = f[order[starts[one]]]  # oriented (outward for a positive tet)
    r["n_boundary_faces"] = len(bfaces)
    nb = len(bfaces)
    he = bfaces[:, _EDGES].reshape(-1, 2)  # half-edge (f, j): bfaces[f, j] -> bfaces[f, j+1]
    hes = np.sort(he, axis=1)
    eg = _group_rows(hes, n)
    bedges, ecnt = hes[eg.first], eg.counts
    bad_edge = ecnt != 2
    r["n_nonmanifold_edges"] = int(bad_edge.sum())
    r["nonmanifold_edges"] = _examples(bedges[bad_edge])

    # vertex links: corners (face, vertex) of boundary faces are nodes; across every
    # manifold boundary edge, join the two corners at each of its endpoints. The corners
    # at a vertex form one component per fan of boundary faces around it; a vertex with
    # more than one fan is pinched. Vertices of non-manifold edges are reported above and
    # left out here.
    if nb:
        good = np.flatnonzero(~bad_edge)
        h1, h2 = eg.order[eg.starts[good]], eg.order[eg.starts[good] + 1]  # ids 3f + j
        f1, j1 = np.divmod(h1, 3)
        f2, j2 = np.divmod(h2, 3)
        u = bfaces[f1, j1]
        # corner of u (and of w) in the second face
        k2u = np.where(bfaces[f2, j2] == u, j2, (j2 + 1) % 3)
        k2w = np.where(bfaces[f2, j2] == u, (j2 + 1) % 3, j2)
        src = np.concatenate([3 * f1 + j1, 3 * f1 + (j1 + 1) % 3])
        dst = np.concatenate([3 * f2 + k2u, 3 * f2 + k2w])
        comp = component_roots(3 * nb, src, dst)
        # distinct (vertex, component) pairs, counted per vertex
        vc = np.unique(bfaces.reshape(-1).astype(np.int64) * (3 * nb) + comp)
        nfans = np.bincount(vc // (3 * nb), minlength=n)
        on_bad = np.zeros(n, bool)
        on_bad[bedges[bad_edge].reshape(-1)] = True
        pinched = np.flatnonzero((nfans > 1) & ~on_bad)
        r["n_nonmanifold_vertices"] = len(pinched)
        r["nonmanifold_vertices"] = _examples(pinched)

    # --- region interfaces end on the boundary or close up: an interface edge that is not a
    # boundary edge must lie in >= 2 interface faces (around an interior edge the region
    # label cannot change exactly once).
    if len(iface_faces):
        ie = np.sort(iface_faces[:, _EDGES].reshape(-1, 2), axis=1)
        ig = _group_rows(ie, n)
        lonely = ie[ig.first[ig.counts == 1]]
        on_boundary = _rows_present(lonely, bedges, n)
        r["n_open_interface_edges"] = int((~on_boundary).sum())
        r["open_interface_edges"] = _examples(lonely[~on_boundary])

    # --- protected faces / edges must still be faces / edges of the mesh
    if pfaces is not None and len(pfaces):
        pf = np.sort(np.asarray(pfaces, np.int64).reshape(-1, 3), axis=1)
        miss = ~_rows_present(pf, faces, n)
        r["n_missing_protected_faces"] = int(miss.sum())
        r["missing_protected_faces"] = _examples(pf[miss])
    if pedges is not None and len(pedges):
        pe = np.sort(np.asarray(pedges, np.int64).reshape(-1, 2), axis=1)
        e6 = np.stack([t[:, [0, 0, 0, 1, 1, 2]], t[:, [1, 2, 3, 2, 3, 3]]], axis=-1)
        all_edges = np.sort(e6.reshape(-1, 2), axis=1)
        miss = ~_rows_present(pe, all_edges, n)
        r["n_missing_protected_edges"] = int(miss.sum())
        r["missing_protected_edges"] = _examples(pe[miss])

    # --- geometric orientation (robust when jtet._predicates is available)
    if len(proper):
        sign, exact = orientation_signs(points, t)
    else:
        sign, exact = np.zeros(0, np.int8), True
    r["n_inverted"] = int((sign < 0).sum())
    r["inverted_tets"] = _examples(proper[sign < 0])
    r["n_degenerate"] = int((sign == 0).sum())
    r["degenerate_tets"] = _examples(proper[sign == 0])
    r["orientation_exact"] = exact

    # --- unreferenced points
    used = np.bincount(tets.reshape(-1), minlength=n) > 0 if m else np.zeros(n, bool)
    r["n_unreferenced_points"] = int((~used).sum())
    r["unreferenced_points"] = _examples(np.flatnonzero(~used))
    pairs = coincident_points(points, tets)
    r["n_coincident_points"] = len(pairs)
    r["coincident_points"] = _examples(pairs)

    return ValidityReport(n_points=n, n_tets=m, **r)


def raise_if_invalid(
    report: ValidityReport, context: str, baseline: ValidityReport | None = None
) -> None:
    """Raise ``InvariantError`` (message: ``context`` + the report) if ``report`` is not ok.

    With ``baseline`` (the report of the input mesh), inverted and degenerate tets are
    tolerated up to the baseline's counts: only *new* ones are an error.
    """
    if baseline is None:
        bad = not report.ok
    else:
        bad = (
            not report.topologically_ok
            or report.n_inverted > baseline.n_inverted
            or report.n_degenerate > baseline.n_degenerate
        )
    if bad:
        raise InvariantError(f"{context}: {report}")
