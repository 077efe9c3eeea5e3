"""Tetrahedron quality measures, written for ONE tet in structure-of-arrays form.

Every function takes the four corners ``p0, p1, p2, p3`` of a tet, each a tuple
``(x, y, z)`` of arrays of the same (broadcastable) shape, and returns an array of
that shape. Written per component on purpose: the same code evaluates one tet or a
whole SoA batch elementwise (and is trivially ``vmap``-able), and measured 10-60x
faster than ``(..., 3)`` vectors with ``jnp.cross`` (see DESIGN.md).

Orientation convention (the one of VTK and pyvista): a tet ``(p0, p1, p2, p3)`` is
correctly oriented when its signed volume ``det[p1-p0, p2-p0, p3-p0] / 6`` is positive,
i.e. ``p0, p1, p2`` appear counterclockwise seen from ``p3``. Every measure is
normalized to 1 for the regular tet, positive for a correctly oriented tet, zero for a
degenerate (flat) one and negative for an inverted one, as Shewchuk's algorithms need.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import _config
from ._aot import cached_call, prefetch, warm_start
from ._errors import JtetError

Vec = tuple[Array, Array, Array]  # SoA point: (x, y, z), each of the same shape

# sin of the regular tet's dihedral angle arccos(1/3)
_SIN_REGULAR = 2.0 * math.sqrt(2.0) / 3.0


def _sub(p: Vec, q: Vec) -> Vec:
    return (p[0] - q[0], p[1] - q[1], p[2] - q[2])


def _cross(u: Vec, v: Vec) -> Vec:
    return (
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    )


def _dot(u: Vec, v: Vec) -> Array:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _norm(u: Vec) -> Array:
    return jnp.sqrt(_dot(u, u))


def _safe_div(num: Array, den: Array) -> Array:
    """num / den, and 0 where den == 0 (a degenerate tet has quality 0, not NaN)."""
    ok = den > 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


class _TetGeometry:
    """Shared intermediate quantities of one tet (SoA).

    ``d``: 6 * signed volume. ``edges``: six edge vectors in the order
    01, 02, 03, 12, 13, 23. ``normals``: outward (for a positive tet) face normals,
    length = 2 * face area, ``normals[i]`` for the face opposite vertex i.
    """

    # The two faces containing edge (i, j) are the faces opposite the other two vertices.
    EDGE_VERTS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    EDGE_FACES = ((2, 3), (1, 3), (1, 2), (0, 3), (0, 2), (0, 1))

    def __init__(self, p0: Vec, p1: Vec, p2: Vec, p3: Vec):
        e01, e02, e03 = _sub(p1, p0), _sub(p2, p0), _sub(p3, p0)
        e12, e13, e23 = _sub(p2, p1), _sub(p3, p1), _sub(p3, p2)
        self.edges = (e01, e02, e03, e12, e13, e23)
        self.d = _dot(e01, _cross(e02, e03))
        self.normals = (
            _cross(e12, e13),
            _cross(e03, e02),
            _cross(e01, e03),
            _cross(e02, e01),
        )

    def edge_lengths_sq(self) -> tuple[Array, ...]:
        return tuple(_dot(e, e) for e in self.edges)

    def normal_lengths(self) -> tuple[Array, ...]:
        return tuple(_norm(n) for n in self.normals)


def signed_volume(p0: Vec, p1: Vec, p2: Vec, p3: Vec) -> Array:
    """Signed volume (length^3): positive for a correctly oriented tet."""
    return _TetGeometry(p0, p1, p2, p3).d / 6.0


def min_sine(p0: Vec, p1: Vec, p2: Vec, p3: Vec) -> Array:
    """Smallest sine of the six dihedral angles, divided by the regular tet's, times sign(V).

    sin(theta_ij) = |N_k x N_l| / (|N_k| |N_l|) with N_k, N_l the normals of the two faces
    at edge ij. Small for both tiny and near-180-degree dihedral angles, so it catches
    every sliver. Mirror-symmetric: swapping two vertices negates it.
    """
    # Speed: the min is taken over squared sines (no sqrt, no per-edge norm), one sqrt at
    # the end. Robustness: the sine comes from the cross product of the two computed normals,
    # not from 6V * l / (|N_k||N_l|): for a nearly collinear tet 6V's round-off (~eps L^3)
    # is huge relative to the tiny normals and that identity returned values like 1e6.
    return _signed_min_sine(_TetGeometry(p0, p1, p2, p3), obtuse_bias=1.0)


def _signed_min_sine(g: _TetGeometry, obtuse_bias: float) -> Array:
    """sign(V) min over edges of sin(theta) (times ``obtuse_bias`` for obtuse angles),
    normalized by the regular tet's sine."""
    n = g.normals
    nsq = [_dot(v, v) for v in n]
    m = None
    for f0, f1 in _TetGeometry.EDGE_FACES:
        c = _cross(n[f0], n[f1])
        s2 = _safe_div(_dot(c, c), nsq[f0] * nsq[f1])
        if obtuse_bias != 1.0:
            # outward normals: the interior angle is obtuse when they point the same way
            # (an inverted tet flips both normals, so the test is orientation-independent)
            s2 = jnp.where(_dot(n[f0], n[f1]) > 0, (obtuse_bias * obtuse_bias) * s2, s2)
        m = s2 if m is None else jnp.minimum(m, s2)
    return jnp.sign(g.d) * jnp.sqrt(m) / _SIN_REGULAR


