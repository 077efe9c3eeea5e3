"""Robust predicates against exact rational references (fractions.Fraction)."""

from fractions import Fraction
from itertools import permutations

import numpy as np
import pytest
from helpers import REGULAR_TET, delaunay_mesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jtet import _predicates as P
from jtet._predicates import orient3d, orient3d_tets, segment_crosses_triangle

SETTINGS = settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None
)

# ------------------------------------------------------------------------------------------
# exact references
# ------------------------------------------------------------------------------------------


def _ints(*points):
    """Points -> lists of Python ints, exactly proportional (one positive common scale), via
    Python's own exact float -> Fraction conversion (independent of jtet's bit tricks)."""
    fr = [[Fraction(float(x)) for x in p] for p in points]
    scale = max(f.denominator for p in fr for f in p)  # powers of two: a common multiple
    out = [[f * scale for f in p] for p in fr]
    assert all(f.denominator == 1 for p in out for f in p)
    return [[int(f) for f in p] for p in out]


def exact_orient(a, b, c, d) -> int:
    """sign det[b-a, c-a, d-a] in exact integer arithmetic (one query)."""
    A, B, C, D = _ints(a, b, c, d)
    u = [B[i] - A[i] for i in range(3)]
    v = [C[i] - A[i] for i in range(3)]
    w = [D[i] - A[i] for i in range(3)]
    det = (
        u[0] * (v[1] * w[2] - v[2] * w[1])
        - u[1] * (v[0] * w[2] - v[2] * w[0])
        + u[2] * (v[0] * w[1] - v[1] * w[0])
    )
    return (det > 0) - (det < 0)


def exact_orients(a, b, c, d) -> np.ndarray:
    a, b, c, d = np.broadcast_arrays(*(np.asarray(x, float).reshape(-1, 3) for x in (a, b, c, d)))
    return np.array([exact_orient(*x) for x in zip(a, b, c, d, strict=True)], dtype=np.int8)


def naive_sign(a, b, c, d) -> np.ndarray:
    return np.sign(np.linalg.det(np.stack([b - a, c - a, d - a], axis=-2))).astype(np.int8)


# ------------------------------------------------------------------------------------------
# strategies
# ------------------------------------------------------------------------------------------

# Batches are drawn from a hypothesis-chosen seed (drawing every coordinate through hypothesis
# costs more than the predicates); degenerate structure comes from integer grids and planes.
seeds = st.integers(0, 2**32 - 1)
any_float = st.floats(allow_nan=False, allow_infinity=False)
small_int = st.integers(-3, 3)
int_point = st.tuples(small_int, small_int, small_int)


@st.composite
def near_plane_batch(draw, n=12):
    """a, b, c random; d computed on plane abc with rounding, then nudged by a few ulps."""
    rng = np.random.default_rng(draw(seeds))
    scale = 2.0 ** draw(st.integers(-30, 30))
    shift = draw(st.sampled_from([0.0, 1.0, 1e3, 12345.678]))
    a, b, c = (shift + scale * rng.uniform(-1, 1, (n, 3)) for _ in range(3))
    s, t = rng.uniform(-2, 2, (2, n, 1))
    d = a + s * (b - a) + t * (c - a)
    nudge = draw(st.integers(0, 3))
    for _ in range(nudge):
        direction = np.where(rng.random((n, 3)) < 0.5, -np.inf, np.inf)
        moved = rng.random((n, 3)) < 0.5
        d = np.where(moved, np.nextafter(d, direction), d)
    return a, b, c, d


# ------------------------------------------------------------------------------------------
# orient3d
# ------------------------------------------------------------------------------------------


def test_convention_is_vtk_and_opposite_to_shewchuk():
    # a correctly oriented VTK tet: det[p1-p0, p2-p0, p3-p0] > 0
    p0, p1, p2, p3 = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.3, 1]])
    assert np.dot(p1 - p0, np.cross(p2 - p0, p3 - p0)) > 0
    assert orient3d(p0, p1, p2, p3) == 1
    assert orient3d(p1, p0, p2, p3) == -1
    # Shewchuk's ORIENT3D(a,b,c,d) = det[a-d, b-d, c-d] has the opposite sign
    shewchuk = np.linalg.det(np.stack([p0 - p3, p1 - p3, p2 - p3]))
    assert np.sign(shewchuk) == -orient3d(p0, p1, p2, p3)
    # helpers.REGULAR_TET, as listed, is negatively oriented (det = -16)
    assert orient3d(*REGULAR_TET) == -1


