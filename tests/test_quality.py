"""Quality measures (jtet._quality) against closed forms and an independent NumPy reference.

Tolerances. The measures are dimensionless and normalized to 1 for the regular tet. Two
float64 implementations of the same quantity differ by round-off that is relative to the
*data*, not to the result: the signed volume 6V is computed with an absolute error of a
few eps * L^3 (L: longest edge), a face normal (length 2 * area) with a few eps * L^2.
Every measure is proportional to V (the mean ratio to V^(2/3)) for a flat tet, so it
inherits a relative error ~ eps * kv with kv = L^3 / |6V|; the dihedral angles and the
min sine, computed from normals, an absolute error ~ eps * kf with kf = L^2 / (smallest
normal). A well-shaped tet has kv, kf ~ 1-10; a sliver of relative thickness h has
kv ~ 1/h, a wedge or needle kf ~ 1/h. So every comparison with the reference asserts

    |q - q_ref| <= 1e-12 * |q_ref| + 64 * eps * (kv * |q_ref| + kf)

that is 1e-12 relative where the problem is well conditioned, and a bound proportional to
the condition number where it is not (64 eps covers the few dozen rounded operations; the
largest measured ratio error / (eps * condition) is ~0.6).
"""

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import REGULAR_TET

import jtet  # noqa: F401  (float64)
from jtet._predicates import orient3d_tets
from jtet._quality import (
    MEASURES,
    _atan2_nonneg,
    _cbrt_nonneg,
    dihedral_angles,
    get_measure,
    signed_volume,
    tet_all_measures,
    tet_dihedrals,
    tet_quality,
)

EPS = np.finfo(np.float64).eps
NAMES = sorted(MEASURES)
REG = REGULAR_TET[[1, 0, 2, 3]]  # helpers' regular tet is negatively oriented
CORNER = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
# faces as the tet's boundary chain: outward normals for a positive tet
FACES = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))


# ------------------------------------------------------------------ helpers


def soa(P):
    """(k, 4, 3) corner array -> the four SoA points of jtet._quality."""
    P = np.asarray(P, np.float64)
    return tuple(tuple(jnp.asarray(P[:, v, c]) for c in range(3)) for v in range(4))


def quality(P, name):
    return np.asarray(jax.jit(MEASURES[name])(*soa(P)))


def dihedrals(P):
    return np.stack([np.asarray(a) for a in jax.jit(dihedral_angles)(*soa(P))], axis=1)


def random_rotation(rng):
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def random_tets(rng, k):
    """k generic tets (uniform corners) + k near-degenerate ones, randomly rotated.

    Near-degenerate: flat (4 points near a plane), wedges (2 points close), caps (a point
    near the opposite face), needles (4 points near a line) and slivers (4 points near a
    circle, the Delaunay kind), perturbed by h = 10^-U(1, 12) (needles 10^-U(1, 6)). The
    floor keeps |6V| (~h L^3, ~h^2 L^3 for needles) far above its round-off (~eps L^3), so
    the sign of every tet is decidable in floating point.
    """
    gen = rng.random((k, 4, 3))
    kind = rng.integers(0, 5, k)
    base = rng.random((k, 4, 3))
    base[kind == 0, :, 2] = 0.5
    base[kind == 1, 1] = base[kind == 1, 0]
    t = rng.random((k, 4, 1))
    nd = kind == 2
    base[nd] = base[nd, :1] + t[nd] * (base[nd, 1:2] - base[nd, :1])
    base[kind == 3, 3] = base[kind == 3, :3].mean(axis=1)
    sl = kind == 4
    th = rng.uniform(0, 2 * np.pi, (sl.sum(), 4))
    base[sl] = 0.5 * np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], -1)
    h = 10.0 ** -rng.uniform(1, np.where(nd, 6, 12))[:, None, None]
    near = base + h * rng.standard_normal((k, 4, 3))
    rot = np.stack([random_rotation(rng) for _ in range(k)])
    near = np.einsum("kij,kvj->kvi", rot, near)
    return np.concatenate([gen, near])


