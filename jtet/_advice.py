"""Notes printed with a run's summary: why the worst tet stayed where it is, and which
option would free it."""

from __future__ import annotations

import numpy as np

from ._topology import CORNER, FREE

# Tets within this much of the worst quality (normalized, regular tet = 1) count as the
# worst: symmetric meshes end with several tets tied at the minimum to the last bits.
TIE = 1e-9

# An input in which more than this share of the tets have no interior vertex gets a note
# (``boundary_only_share``): with the boundary fixed, smoothing has next to nothing to
# move there. TetGen's ``-p`` without ``-q`` puts no point inside a sphere (every tet);
# the Gmsh reference meshes have 3-4 % such tets.
BOUNDARY_ONLY_SHARE = 0.5


def _pinned(kinds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pinned, slidable), each (t,) bool, for the vertex kinds (t, 4) of t tets: whether
    all four vertices lie on the boundary or on interfaces (no FREE one), and whether
    such a tet has one on a flat facet or a straight subsegment (not a CORNER), which
    ``boundary="slide"`` may move."""
    pinned = (kinds != FREE).all(axis=1)
    return pinned, pinned & (kinds != CORNER).any(axis=1)


def boundary_only_share(mesh) -> tuple[float, bool]:
    """(share of the tets of ``mesh`` whose four vertices all lie on the boundary or on
    interfaces, whether ``boundary="slide"`` may move a vertex of one of them)."""
    if not mesh.n_tets:
        return 0.0, False
    pinned, slidable = _pinned(mesh.topology.vertex_kind[mesh.tets])
    return float(pinned.mean()), bool(slidable.any())


def _worst_kinds(mesh, quality: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ids (w,) of the worst tets, within ``TIE`` of ``quality``'s (m,) minimum, and
    the kinds (w, 4) of their vertices)."""
    quality = np.asarray(quality)
    if not len(quality):
        return np.zeros(0, np.int64), np.zeros((0, 4), np.int8)
    worst = np.flatnonzero(quality <= quality.min() + TIE)
    # the kinds of these vertices only: after perturbation rounds the mesh has no
    # topology, and a whole build here was ~3 % of a holeplate run
    return worst, mesh.vertex_kinds(mesh.tets[worst].reshape(-1)).reshape(-1, 4)


def pinned_worst_tets(mesh, quality: np.ndarray) -> np.ndarray:
    """Ids of the worst tets (within ``TIE`` of ``quality``'s (m,) minimum) whose four
    vertices all lie on the boundary or on interfaces (no FREE vertex), with at least
    one of them on a flat facet or a straight subsegment (not a CORNER): the tets that
    ``boundary="fixed"`` keeps from being smoothed and ``"slide"`` may move."""
    worst, kinds = _worst_kinds(mesh, quality)
    return worst[_pinned(kinds)[1]]


def cornered_worst_tets(mesh, quality: np.ndarray) -> np.ndarray:
    """Ids of the worst tets (within ``TIE`` of ``quality``'s (m,) minimum) whose four
    vertices are all CORNERs of the boundary or of interfaces (where their surfaces bend
    or meet): no boundary setting moves them, so only flips and new vertices change
    such a tet."""
    worst, kinds = _worst_kinds(mesh, quality)
    return worst[(kinds == CORNER).all(axis=1)]