def test_shapes_and_broadcasting():
    s = orient3d([0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1])
    assert isinstance(s, np.int8) and np.ndim(s) == 0
    rng = np.random.default_rng(0)
    a, b, c = rng.random((3, 5, 3))
    d = rng.random((4, 5, 3))
    out = orient3d(a, b, c, d)  # (5,3) x3 with (4,5,3)
    assert out.shape == (4, 5) and out.dtype == np.int8
    ref = exact_orients(np.broadcast_to(a, d.shape), np.broadcast_to(b, d.shape),
                        np.broadcast_to(c, d.shape), d)  # fmt: skip
    np.testing.assert_array_equal(out.ravel(), ref)
    assert orient3d(
        np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    ).shape == (0,)
    with pytest.raises(ValueError):
        orient3d(np.zeros(2), np.zeros(2), np.zeros(2), np.zeros(2))


def test_nonfinite_input_raises():
    with pytest.raises(ValueError, match="NaN or infinite"):
        orient3d([0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, np.nan])
    with pytest.raises(ValueError, match="NaN or infinite"):
        orient3d([0, 0, 0], [1, 0, 0], [0, np.inf, 0], [0, 0, 1])


@SETTINGS
@given(seeds, st.sampled_from([1.0, 1e-8, 1e8]))
def test_random_matches_exact(seed, scale):
    rng = np.random.default_rng(seed)
    a, b, c, d = scale * rng.uniform(-1, 1, (4, 8, 3))
    np.testing.assert_array_equal(orient3d(a, b, c, d), exact_orients(a, b, c, d))


@SETTINGS
@given(seeds, st.sampled_from([1.0, 0.1, 2.0**-40, 1e-3, 3.0e7, 2.0**600, 2.0**-1000]))
def test_integer_grid_coplanar(seed, scale):
    """Small-integer points are coplanar very often; scaled by non-powers of two they are
    rounded off the plane (near-coplanar), by powers of two they stay exactly coplanar."""
    rng = np.random.default_rng(seed)
    a, b, c, d = rng.integers(-2, 3, (4, 12, 3)) * scale
    np.testing.assert_array_equal(orient3d(a, b, c, d), exact_orients(a, b, c, d))


@SETTINGS
@given(near_plane_batch())
def test_near_coplanar_matches_exact(batch):
    """The full predicate, and each stage on its own (the later stages rarely see a batch
    this size), against one exact reference."""
    ref = exact_orients(*batch)
    np.testing.assert_array_equal(orient3d(*batch), ref)
    sign, decided = P._orient3d_filter(*batch)
    np.testing.assert_array_equal(sign[decided], ref[decided])
    if P._LD_ENABLED:
        sign, decided = P._orient3d_filter_ld(*batch)
        np.testing.assert_array_equal(sign[decided], ref[decided])
    np.testing.assert_array_equal(P._orient3d_exact(*batch), ref)


@SETTINGS
@given(near_plane_batch(n=6), st.integers(-1074, 1000))
def test_huge_and_tiny_magnitudes(batch, k):
    """Scaled far into the subnormal / huge range (scaling may round: the reference is the
    exact determinant of whatever doubles result)."""
    top = max(np.abs(x).max() for x in batch)
    k = min(k, 1020 - int(np.ceil(np.log2(top))))  # stay finite
    a, b, c, d = (x * 2.0**k for x in batch)
    np.testing.assert_array_equal(orient3d(a, b, c, d), exact_orients(a, b, c, d))
    a, b, c, d = (x * 1e-300 for x in batch)
    np.testing.assert_array_equal(orient3d(a, b, c, d), exact_orients(a, b, c, d))


@SETTINGS
@given(st.tuples(any_float, any_float, any_float),
       st.tuples(any_float, any_float, any_float),
       st.tuples(any_float, any_float, any_float),
       st.tuples(any_float, any_float, any_float))  # fmt: skip