def reference(P):
    """Independent NumPy formulas (k, 4, 3) -> dict of measures, cos and sin of dihedrals.

    Volume by np.linalg.det; dihedral angles from outward face normals (np.cross); the
    circumradius by solving the 3x3 linear system 2 (p_i - p0) . c = |p_i - p0|^2; the
    inradius from volume and face areas; the mean ratio from the Jacobian S = J W^-1
    relative to the unit regular tet: 3 |det S|^(2/3) / |S|_F^2. Signs from the exact
    orientation predicate. Also returns the condition numbers kv, kf (module docstring).
    """
    P = np.asarray(P, np.float64)
    k = len(P)
    J = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]], axis=-1)
    vol = np.abs(np.linalg.det(J)) / 6.0
    sign = orient3d_tets(P.reshape(-1, 3), np.arange(4 * k).reshape(k, 4)).astype(float)
    n = np.stack([np.cross(P[:, b] - P[:, a], P[:, c] - P[:, a]) for a, b, c in FACES], 1)
    nlen = np.linalg.norm(n, axis=-1)
    cos, sin = [], []
    for i, j in EDGES:
        f, g = (v for v in range(4) if v not in (i, j))  # faces opposite the other two
        den = nlen[:, f] * nlen[:, g]
        cos.append(-np.einsum("ij,ij->i", n[:, f], n[:, g]) / den)
        sin.append(np.linalg.norm(np.cross(n[:, f], n[:, g]), axis=-1) / den)
    cos, sin = np.stack(cos, 1), np.stack(sin, 1)
    out = {"min_sine": sign * sin.min(axis=1) / (2 * math.sqrt(2) / 3)}
    biased = np.where(cos < 0, 0.7 * sin, sin)  # obtuse angles count 0.7 times
    out["biased_min_sine"] = sign * biased.min(axis=1) / (2 * math.sqrt(2) / 3)
    r_in = 3 * vol / (nlen.sum(axis=1) / 2)
    E = np.transpose(J, (0, 2, 1))  # rows p_i - p0
    centre = np.linalg.solve(2 * E, np.einsum("kij,kij->ki", E, E)[..., None])[..., 0]
    out["radius_ratio"] = sign * 3 * r_in / np.linalg.norm(centre, axis=-1)
    lrms = np.sqrt(np.mean([np.sum((P[:, j] - P[:, i]) ** 2, -1) for i, j in EDGES], axis=0))
    out["vol_length"] = sign * 6 * math.sqrt(2) * vol / lrms**3
    W = np.array([[1, 0.5, 0.5], [0, math.sqrt(3) / 2, math.sqrt(3) / 6], [0, 0, math.sqrt(2 / 3)]])
    S = J @ np.linalg.inv(W)
    out["mean_ratio"] = sign * 3 * np.abs(np.linalg.det(S)) ** (2 / 3) / np.sum(S**2, axis=(1, 2))
    lmax = np.sqrt(np.max([np.sum((P[:, j] - P[:, i]) ** 2, -1) for i, j in EDGES], 0))
    kv = lmax**3 / (6 * vol)
    kf = lmax**2 / nlen.min(1)
    return out, cos, sin, (kv, kf)


def assert_close_cond(q, ref, cond, what):
    kv, kf = cond
    tol = 1e-12 * np.abs(ref) + 64 * EPS * (kv * np.abs(ref) + kf)
    bad = ~(np.abs(q - ref) <= tol)
    assert not bad.any(), (
        f"{what}: {bad.sum()} tets disagree, e.g. {q[bad][:3]} vs {ref[bad][:3]} "
        f"(kv {kv[bad][:3]}, kf {kf[bad][:3]})"
    )


# ------------------------------------------------------------------ closed forms


@pytest.mark.parametrize("name", NAMES)
def test_regular_tet_is_one(name, rng):
    P = np.stack([REG, 0.37 * REG @ random_rotation(rng).T + [5.0, -2.0, 1.0]])
    np.testing.assert_allclose(quality(P, name), 1.0, rtol=0, atol=1e-12)


def test_regular_tet_dihedrals():
    np.testing.assert_allclose(
        dihedrals(REG[None]), np.degrees(np.arccos(1 / 3)), rtol=0, atol=1e-12
    )