OBTUSE_BIAS = 0.7  # the sine of an obtuse dihedral angle counts 0.7 times (Stellar's bias)


def biased_min_sine(p0: Vec, p1: Vec, p2: Vec, p3: Vec) -> Array:
    """``min_sine`` with the sines of obtuse dihedral angles scaled by ``OBTUSE_BIAS``.

    Min sine rates a 140-degree angle like a 40-degree one; the bias (used by Klingner and
    Shewchuk's Stellar) makes the optimizer shrink large angles too, which lowers the
    maximum dihedral angle at little cost to the minimum. 1 for the regular tet (its
    dihedral angles are acute), signed like every measure.
    """
    return _signed_min_sine(_TetGeometry(p0, p1, p2, p3), obtuse_bias=OBTUSE_BIAS)


def radius_ratio(p0: Vec, p1: Vec, p2: Vec, p3: Vec) -> Array:
    """Normalized radius ratio 3 r_in / R_circ (signed).

    With a, b, c = p1-p0, p2-p0, p3-p0 and d = 6V: r_in = |d| / sum|N| and
    R_circ = |w| / (2|d|) for w = |a|^2 (b x c) + |b|^2 (c x a) + |c|^2 (a x b) (2d times
    the circumcentre's offset from p0); hence 3 r / R = 6 d |d| / (sum|N| |w|).
    """
    # b x c, c x a, a x b are -N1, -N2, -N3: w costs no new cross product. This replaced the
    # product-of-opposite-edges formula, whose Heron-like factor cancels catastrophically for
    # cocircular slivers (error ~ eps / h^2 at relative thickness h, so slivers thinner than
    # ~1e-8 came out 0 or over-estimated up to 2.6x); w's error is ~ eps / h. Also 3 fewer sqrt.
    g = _TetGeometry(p0, p1, p2, p3)
    lsq = g.edge_lengths_sq()
    n = g.normals
    w = tuple(lsq[0] * n[1][k] + lsq[1] * n[2][k] + lsq[2] * n[3][k] for k in range(3))
    nl = g.normal_lengths()
    den = (nl[0] + nl[1] + nl[2] + nl[3]) * _norm(w)
    return _safe_div(6.0 * g.d * jnp.abs(g.d), den)


def vol_length(p0: Vec, p1: Vec, p2: Vec, p3: Vec) -> Array:
    """Normalized volume-length ratio 6*sqrt(2) V / l_rms^3 (signed)."""
    g = _TetGeometry(p0, p1, p2, p3)
    lsq = g.edge_lengths_sq()
    msq = (lsq[0] + lsq[1] + lsq[2] + lsq[3] + lsq[4] + lsq[5]) / 6.0
    return _safe_div(math.sqrt(2.0) * g.d, msq * jnp.sqrt(msq))