def test_arbitrary_doubles(a, b, c, d):
    """Whole double range: differences may overflow to inf (exact stage must take over)."""
    assert orient3d(a, b, c, d) == exact_orient(a, b, c, d)


def _parity(perm) -> int:
    perm, sign = list(perm), 1
    for i in range(len(perm)):
        while perm[i] != i:
            j = perm[i]
            perm[i], perm[j] = perm[j], perm[i]
            sign = -sign
    return sign


@SETTINGS
@given(near_plane_batch())
def test_permutation_symmetry(batch):
    """Odd permutations flip the sign, even ones (e.g. cyclic shifts of 3) keep it."""
    base = orient3d(*batch)
    perms = list(permutations(range(4)))
    # all 24 permutations in one vectorized call
    stacked = [np.concatenate([batch[perm[j]] for perm in perms]) for j in range(4)]
    got = orient3d(*stacked).reshape(len(perms), -1)
    expected = np.array([_parity(perm) for perm in perms])[:, None] * base[None, :]
    np.testing.assert_array_equal(got, expected)


def test_naive_determinant_is_wrong_where_orient3d_is_right():
    """Search rounded-onto-a-plane points for queries where float64 det gets the sign wrong."""
    rng = np.random.default_rng(7)
    n = 20000
    a, b, c = (rng.uniform(-1, 1, (n, 3)) + 0.5 for _ in range(3))
    s, t = rng.uniform(-2, 2, (2, n, 1))
    d = a + s * (b - a) + t * (c - a)
    d = np.nextafter(d, np.where(rng.random((n, 3)) < 0.5, -np.inf, np.inf))
    naive = naive_sign(a, b, c, d)
    fast = orient3d(a, b, c, d)
    # check the whole sample where either estimate disagrees with the robust one
    suspects = np.flatnonzero(naive != fast)
    assert suspects.size > 10
    exact = exact_orients(a[suspects], b[suspects], c[suspects], d[suspects])
    np.testing.assert_array_equal(fast[suspects], exact)
    wrong = (naive[suspects] != exact) & (exact != 0)
    assert wrong.sum() > 10, "expected float64 det to get some signs wrong"
    # and a spot check of the rest against the exact reference
    idx = rng.choice(n, 300, replace=False)
    np.testing.assert_array_equal(fast[idx], exact_orients(a[idx], b[idx], c[idx], d[idx]))
    i = suspects[np.flatnonzero(wrong)[0]]
    assert orient3d(a[i], b[i], c[i], d[i]) == exact_orient(a[i], b[i], c[i], d[i]) != naive[i]


def test_chunking(monkeypatch):
    rng = np.random.default_rng(4)
    a, b, c = rng.uniform(-1, 1, (3, 1000, 3))
    d = a + 0.3 * (b - a) + 0.6 * (c - a)  # near coplanar: all stages, in every chunk
    d[::4] = rng.uniform(-1, 1, (250, 3))
    whole = orient3d(a, b, c, d)
    monkeypatch.setattr(P, "_CHUNK", 77)
    np.testing.assert_array_equal(orient3d(a, b, c, d), whole)
    np.testing.assert_array_equal(whole, exact_orients(a, b, c, d))