def test_right_corner_tet():
    # V = 1/6; edges 1,1,1,sqrt2,sqrt2,sqrt2; faces 1/2 x3 and sqrt3/2;
    # circumcentre (1/2,1/2,1/2), R = sqrt3/2; inradius 1/(3+sqrt3);
    # dihedral angles 90 at the three edges at the corner, arccos(1/sqrt3) at the others.
    expected = {
        "min_sine": math.sqrt(2 / 3) / (2 * math.sqrt(2) / 3),  # = sqrt3/2
        "radius_ratio": math.sqrt(3) - 1,
        "vol_length": math.sqrt(2) / 1.5**1.5,
        "mean_ratio": 12 * 0.5 ** (2 / 3) / 9,
    }
    for name, value in expected.items():
        np.testing.assert_allclose(quality(CORNER[None], name), value, rtol=1e-14)
    a = math.degrees(math.acos(1 / math.sqrt(3)))
    np.testing.assert_allclose(dihedrals(CORNER[None])[0], [90, 90, 90, a, a, a], rtol=1e-14)
    np.testing.assert_allclose(np.asarray(signed_volume(*soa(CORNER[None]))), 1 / 6)


FLAT = {
    "square (cocircular: radius ratio 0/0)": [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]],
    "generic coplanar": [[0, 0, 0], [3, 1, 0], [1, 2, 0], [2, 5, 0]],
    "tilted plane x+y+z=1": [[1, 0, 0], [0, 1, 0], [0, 0, 1], [2, -1, 0]],
    "three collinear": [[0, 0, 0], [1, 1, 1], [2, 2, 2], [0, 1, 0]],
    "four collinear": [[0, 0, 0], [1, 2, 3], [2, 4, 6], [-1, -2, -3]],
    "coincident pair": [[0, 0, 0], [0, 0, 0], [1, 0, 0], [0, 1, 1]],
    "all coincident": [[1, 2, 3]] * 4,
}


@pytest.mark.parametrize("name", NAMES)
def test_flat_tets_are_exactly_zero(name):
    P = np.array(list(FLAT.values()), np.float64)
    q = quality(P, name)
    assert np.all(q == 0.0), dict(zip(FLAT, q, strict=True))
    assert np.isfinite(dihedrals(P)).all()


# ------------------------------------------------------------------ symmetries


def well_shaped(rng, k=2000):
    P = rng.random((k, 4, 3))
    return P[np.abs(reference(P)[0]["vol_length"]) > 0.2]


@pytest.mark.parametrize("name", NAMES)
def test_swapping_two_vertices_negates(name, rng):
    P = random_tets(rng, 500)
    q = quality(P, name)
    cond = reference(P)[3]
    for i, j in itertools.combinations(range(4), 2):
        perm = list(range(4))
        perm[i], perm[j] = j, i
        assert_close_cond(quality(P[:, perm], name), -q, cond, f"{name} swap {i}{j}")
    # even permutations keep the value
    assert_close_cond(quality(P[:, [1, 2, 0, 3]], name), q, cond, f"{name} 3-cycle")


@pytest.mark.parametrize("name", NAMES)
def test_invariance(name, rng):
    P = well_shaped(rng)
    q = quality(P, name)
    R = random_rotation(rng)
    np.testing.assert_allclose(quality(P @ R.T, name), q, rtol=1e-12)
    np.testing.assert_allclose(quality(P + [10.0, -7.0, 3.0], name), q, rtol=1e-12)
    np.testing.assert_allclose(quality(P * 1e-3, name), q, rtol=1e-12)
    np.testing.assert_allclose(quality(P * 1e4, name), q, rtol=1e-12)
    # scaling by a power of two is exact in floating point: so is the measure
    np.testing.assert_array_equal(quality(P * 2.0**-20, name), q)
    np.testing.assert_array_equal(quality(P * 2.0**30, name), q)


def test_dihedral_invariance(rng):
    P = well_shaped(rng)
    a = dihedrals(P)
    R = random_rotation(rng)
    np.testing.assert_allclose(dihedrals(1e3 * P @ R.T + 4.0), a, rtol=1e-11)
    # a vertex swap permutes the angles: edge 01 stays, 02 <-> 12, 03 <-> 13, 23 stays
    np.testing.assert_allclose(dihedrals(P[:, [1, 0, 2, 3]]), a[:, [0, 3, 4, 1, 2, 5]], rtol=1e-12)


# ------------------------------------------------------------------ independent reference