def notes(
    mesh,
    options,
    quality: np.ndarray,
    min_dihedral,
    max_dihedral,
    kept_rounds: int = 0,
    rounds: int | None = None,
    input_boundary_only: tuple[float, bool] = (0.0, False),
) -> list[str]:
    """Sentences for the user about the result ``mesh`` of a run with ``options``:
    ``quality`` (m,) is its ``options.quality`` per tet, ``min_dihedral`` and
    ``max_dihedral`` (m,) its dihedral angle range per tet in degrees; ``kept_rounds``
    the perturbation rounds the run kept (-1: it stopped for a goal or a time limit) of
    its limit ``rounds`` (None: ``options.perturb_rounds`` of ``mesh``);
    ``input_boundary_only``: ``boundary_only_share`` of the run's input."""
    out = []
    missed = _missed_goals(options, min_dihedral, max_dihedral) if len(quality) else ""
    if missed:
        out.append(
            f"the goals were not reached: {missed}; more perturbation rounds (--perturb), "
            "--boundary slide or a feature angle may get closer"
        )
    good = options.good_quality
    if good is not None and len(quality) and quality.min() >= good:
        return out  # every tet is good enough: the run left them alone on purpose
    if rounds is None:
        rounds = options.perturb_rounds(mesh.n_tets)
    if rounds and kept_rounds >= rounds:
        auto = options.perturb == "auto"
        which = f"perturb auto: {rounds} kept rounds" if auto else f"perturb {rounds}: kept rounds"
        out.append(
            f"the perturbation rounds stopped at their limit ({which}) while "
            f"they still raised the worst tet; more rounds (--perturb {2 * rounds}) may "
            "raise it further, at more time"
        )
    share, slidable = input_boundary_only
    boundary_only = share > BOUNDARY_ONLY_SHARE and options.boundary == "fixed"
    if boundary_only:
        out.append(
            f"{share:.0%} of the input's tets have all four vertices on the boundary or on "
            "interfaces, where boundary 'fixed' keeps them: smoothing moves only interior "
            "vertices, so flips and the few vertices the perturbation rounds add are what "
            "can change those tets"
            + ("; boundary 'slide' (--boundary slide) lets those on flat facets and "
               "straight edges move" if slidable else "")
            + ". A mesh generated with interior points (TetGen -q, Gmsh) can be improved "
            "much further"
        )  # fmt: skip

    def worst_tet(t: int) -> str:
        return (
            f"the worst tet by {options.quality} (quality {quality[t]:.4f}, dihedral "
            f"angles {min_dihedral[t]:.2f}-{max_dihedral[t]:.2f} deg)"
        )

    if options.boundary == "fixed" and "smooth" in options.ops:  # only smoothing slides
        stuck = pinned_worst_tets(mesh, quality)
        if len(stuck):
            out.append(
                f"{worst_tet(stuck[0])} has all four vertices on the boundary or on "
                "interfaces, which boundary 'fixed' keeps in place; boundary 'slide' "
                "(--boundary slide) lets them slide within flat facets and along straight "
                "edges, and may raise it"
            )
            return out
    # the boundary-only note above already says that flips are what can change such tets
    cornered = np.zeros(0, np.int64) if boundary_only else cornered_worst_tets(mesh, quality)
    if len(cornered):
        flips = "edge" in options.ops or "face" in options.ops
        out.append(
            f"{worst_tet(cornered[0])} has all four vertices at corners of the boundary or "
            "of interfaces (where their surfaces bend or meet), which no boundary setting "
            "moves; "
            + ("only flips or new vertices inside it can change it, and none of the "
               "run's flips raised it" if flips else
               "only flips (--ops edge,face) or new vertices inside it can change it")
            + ". The boundary and interface triangles around it bound it: a mesh whose "
            "surfaces are smoother or finer there can be improved further"
        )  # fmt: skip
    return out


def _missed_goals(options, min_dihedral, max_dihedral) -> str:
    """The dihedral-angle goals of ``options`` (``Options.missed_goals``) that the (m,)
    per-tet angles miss, as words ("" when every goal set is met, or none is set)."""
    lo, hi = float(min_dihedral.min()), float(max_dihedral.max())
    missed = options.missed_goals(lo, hi)
    parts = []
    if "goal_min_dihedral" in missed:
        parts.append(
            f"smallest dihedral angle {lo:.2f} deg (goal >= {options.goal_min_dihedral:g})"
        )
    if "goal_max_dihedral" in missed:
        parts.append(f"largest dihedral angle {hi:.2f} deg (goal <= {options.goal_max_dihedral:g})")
    return ", ".join(parts)