def test_every_stage_is_exercised_and_exact():
    rng = np.random.default_rng(3)
    n = 4000
    a, b, c = (rng.uniform(-1, 1, (n, 3)) for _ in range(3))
    s, t = rng.uniform(-1, 1, (2, n, 1))
    d = a + s * (b - a) + t * (c - a)
    d[: n // 2] = np.nextafter(d[: n // 2], np.inf)
    sign, (n_ld, n_exact) = P._orient3d_staged(a, b, c, d)
    assert n_ld > n // 2  # float64 cannot decide most of these
    if P._LD_ENABLED:
        assert 0 < n_exact < n_ld  # extended precision decides most of the rest
    idx = np.concatenate([rng.choice(n, 300, replace=False), np.flatnonzero(sign == 0)])
    np.testing.assert_array_equal(sign[idx], exact_orients(a[idx], b[idx], c[idx], d[idx]))


def test_float64_filter_alone_never_lies_and_without_long_double(monkeypatch):
    rng = np.random.default_rng(11)
    n = 3000
    a, b, c = (rng.uniform(-1, 1, (n, 3)) for _ in range(3))
    s, t = rng.uniform(-1, 1, (2, n, 1))
    d = a + s * (b - a) + t * (c - a)
    d[::2] = np.nextafter(d[::2], -np.inf)
    sign, decided = P._orient3d_filter(a, b, c, d)
    ref = exact_orients(a, b, c, d)
    np.testing.assert_array_equal(sign[decided], ref[decided])
    monkeypatch.setattr(P, "_LD_ENABLED", False)
    s2, (n_ld, n_exact) = P._orient3d_staged(a, b, c, d)
    assert n_exact == n_ld == (~decided).sum()
    np.testing.assert_array_equal(s2, ref)


def test_underflow_guard():
    """A configuration where a 2x2 product underflows to 0 and float64 det, with Shewchuk's
    bound alone, would confidently return the wrong sign (the bound assumes no underflow)."""
    d = np.zeros(3)
    a = np.array([2.0**59, 0.0, 2.0**600])
    b = np.array([2.0**-540, 0.0, 1.0])
    c = np.array([0.0, 2.0**-540, 0.0])
    # exact: det[a-d, b-d, c-d] = 2**-480 - 2**-481 > 0 (Shewchuk's sign); float64 sees -2**-481
    ad, bd, cd = (x - d for x in (a, b, c))
    det, perm = P._shewchuk_det(ad[None], bd[None], cd[None])
    assert det[0] < 0 and abs(det[0]) > P.O3D_ERRBOUND_A * perm[0]  # unguarded filter: wrong
    assert exact_orient(a, b, c, d) == -1  # jtet sign = -(Shewchuk's sign) = -1
    assert orient3d(a, b, c, d) == -1
    _, decided = P._orient3d_filter(a[None], b[None], c[None], d[None])
    assert not decided[0]
    # mixed into a batch of ordinary queries too: a few (each query tested directly) and
    # many (the batch's bit patterns reduced first)
    rng = np.random.default_rng(0)
    for size in (50, P.FEW_QUERIES + 100):
        A, B, C, D = rng.random((4, size, 3))
        A[17], B[17], C[17], D[17] = a, b, c, d
        _, decided = P._orient3d_filter(A, B, C, D)
        assert not decided[17] and decided.sum() >= size - 5
        np.testing.assert_array_equal(orient3d(A, B, C, D), exact_orients(A, B, C, D))


def test_exact_zero_shortcuts():
    # a repeated point; an axis-aligned flat configuration (permanent == 0, decided at once)
    a = np.array([[0.1, 0.2, 0.3], [0.0, 0.0, 5.0]])
    b = np.array([[0.1, 0.2, 0.3], [1.0, 0.3, 5.0]])
    c = np.array([[0.7, 0.2, 0.9], [0.4, 1.0, 5.0]])
    d = np.array([[0.5, 0.5, 0.5], [7.0, 3.0, 5.0]])
    sign, decided = P._orient3d_filter(a, b, c, d)
    assert not decided[0]  # repeated point: float64 det is 0 but that proves nothing
    assert decided[1] and sign[1] == 0  # axis-aligned flat: permanent == 0, exact zero
    np.testing.assert_array_equal(orient3d(a, b, c, d), [0, 0])


def test_orient3d_tets():
    mesh = delaunay_mesh(150, seed=2)
    pts, tets = mesh.points, mesh.tets
    assert (orient3d_tets(pts, tets) == 1).all()
    flipped = tets[:, [1, 0, 2, 3]]
    assert (orient3d_tets(pts, flipped) == -1).all()
    # a flat tet on the (rotated, rounded) plane through three mesh points
    grid = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1]], float)
    t = np.array([[0, 1, 2, 3], [0, 1, 2, 4], [0, 2, 1, 4]])
    np.testing.assert_array_equal(orient3d_tets(grid, t), [0, 1, -1])
    rng = np.random.default_rng(1)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    rot = grid @ q.T
    np.testing.assert_array_equal(
        orient3d_tets(rot, t), exact_orients(*(rot[t[:, i]] for i in range(4)))
    )


# ------------------------------------------------------------------------------------------
# segment_crosses_triangle
# ------------------------------------------------------------------------------------------