@pytest.fixture(scope="module")
def random_set():
    P = random_tets(np.random.default_rng(7), 5000)  # 10k tets
    return P, reference(P)


@pytest.mark.parametrize("name", NAMES)
def test_matches_numpy_reference(name, random_set):
    P, (ref, _, _, cond) = random_set
    q = quality(P, name)
    assert_close_cond(q, ref[name], cond, name)
    # the reference signs are exact (orient3d); the measures must agree with them
    assert np.array_equal(np.sign(q), np.sign(ref[name]))


def test_dihedrals_match_numpy_reference(random_set):
    P, (_, cos, sin, (_, kf)) = random_set
    a = np.radians(dihedrals(P))
    cond = (0.0, kf[:, None])  # computed from normals only: no volume conditioning
    assert_close_cond(np.cos(a), cos, cond, "cos dihedral")
    assert_close_cond(np.sin(a), sin, cond, "sin dihedral")
    # and against arccos of the normals' dot product where arccos is well conditioned
    ok = (np.abs(cos) < 0.999) & (kf[:, None] < 100)
    np.testing.assert_allclose(a[ok], np.arccos(cos[ok]), rtol=0, atol=1e-11)


def test_cbrt_nonneg(rng):
    x = np.concatenate([10.0 ** rng.uniform(-307, 307, 10000), [0.0, 1.0, 8.0, 27.0]])
    y = np.asarray(jax.jit(_cbrt_nonneg)(jnp.asarray(x)))
    r = np.cbrt(x)
    np.testing.assert_allclose(y, r, rtol=4 * EPS, atol=0)
    assert y[-4] == 0.0


def test_atan2_nonneg(rng):
    n = 100000
    y = np.abs(rng.standard_normal(n)) * 10.0 ** rng.uniform(-30, 30, n)
    x = rng.standard_normal(n) * 10.0 ** rng.uniform(-30, 30, n)
    y[:3], x[:3] = 0.0, [0.0, 1.0, -1.0]  # 0, 0, pi
    x[3:6], y[3:6] = 0.0, [1.0, 2.0, 1e-300]  # pi/2
    x[6:9], y[6:9] = [1.0, -1.0, 2.0], [1.0, 1.0, 2.0]  # pi/4, 3pi/4, pi/4 (the t = 1 edge)
    got = np.asarray(jax.jit(_atan2_nonneg)(jnp.asarray(y), jnp.asarray(x)))
    np.testing.assert_allclose(got, np.arctan2(y, x), rtol=0, atol=2 * EPS * np.pi)
    assert got[0] == 0.0 and got[1] == 0.0 and got[2] == np.pi


# ------------------------------------------------------------------ vmap / jit / host helpers


@pytest.mark.parametrize("name", NAMES + ["dihedral"])
def test_vmap_soa_loop_and_jit_agree(name, rng):
    P = random_tets(rng, 16)
    fn = dihedral_angles if name == "dihedral" else get_measure(name)

    def one(p):  # ONE tet: p (4, 3) -> scalar (or 6 angles)
        out = fn(*[(p[v, 0], p[v, 1], p[v, 2]) for v in range(4)])
        return jnp.stack(out) if name == "dihedral" else out

    batch = jnp.asarray(P)
    vm = np.asarray(jax.jit(jax.vmap(one))(batch))
    soa_jit = jax.jit(fn)(*soa(P))
    soa_eager = fn(*soa(P))
    if name == "dihedral":
        soa_jit, soa_eager = np.stack(soa_jit, 1), np.stack(soa_eager, 1)
    loop = np.stack([np.asarray(jax.jit(one)(batch[i])) for i in range(len(P))])
    loop_eager = np.stack([np.asarray(one(batch[i])) for i in range(4)])
    # Same formula, but XLA fuses (and contracts a*b+c into FMAs) differently under jit, vmap
    # and eager op-by-op dispatch: the results agree to round-off, i.e. within the
    # conditioning bound of the module docstring (bitwise for well-shaped tets).
    _, _, _, (kv, kf) = reference(P)
    if name == "dihedral":
        cond, scale = (0.0, kf[:, None]), math.pi / 180  # compare in radians
    else:
        cond, scale = (kv, kf), 1.0
    ref = np.asarray(soa_jit) * scale
    assert_close_cond(vm * scale, ref, cond, "vmap vs SoA")
    assert_close_cond(loop * scale, ref, cond, "loop vs SoA")
    assert_close_cond(np.asarray(soa_eager) * scale, ref, cond, "no jit vs jit")
    c4 = tuple(np.asarray(c)[:4] if np.ndim(c) else c for c in cond)
    assert_close_cond(loop_eager * scale, ref[:4], c4, "eager loop vs SoA")