def _cbrt_nonneg(x: Array) -> Array:
    """Cube root of x >= 0 (relative error < 1e-15) without the slow libm ``cbrt``.

    Start: the high 32 bits of x's IEEE pattern divided by 3 (a 3 % guess, exponent / 3),
    in 32-bit lanes so it vectorizes; then four Newton steps (3 % -> 1e-3 -> 1e-6 -> 1e-12
    -> round-off). Measured ~10x faster than ``jnp.cbrt`` under XLA on CPU. Denormal x
    (< 2.2e-308) gets a rough value of the right sign; 0 gives 0.
    """
    bits = jax.lax.bitcast_convert_type(x, jnp.int64)
    hi = (bits >> 32).astype(jnp.int32)
    y = jax.lax.bitcast_convert_type((hi // 3 + 0x2A9F7893).astype(jnp.int64) << 32, x.dtype)
    for _ in range(4):
        y = (2.0 * y + x / (y * y)) * (1.0 / 3.0)
    return jnp.where(x > 0, y, 0.0)


def mean_ratio(p0: Vec, p1: Vec, p2: Vec, p3: Vec) -> Array:
    """Mean ratio 12 (3|V|)^(2/3) / sum(l^2), with the sign of V."""
    g = _TetGeometry(p0, p1, p2, p3)
    lsq = g.edge_lengths_sq()
    ssq = lsq[0] + lsq[1] + lsq[2] + lsq[3] + lsq[4] + lsq[5]
    # 12 (|6V|/2)^(2/3) / ssq = 12 u^(2/3) with the dimensionless u = |6V| / (2 ssq^(3/2))
    # in [0, 12^(-3/2)]: no d^2 to overflow or underflow for extreme coordinate scales.
    u = _safe_div(jnp.abs(g.d), 2.0 * ssq * jnp.sqrt(ssq))
    c = _cbrt_nonneg(u)
    return 12.0 * jnp.sign(g.d) * (c * c)


# Cephes' atan: rational approximation on |x| <= 0.66, with atan(t) = pi/4 + atan((t-1)/(t+1))
# above; relative error ~1e-16.
_ATAN_P = (
    -8.750608600031904122785e-1,
    -1.615753718733365076637e1,
    -7.500855792314704667340e1,
    -1.228866684490136173410e2,
    -6.485021904942025371773e1,
)
_ATAN_Q = (
    2.485846490142306297962e1,
    1.650270098316988542046e2,
    4.328810604912902668951e2,
    4.853903996359136964868e2,
    1.945506571482613964425e2,
)
_PI_LO = 1.2246467991473532e-16  # pi - float(pi): keeps pi/2 - a and pi - a correctly rounded


def _atan2_nonneg(y: Array, x: Array) -> Array:
    """atan2(y, x) in radians for y >= 0 (so in [0, pi]); atan2(0, 0) = 0.

    Arithmetic only (error <= 2 ulp): XLA's CPU ``atan2`` is a scalar libm call, measured
    ~15x slower, and the dihedral kernel needs six per tet.
    """
    ax = jnp.abs(x)
    swap = y > ax  # reduce to t = min / max in [0, 1]
    num = jnp.where(swap, ax, y)
    den = jnp.where(swap, y, ax)
    t = _safe_div(num, den)
    big = t > 0.66
    u = jnp.where(big, (t - 1.0) / (t + 1.0), t)
    z = u * u
    p = (((_ATAN_P[0] * z + _ATAN_P[1]) * z + _ATAN_P[2]) * z + _ATAN_P[3]) * z + _ATAN_P[4]
    q = ((((z + _ATAN_Q[0]) * z + _ATAN_Q[1]) * z + _ATAN_Q[2]) * z + _ATAN_Q[3]) * z + _ATAN_Q[4]
    a = u * (z * p / q) + u
    a = jnp.where(big, (math.pi / 4 + 0.25 * _PI_LO) + a, a)
    a = jnp.where(swap, (math.pi / 2 + 0.5 * _PI_LO) - a, a)
    return jnp.where(x < 0, (math.pi + _PI_LO) - a, a)


def dihedral_angles(p0: Vec, p1: Vec, p2: Vec, p3: Vec) -> tuple[Array, ...]:
    """The six interior dihedral angles in degrees, at edges 01, 02, 03, 12, 13, 23.

    theta = atan2(|N_k x N_l|, -N_k . N_l): stable near 0 and 180 degrees, no arccos, and
    both arguments come from the same two computed normals (accurate even for needles).
    """
    g = _TetGeometry(p0, p1, p2, p3)
    n = g.normals
    return tuple(
        jnp.degrees(_atan2_nonneg(_norm(_cross(n[f0], n[f1])), -_dot(n[f0], n[f1])))
        for f0, f1 in _TetGeometry.EDGE_FACES
    )


QualityFn = Callable[[Vec, Vec, Vec, Vec], Array]

MEASURES: dict[str, QualityFn] = {
    "min_sine": min_sine,
    "biased_min_sine": biased_min_sine,
    "radius_ratio": radius_ratio,
    "vol_length": vol_length,
    "mean_ratio": mean_ratio,
}


def get_measure(name: str) -> QualityFn:
    """The quality function registered under ``name`` (see ``MEASURES``)."""
    try:
        return MEASURES[name]
    except KeyError:
        raise JtetError(
            f"unknown quality measure {name!r}; choose one of {sorted(MEASURES)}"
        ) from None


# ---------------------------------------------------------------------------------------
# Host-side evaluation on whole meshes: gather SoA corners, pad to a bucket capacity.


def soa_corners(points: Float[np.ndarray, "n 3"], tets: np.ndarray) -> tuple[Vec, Vec, Vec, Vec]:
    """Corner coordinates of ``tets`` (m, 4) as four SoA points of (m,) arrays."""
    xyz = np.ascontiguousarray(points.T)  # (3, n): gathers below read contiguous rows
    return tuple(tuple(xyz[c][tets[:, i]] for c in range(3)) for i in range(4))


def _all_measures_soa(*xyz, names: tuple[str, ...]):
    """((6, m) dihedral angles, one row per edge, then each measure of ``names`` (m,)).

    The one per-tet kernel of the host helpers: statistics need every measure, the
    optimizer one measure and the angles, and a new process builds (or loads) one
    executable instead of three (cold compile: 1.9 s of CPU less; a 4096-tet call 0.9 ms
    against 0.6 + 0.2 ms for separate angle and min-sine kernels; measured). The kernel
    shares the corners and face normals between the measures. The smallest / largest
    angle of each tet are taken on the host (``_angle_extremes``): with the min / max
    (and an (m, 6) layout) in the kernel, XLA recomputed the angles in each of its
    fusions (3.3 -> 1.0 s of CPU to compile, 2.5 -> 0.9 ms a call, measured)."""
    corners = tuple(xyz[3 * i : 3 * i + 3] for i in range(4))
    rows = jnp.stack(dihedral_angles(*corners))
    return (rows, *(MEASURES[name](*corners) for name in names))


def _angle_extremes(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(angles (m, 6), min (m,), max (m,)) from the kernels' (6, m) rows of angles."""
    return np.ascontiguousarray(rows.T), rows.min(axis=0), rows.max(axis=0)


# Tets per kernel call: every call has this shape whatever the number of tets, so each
# kernel compiles (or loads from the cache) once per process, not once per power-of-two
# size; calls run on the worker threads. Small: the driver re-evaluates only the few
# tets a step created or moved (dihedrals + min_sine of 300 tets: 1.6 ms at 4096, 7.3 ms
# at 16384; a whole 10k-tet mesh 5.4 vs 7.0 ms).
TET_CHUNK = 1 << 12
# At most this many tets go to one call of this size instead (a second shape of the
# same kernel): the steps of the perturbation rounds' climbs and the late passes
# re-evaluate tens to hundreds of tets, and a call padded to TET_CHUNK computed the
# whole chunk (holeplate tets, host work included: 50 tets 0.80 -> 0.44 ms, 500 tets
# 0.83 -> 0.38 ms, bit-identical values; ~1 s more CPU to build in a new process).
SMALL_TET_CHUNK = 1 << 9


def _chunk(m: int) -> int:
    """Tets per call for an evaluation of m tets."""
    return SMALL_TET_CHUNK if m <= SMALL_TET_CHUNK < TET_CHUNK else TET_CHUNK


def _per_tet(name: str, settings: tuple, fn, points: np.ndarray, tets: np.ndarray):
    """``fn`` over the SoA corners of ``tets`` in calls of ``_chunk(len(tets))`` tets
    (padding repeats the first tet); each output has one entry per tet along its LAST
    axis, concatenated over the calls and cut back to ``len(tets)``."""
    m = len(tets)
    chunk = _chunk(m)
    cap = max(1, -(-m // chunk)) * chunk
    if cap != m:
        pad = np.broadcast_to(tets[:1] if m else np.zeros((1, 4), np.int64), (cap - m, 4))
        tets = np.concatenate([tets, pad]) if m else np.zeros((cap, 4), np.int64)
    xyz = [c for corner in soa_corners(points, tets) for c in corner]
    parts = [[c[i : i + chunk] for c in xyz] for i in range(0, cap, chunk)]
    outs = _config.parallel_map(
        lambda part: jax.device_get(cached_call(name, settings, fn, *part)), parts
    )
    outs = [o if isinstance(o, tuple) else (o,) for o in outs]
    return tuple(np.concatenate(o, axis=-1)[..., :m] for o in zip(*outs, strict=True))


def tet_quality(points: np.ndarray, tets: np.ndarray, measure: str = "min_sine") -> np.ndarray:
    """Quality ``measure`` of every tet: (m,) float64 NumPy array."""
    get_measure(measure)
    return tet_all_measures(points, tets)[3][measure]


def tet_all_measures(
    points: np.ndarray, tets: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(angles (m, 6), min (m,), max (m,) dihedral angles in degrees, {measure: (m,)})
    of every tet, for every measure of ``MEASURES``: one kernel and one gather of the
    corners (six separate kernels took 3.6x as long at 182k tets). ``tet_quality`` and
    ``tet_dihedrals`` return parts of this, so every caller sees the same numbers."""
    names = tuple(MEASURES)
    if len(points) == 0:
        empty = np.zeros(len(tets))
        return np.zeros((len(tets), 6)), empty, empty, {name: empty for name in names}
    if not _kernels_prefetched:
        prefetch_kernels()
    fn = functools.partial(_all_measures_soa, names=names)
    rows, *qs = _per_tet(*PER_TET_KERNEL, fn, points, tets)
    return *_angle_extremes(rows), dict(zip(names, qs, strict=True))


_kernels_prefetched = False
# (name, settings) of the per-tet kernel: every measure and the dihedral angles
PER_TET_KERNEL = ("tet_all_measures", tuple(MEASURES))


def warm_start_kernels(pass_groups) -> None:
    """Start loading, in the background, the kernels of ``pass_groups`` (the (name,
    settings) of ``jtet.improve``'s pass kernels) and the per-tet kernel that earlier
    processes used most recently (``_aot.warm_start``, once per process; nothing is
    compiled). A warm first run loaded them one group at a time as its passes first
    needed them."""
    warm_start(groups={*pass_groups, PER_TET_KERNEL})


def prefetch_kernels() -> None:
    """Build the per-tet kernel (every measure and the dihedral angles) at both call
    sizes, or wait for the threads loading them; returns when they are ready."""
    global _kernels_prefetched
    _kernels_prefetched = True
    name, names = PER_TET_KERNEL
    fn = functools.partial(_all_measures_soa, names=names)
    sizes = sorted({TET_CHUNK, _chunk(1)})
    prefetch([(name, names, fn, [jax.ShapeDtypeStruct((k,), np.float64)] * 12) for k in sizes])


def tet_dihedrals(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, ...]:
    """(angles (m, 6), min (m,), max (m,)) dihedral angles of every tet, in degrees."""
    return tet_all_measures(points, tets)[:3]