def _orient2d(u, v, w):
    return (v[0] - u[0]) * (w[1] - u[1]) - (v[1] - u[1]) * (w[0] - u[0])


def _segment_distance_is_zero(P0, P1, U, V) -> bool:
    """Exact: does closed segment P0P1 meet closed segment UV (3D)? via the exact min of
    |P0 + t (P1-P0) - U - s (V-U)|^2 over the unit square (convex QP, candidates enumerated)."""
    d1 = [P1[i] - P0[i] for i in range(3)]
    d2 = [V[i] - U[i] for i in range(3)]
    r = [P0[i] - U[i] for i in range(3)]

    def dot(x, y):
        return sum(x[i] * y[i] for i in range(3))

    def f(t, s):
        w = [r[i] + t * d1[i] - s * d2[i] for i in range(3)]
        return dot(w, w)

    def clamp(x):
        return min(max(x, Fraction(0)), Fraction(1))

    a11, a22, a12 = dot(d1, d1), dot(d2, d2), dot(d1, d2)
    cands = [(Fraction(t), Fraction(s)) for t in (0, 1) for s in (0, 1)]
    for t in (Fraction(0), Fraction(1)):  # minimize over s with t fixed
        if a22:
            cands.append((t, clamp(dot([r[i] + t * d1[i] for i in range(3)], d2) / a22)))
    for s in (Fraction(0), Fraction(1)):
        if a11:
            cands.append((clamp(-dot([r[i] - s * d2[i] for i in range(3)], d1) / a11), s))
    det = a11 * a22 - a12 * a12
    if det:  # interior critical point
        b1, b2 = -dot(r, d1), dot(r, d2)
        t = (b1 * a22 + a12 * b2) / det
        s = (a11 * b2 + a12 * b1) / det
        if 0 <= t <= 1 and 0 <= s <= 1:
            cands.append((t, s))
    return min(f(t, s) for t, s in cands) == 0


def ref_cross(p, q, a, b, c) -> int:
    """Independent exact reference: plane crossing parameter + barycentric coordinates;
    coplanar: Cyrus-Beck clipping of pq against the triangle; degenerate triangle: exact
    segment-segment distance."""
    Pp, Qq, A, B, C = _ints(p, q, a, b, c)
    ab = [B[i] - A[i] for i in range(3)]
    ac = [C[i] - A[i] for i in range(3)]
    n = [
        ab[1] * ac[2] - ab[2] * ac[1],
        ab[2] * ac[0] - ab[0] * ac[2],
        ab[0] * ac[1] - ab[1] * ac[0],
    ]
    if n == [0, 0, 0]:  # degenerate triangle: the hull of its two farthest vertices
        pairs = [(A, B), (B, C), (A, C)]
        U, V = max(pairs, key=lambda uv: sum((uv[0][i] - uv[1][i]) ** 2 for i in range(3)))
        as_frac = [[Fraction(x) for x in X] for X in (Pp, Qq, U, V)]
        return -1 if _segment_distance_is_zero(*as_frac) else 0
    sp = sum(n[i] * (Pp[i] - A[i]) for i in range(3))
    sq = sum(n[i] * (Qq[i] - A[i]) for i in range(3))
    if sp * sq > 0:
        return 0
    k = max(range(3), key=lambda i: abs(n[i]))  # drop axis k: an affine bijection of the plane

    def proj(X):
        return [X[i] for i in range(3) if i != k]

    A2, B2, C2 = proj(A), proj(B), proj(C)
    area = _orient2d(A2, B2, C2)
    assert area != 0
    if sp == 0 and sq == 0:  # coplanar: clip t in [0, 1] by the three edge half-planes
        P2, Q2 = proj(Pp), proj(Qq)
        lo, hi = Fraction(0), Fraction(1)
        for u, v in ((A2, B2), (B2, C2), (C2, A2)):
            f0 = _orient2d(u, v, P2) * (1 if area > 0 else -1)
            f1 = _orient2d(u, v, Q2) * (1 if area > 0 else -1)
            delta = f1 - f0
            if delta == 0:
                if f0 < 0:
                    return 0
            elif delta > 0:
                lo = max(lo, Fraction(-f0, delta))
            else:
                hi = min(hi, Fraction(-f0, delta))
        return -1 if lo <= hi else 0
    # X = p + t (q - p), t = sp / (sp - sq), i.e. X = XD / D with integer XD = sp q - sq p and
    # D = sp - sq != 0; barycentric coordinate of X w.r.t. a = orient2d(X, b, c) / area, and
    # orient2d(XD, D b, D c) = D^2 orient2d(X, b, c): same sign, no division needed.
    D = sp - sq
    XD = proj([sp * Qq[i] - sq * Pp[i] for i in range(3)])
    A2D, B2D, C2D = ([D * x for x in X] for X in (A2, B2, C2))
    orients = [_orient2d(XD, B2D, C2D), _orient2d(A2D, XD, C2D), _orient2d(A2D, B2D, XD)]
    lam_signs = [((o > 0) - (o < 0)) * (1 if area > 0 else -1) for o in orients]
    if min(lam_signs) < 0:
        return 0
    if sp * sq < 0 and min(lam_signs) > 0:
        return 1
    return -1