def test_host_helpers_on_a_mesh(rng):
    """The host helpers (one fused kernel for every measure and the dihedral angles, in
    padded calls) against each function jitted alone on the same tets: equal, or within
    an ulp where fusion orders operations differently."""
    P = random_tets(rng, 700)  # 1400 tets: not a bucket size, so padding is exercised
    points = P.reshape(-1, 3)
    tets = rng.permutation(len(points)).reshape(-1, 4)
    corners = points[tets]
    angles, lo, hi, qs = tet_all_measures(points, tets)
    assert sorted(qs) == NAMES
    for name in NAMES:
        # measures are O(1) (regular tet = 1): a reordered sum is off by ~eps absolutely,
        # also for slivers whose quality is tiny
        np.testing.assert_allclose(qs[name], quality(corners, name), rtol=0, atol=2 * EPS)
        np.testing.assert_array_equal(tet_quality(points, tets, name), qs[name])
    np.testing.assert_allclose(angles, dihedrals(corners), rtol=2 * EPS, atol=0)
    np.testing.assert_array_equal(lo, angles.min(1))
    np.testing.assert_array_equal(hi, angles.max(1))
    for got, want in zip(tet_dihedrals(points, tets), (angles, lo, hi), strict=True):
        np.testing.assert_array_equal(got, want)


def test_small_calls_give_the_values_of_large_ones(rng, monkeypatch):
    """An evaluation of at most SMALL_TET_CHUNK tets runs in calls of that size, a larger
    one in calls of TET_CHUNK: the optimizer mixes both (whole-mesh values, then the few
    tets each step changed), so every tet must get the same bits from either."""
    from jtet import _quality

    P = random_tets(rng, 2500)  # 5000 tets: two large calls
    points = P.reshape(-1, 3)
    tets = rng.permutation(len(points)).reshape(-1, 4)
    sizes = []  # the tets per kernel call of each evaluation
    real_call = _quality.cached_call

    def spy(name, settings, fn, *args):
        sizes.append(args[0].shape[0])
        return real_call(name, settings, fn, *args)

    monkeypatch.setattr(_quality, "cached_call", spy)
    whole = tet_all_measures(points, tets)
    assert set(sizes) == {_quality.TET_CHUNK}
    for part in (np.arange(1), np.arange(300), rng.choice(len(tets), 512, replace=False)):
        sizes.clear()
        small = tet_all_measures(points, tets[part])
        assert sizes == [_quality.SMALL_TET_CHUNK] and _quality.SMALL_TET_CHUNK < _quality.TET_CHUNK
        for got, want in zip(small[:3], whole[:3], strict=True):
            np.testing.assert_array_equal(got, want[part])
        for name in NAMES:
            np.testing.assert_array_equal(small[3][name], whole[3][name][part])


def test_unknown_measure():
    with pytest.raises(jtet.JtetError, match="min_sine"):
        get_measure("nope")


def test_mesh_volumes_match_a_determinant_reference(rng):
    """TetMesh.volumes (the statistics' volume) against det[p1 - p0, p2 - p0, p3 - p0] / 6
    of NumPy's LU determinant, tet by tet; relative 1e-12 of the tet's edge lengths cubed
    (both are a few float64 roundings of products of coordinate differences)."""
    points = rng.normal(size=(60, 3)) * 10.0 ** rng.uniform(-3, 3, size=(60, 1))
    tets = np.array([rng.choice(60, 4, replace=False) for _ in range(200)])
    mesh = jtet.TetMesh(points, tets)
    p = points[tets]
    edges = p[:, 1:] - p[:, :1]
    ref = np.linalg.det(edges) / 6.0
    scale = np.linalg.norm(edges, axis=2).prod(axis=1)
    assert np.all(np.abs(mesh.volumes - ref) <= 1e-12 * scale)
    assert np.array_equal(np.sign(mesh.volumes), np.sign(orient3d_tets(points, tets)))