def ref_crosses(p, q, a, b, c) -> np.ndarray:
    arrs = np.broadcast_arrays(*(np.asarray(x, float).reshape(-1, 3) for x in (p, q, a, b, c)))
    return np.array([ref_cross(*x) for x in zip(*arrs, strict=True)], dtype=np.int8)


def test_segment_hand_cases():
    a, b, c = np.array([0.0, 0, 0]), np.array([4.0, 0, 0]), np.array([0.0, 4, 0])
    cases = [
        ((1, 1, -1), (1, 1, 1), 1),  # proper crossing
        ((1, 1, 1), (1, 1, -1), 1),
        ((1, 1, 1), (1, 1, 2), 0),  # same side
        ((5, 5, -1), (5, 5, 1), 0),  # crosses the plane outside
        ((0, 0, -1), (0, 0, 1), -1),  # through vertex a
        ((2, 0, -1), (2, 0, 1), -1),  # through edge ab
        ((2, 2, -1), (2, 2, 1), -1),  # through edge bc
        ((1, 1, 0), (1, 1, 3), -1),  # endpoint in the open triangle
        ((9, 9, 0), (1, 1, 3), 0),  # endpoint on the plane, outside
        ((-1, 1, 0), (1, 1, 0), -1),  # coplanar, overlapping
        ((-1, -1, 0), (-3, 2, 0), 0),  # coplanar, disjoint
        ((3, 3, 0), (5, 5, 0), 0),  # coplanar, beyond edge bc
        ((2, 2, 0), (5, 5, 0), -1),  # coplanar, touches edge bc
        ((1, 1, 0), (1, 1, 0), -1),  # a point segment inside
        ((1, 1, 1), (1, 1, 1), 0),  # a point segment off the plane
    ]
    p = np.array([x[0] for x in cases], float)
    q = np.array([x[1] for x in cases], float)
    expected = np.array([x[2] for x in cases], np.int8)
    got = segment_crosses_triangle(p, q, a, b, c)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(ref_crosses(p, q, a, b, c), expected)
    # degenerate (collinear) triangles
    deg = (np.array([0.0, 0, 0]), np.array([2.0, 0, 0]), np.array([4.0, 0, 0]))
    assert segment_crosses_triangle([3, 1, 1], [3, -1, -1], *deg) == -1
    assert segment_crosses_triangle([5, 1, 1], [5, -1, -1], *deg) == 0
    assert segment_crosses_triangle([1, 1, 0], [1, 2, 0], *deg) == 0
    assert segment_crosses_triangle([1, 0, 0], [9, 0, 0], *deg) == -1
    pt = (np.array([1.0, 1, 1]),) * 3
    assert segment_crosses_triangle([0, 0, 0], [2, 2, 2], *pt) == -1
    assert segment_crosses_triangle([0, 0, 0], [2, 2, 3], *pt) == 0
    assert isinstance(segment_crosses_triangle([1, 1, -1], [1, 1, 1], a, b, c), np.int8)


@SETTINGS
@given(seeds, st.sampled_from([1.0, 0.5, 0.1, 3.0]), st.sampled_from([1, 2]))
def test_segment_integer_grid(seed, scale, radius):
    """Small integer grids: full of coplanar, collinear, through-vertex/edge configurations."""
    rng = np.random.default_rng(seed)
    p, q, a, b, c = rng.integers(-radius, radius + 1, (5, 8, 3)) * scale
    # symmetric in p <-> q and in any permutation of the triangle's vertices (one call)
    variants = [(p, q, a, b, c), (q, p, a, b, c), (p, q, c, a, b), (p, q, b, a, c)]
    stacked = [np.concatenate(x) for x in zip(*variants, strict=True)]
    got = segment_crosses_triangle(*stacked).reshape(len(variants), -1)
    np.testing.assert_array_equal(got[0], ref_crosses(p, q, a, b, c))
    assert (got == got[0]).all()


@SETTINGS
@given(seeds)
def test_segment_random(seed):
    rng = np.random.default_rng(seed)
    p, q, a, b, c = rng.uniform(-1, 1, (5, 8, 3))
    np.testing.assert_array_equal(
        segment_crosses_triangle(p, q, a, b, c), ref_crosses(p, q, a, b, c)
    )


def through_feature(rng, n, mode):
    """Segments through a vertex, an edge point or an interior point of integer triangles, or
    with an endpoint there (exact dyadic arithmetic, so the degeneracies are exact)."""
    a, b, c = rng.integers(-3, 4, (3, n, 3)).astype(float)
    weights = np.array([(1, 0, 0), (0.5, 0.5, 0), (0.25, 0.25, 0.5), (0.75, 0.25, 0)])
    w = rng.permuted(weights[rng.integers(0, 4, n)], axis=1)
    x = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
    u = rng.integers(-3, 4, (n, 3)).astype(float)
    if mode == "through":
        return x + u, x - rng.choice([0.5, 1.0, 2.0], (n, 1)) * u, a, b, c
    if mode == "endpoint":
        return x, x + u, a, b, c
    return x + u + rng.integers(-3, 4, (n, 3)) / 8, x - u, a, b, c


@SETTINGS
@given(seeds, st.sampled_from(["through", "endpoint", "shifted"]))
def test_segment_through_features(seed, mode):
    p, q, a, b, c = through_feature(np.random.default_rng(seed), 8, mode)
    got = segment_crosses_triangle(p, q, a, b, c)
    np.testing.assert_array_equal(got, ref_crosses(p, q, a, b, c))


def test_segment_large_mixed_batch():
    """One big vectorized call mixing all classes (indexing of the sub-batches)."""
    rng = np.random.default_rng(5)
    n = 3000
    p, q, a, b, c = (rng.integers(-2, 3, (n, 3)).astype(float) for _ in range(5))
    got = segment_crosses_triangle(p, q, a, b, c)
    assert set(np.unique(got).tolist()) == {-1, 0, 1}
    np.testing.assert_array_equal(got, ref_crosses(p, q, a, b, c))
    # near-degenerate: rotated copies (rounded) of the same configurations
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    p, q, a, b, c = (x[:600] @ Q.T for x in (p, q, a, b, c))
    np.testing.assert_array_equal(
        segment_crosses_triangle(p, q, a, b, c), ref_crosses(p, q, a, b, c)
    )


def test_segment_broadcasting():
    rng = np.random.default_rng(2)
    a, b, c = rng.uniform(-1, 1, (3, 40, 3))
    p, q = np.array([0.0, 0.0, -3.0]), np.array([0.0, 0.0, 3.0])
    got = segment_crosses_triangle(p, q, a, b, c)
    assert got.shape == (40,)
    np.testing.assert_array_equal(got, ref_crosses(p, q, a, b, c))


def test_orient3d_stacked_equals_each_group_exactly():
    """Groups of queries in one call give each group's exact signs, in group order
    (near-coplanar queries, so the later stages run too)."""
    rng = np.random.default_rng(3)
    groups = []
    for _ in range(3):
        a, b, c = rng.random((3, 40, 3))
        d = a + 0.5 * (b - a) + 0.25 * (c - a)  # on the plane, up to rounding
        d[::2] = rng.random((20, 3))
        groups.append((a, b, c, d))
    got = P.orient3d_stacked(groups)
    assert got.shape == (3, 40)
    for g, (a, b, c, d) in enumerate(groups):
        np.testing.assert_array_equal(got[g], exact_orients(a, b, c, d))
