"""The one options object shared by the Python API, the CLI and the config files."""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass

from ._errors import JtetError
from ._quality import MEASURES

OPS = ("edge", "face", "smooth")
_INTS = ("max_ring", "max_faces", "max_passes", "patience", "seed")
_FLOATS = (
    "feature_angle",
    "time_limit",
    "min_improvement",
    "min_progress",
    "good_quality",
    "smooth_threshold",
    "goal_min_dihedral",
    "goal_max_dihedral",
    "min_scaled_jacobian",
)
_OPTIONAL = (
    "time_limit",
    "good_quality",
    "smooth_threshold",
    "goal_min_dihedral",
    "goal_max_dihedral",
    "min_scaled_jacobian",
)
BOUNDARY_MODES = ("fixed", "slide")

# ``perturb="auto"``: this many kept rounds on meshes of up to PERTURB_AUTO_TETS tets, and
# PERTURB_AUTO_ROUNDS * (tets / PERTURB_AUTO_TETS) ** PERTURB_AUTO_POWER on larger ones. A
# round frees the current worst place of the mesh, and a large mesh has more places about
# as bad as its worst: with 8 rounds the 983k-tet Gmsh cube ends at 31.92 degrees (17.7
# s), with 12 at 32.89 (18.1 s), 16 at 33.42 (22.1 s), 25 at 33.81 (29.8 s); the 182k cube
# with 8 / 11 / 16 at 32.98 / 33.41 / 33.95 (4.9 / 6.1 / 10.5 s). The fourth root gives
# the 983k cube 14 rounds and the 182k cube 9, and leaves meshes up to 100k tets (the
# reference meshes, whose runs it does not change) at 8.
PERTURB_AUTO_ROUNDS = 8
PERTURB_AUTO_TETS = 100_000
PERTURB_AUTO_POWER = 0.25


def auto_perturb_rounds(n_tets: int) -> int:
    """The kept perturbation rounds of ``perturb="auto"`` for a mesh of ``n_tets`` tets:
    8 up to 100k tets, then growing with the fourth root of the size (14 at 1M)."""
    scale = max(1.0, n_tets / PERTURB_AUTO_TETS) ** PERTURB_AUTO_POWER
    return int(round(PERTURB_AUTO_ROUNDS * scale))


@dataclass(frozen=True)
class Options:
    """Settings of ``jtet.improve``.

    Attributes:
        ops: operations to run, any of "edge" (optimal edge removal), "face" (optimal
            multi-face removal), "smooth" (vertex smoothing).
        quality: quality measure the optimizer maximizes (see ``jtet.MEASURES``). The
            default ``biased_min_sine`` (min sine with obtuse angles' sines counted 0.7x)
            raises the smallest dihedral angles and lowers the largest: on the reference
            Gmsh meshes it reached max dihedral angles of 126-135 degrees against 135-146
            for ``min_sine``, at the same worst angle within +-2.5 degrees.
        max_ring: largest ring (or boundary chain) tried by edge removal, 3..16.
        max_faces: capacity of a multi-face removal tree (faces sandwiched between a, b).
        boundary: "fixed" keeps every boundary / interface vertex in place; "slide" lets
            vertices slide inside flat facets and along straight subsegments.
        feature_angle: degrees; two subfacets whose planes differ by more than this make
            their edge a subsegment. 0 (default): only exactly coplanar subfacets may be
            flipped, so the boundary stays geometrically identical. A positive angle lets
            flips replace subfacets bent by less than it: the boundary and interfaces
            then keep their vertices but their shape (and the region volumes) change.
        regions: region labels (``TetMesh.region``) whose tets may change, or names of
            regions (``TetMesh.label_names``: Gmsh physical volumes), or None (all):
            the tets of the other regions stay exactly as they are, with their vertices
            and the faces they share with the improved regions, as Gmsh's
            ``optimize(dimTags=...)`` works on the volumes it is given. The run improves
            those regions as a mesh of their own (goals, notes and history are theirs;
            the statistics before / after are the whole mesh's) and splices it back.
        max_passes: stop after this many passes.
        patience: stop after this many passes in a row without progress.
        perturb: at most this many kept perturbation rounds after the climb converges
            (0: none), or "auto" (the default): 8 on meshes of up to 100k tets, more on
            larger ones (``auto_perturb_rounds``: 9 at 182k tets, 14 at 1M, 19 at 3M),
            which have more places about as bad as their worst for the rounds to free.
            A round kicks the worst tets (flips that may lower them a little, a new
            vertex inside them, random moves of the free vertices around them,
            single deep flips), climbs again around them, and keeps the result only if
            the worst quality rose (or stayed and one of several tets tied near it was
            fixed); otherwise the mesh goes back. Stops at the first round that keeps
            nothing. It frees worst tets whose vertices are all pinned (boundary fixed)
            and local optima of the climb: holeplate 29.1-29.5 -> 32.7-34.3 degrees over
            seeds 0-4, for +0.6-1.3 s. Inserted vertices are appended to the points.
        insert: whether the perturbation rounds may add vertices (a new vertex inside the
            worst tets is one of their kicks). False keeps the mesh's points: the output
            has exactly the input's vertices, in their order (smoothing may still move
            the free ones; ``ops=("edge", "face")`` keeps them in place too), as MMG's
            ``-noinsert`` and Stellar with vertex insertion disabled do.
        time_limit: seconds of wall time, or None.
        goal_min_dihedral, goal_max_dihedral: degrees, or None (default: no goal). The
            run stops ("goal reached") as soon as the smallest dihedral angle of the mesh
            is at least ``goal_min_dihedral`` and its largest at most
            ``goal_max_dihedral`` (a goal left None always holds; with both None the run
            never stops for a goal), as Stellar's ``goalanglemin`` / ``goalanglemax`` do.
            Checked before the first pass, after every operation and after every kept
            perturbation round: a mesh that is good enough for the user's purpose is
            not polished further. Gmsh reference meshes with goals 32 / 138: cube,
            sphere and torus stop in the climb, at 18-19 us per tet instead of 22-40
            (medians of 5; ``experiments/results/bench_improve.md``, session 27).
        min_improvement: an operation must raise its worst tet by more than this.
        min_progress: a pass counts as progress when the worst quality or a thresholded
            mean of the worst tets rose by more than this fraction; ``patience`` passes in
            a row without progress stop the run.
        good_quality: tets of at least this quality are good enough: every operation
            works only around tets below it (edges, faces and vertices made only of good
            tets are not attempted), and the thresholded means of the objective stop
            here. None: work everywhere. Qualities are normalized (regular tet = 1). The
            default 0.6 is a tet with all dihedral angles in [34.4, 126.1] degrees under
            ``biased_min_sine`` ([34.4, 145.6] under ``min_sine``). Measured on the
            reference meshes: 2-4x faster than 0.7 at the same worst angle within +-1.5
            degrees (``experiments/results/defaults.md``).
        smooth_threshold: vertices whose worst tet has quality below this are smoothed
            (None: ``good_quality`` alone decides).
        min_scaled_jacobian: the floor of the guard on curved tets, or None (no guard).
            Only a mesh with curved edges (``TetMesh.curved_edges``: a quadratic file
            read with ``load(path, linear=True)``) has curved tets. No flip, split or
            vertex move may leave a new tet with a curved edge whose scaled Jacobian
            (Gmsh's ``minSJ`` of the 10-node tet, 1 for a straight one) is below both
            this and the smallest of the tets it replaces, so the output written with
            ``save(..., quadratic=True)`` has no curved tet folded or bent worse than
            min(this, the input's worst).
        check: verify the invariants after every operation (slower; on in tests).
        seed: seed of every random choice (independent sets); runs are reproducible.
        progress: show a progress bar / per-pass log on stderr.
    """

    ops: tuple[str, ...] = OPS
    quality: str = "biased_min_sine"
    max_ring: int = 7
    max_faces: int = 16
    boundary: str = "fixed"
    feature_angle: float = 0.0
    regions: tuple[int | str, ...] | None = None
    max_passes: int = 50
    patience: int = 2
    perturb: int | str = "auto"
    insert: bool = True
    time_limit: float | None = None
    goal_min_dihedral: float | None = None
    goal_max_dihedral: float | None = None
    min_improvement: float = 1e-9
    min_progress: float = 1e-3
    good_quality: float | None = 0.6
    smooth_threshold: float | None = None
    min_scaled_jacobian: float | None = 0.3
    check: bool = False
    seed: int = 0
    progress: bool = False

    def __post_init__(self):
        for name in _INTS:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise JtetError(f"{name} must be an integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        if self.perturb != "auto":
            value = self.perturb
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise JtetError(f"perturb must be an integer or 'auto', got {value!r}")
            object.__setattr__(self, "perturb", int(value))
        for name in _FLOATS:
            value = getattr(self, name)
            if value is None and name in _OPTIONAL:
                continue
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise JtetError(f"{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise JtetError(f"{name} must be finite, got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in ("insert", "check", "progress"):
            if not isinstance(getattr(self, name), bool):
                raise JtetError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if self.seed < 0:
            raise JtetError(f"seed must be >= 0, got {self.seed}")
        object.__setattr__(self, "regions", _region_labels(self.regions))
        ops = (self.ops,) if isinstance(self.ops, str) else tuple(self.ops)
        object.__setattr__(self, "ops", ops)
        bad = [o for o in ops if o not in OPS]
        if bad or not ops:
            raise JtetError(f"unknown operation(s) {bad or ops}; choose from {list(OPS)}")
        if self.quality not in MEASURES:
            raise JtetError(
                f"unknown quality measure {self.quality!r}; choose from {sorted(MEASURES)}"
            )
        if not 3 <= int(self.max_ring) <= 16:
            raise JtetError(f"max_ring must be in 3..16, got {self.max_ring}")
        if not 1 <= int(self.max_faces) <= 256:
            raise JtetError(f"max_faces must be in 1..256, got {self.max_faces}")
        if self.boundary not in BOUNDARY_MODES:
            raise JtetError(
                f"boundary must be one of {list(BOUNDARY_MODES)}, got {self.boundary!r}"
            )
        if not 0.0 <= float(self.feature_angle) < 90.0:
            raise JtetError(f"feature_angle must be in [0, 90) degrees, got {self.feature_angle}")
        if int(self.max_passes) < 0 or int(self.patience) < 1:
            raise JtetError("max_passes must be >= 0 and patience >= 1")
        if self.perturb != "auto" and self.perturb < 0:
            raise JtetError(f"perturb must be >= 0 or 'auto', got {self.perturb}")
        if not 0.0 <= float(self.min_progress) < 1.0:
            raise JtetError(f"min_progress must be in [0, 1), got {self.min_progress}")
        if self.good_quality is not None and not 0.0 < float(self.good_quality) <= 1.0:
            raise JtetError(f"good_quality must be in (0, 1] or None, got {self.good_quality}")
        if self.time_limit is not None and float(self.time_limit) <= 0:
            raise JtetError(f"time_limit must be positive seconds, got {self.time_limit}")
        if self.min_scaled_jacobian is not None and not -1.0 <= self.min_scaled_jacobian <= 1.0:
            raise JtetError(
                f"min_scaled_jacobian must be in [-1, 1] or None, got {self.min_scaled_jacobian}"
            )
        for name in ("goal_min_dihedral", "goal_max_dihedral"):
            value = getattr(self, name)
            if value is not None and not 0.0 < value < 180.0:
                raise JtetError(f"{name} must be in (0, 180) degrees or None, got {value}")

    def perturb_rounds(self, n_tets: int) -> int:
        """The kept perturbation rounds a run on a mesh of ``n_tets`` tets may make:
        ``perturb``, or ``auto_perturb_rounds(n_tets)`` for "auto"."""
        return auto_perturb_rounds(n_tets) if self.perturb == "auto" else self.perturb

    def missed_goals(self, min_dihedral: float, max_dihedral: float) -> tuple[str, ...]:
        """The goals set ("goal_min_dihedral", "goal_max_dihedral") that a mesh whose
        dihedral angles span [``min_dihedral``, ``max_dihedral``] degrees misses."""
        lo, hi = self.goal_min_dihedral, self.goal_max_dihedral
        return tuple(
            name
            for name, missed in (
                ("goal_min_dihedral", lo is not None and min_dihedral < lo),
                ("goal_max_dihedral", hi is not None and max_dihedral > hi),
            )
            if missed
        )

    def replace(self, **changes) -> Options:
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise JtetError(f"unknown option(s) {sorted(unknown)}")
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["ops"] = list(self.ops)
        if self.regions is not None:
            d["regions"] = list(self.regions)
        return d


def _region_labels(regions) -> tuple[int | str, ...] | None:
    """``Options.regions`` as a tuple of distinct labels (ints, sorted) and names (str, in
    their order) (None stays None)."""
    if regions is None:
        return None
    if isinstance(regions, numbers.Integral | str) and not isinstance(regions, bool):
        regions = (regions,)
    if isinstance(regions, bytes) or not hasattr(regions, "__iter__"):
        raise JtetError(f"regions must be a list of region labels or None, got {regions!r}")
    items = list(regions)

    def ok(r):
        return (isinstance(r, numbers.Integral) and not isinstance(r, bool)) or (
            isinstance(r, str) and r != ""
        )

    if not items or not all(ok(r) for r in items):
        raise JtetError(
            "regions must be a non-empty list of integer region labels or region names, "
            f"got {regions!r}"
        )
    labels = sorted({int(r) for r in items if not isinstance(r, str)})
    names = list(dict.fromkeys(r for r in items if isinstance(r, str)))
    return tuple(labels + names)


_FIELDS = frozenset(f.name for f in dataclasses.fields(Options))


def load_options(path) -> Options:
    """``Options`` from a JSON or YAML file (``.json``, ``.yaml``, ``.yml``).

    The file holds a mapping of ``Options`` fields (fields it leaves out keep their
    defaults), or is one of:

    - a jtet report (``jtet improve --report``): its ``options``, to run again exactly
      what made it;
    - a config file of the ``configs/optimizer`` group: its ``defaults`` list names other
      files of the same directory (``default`` is ``default.yaml``), merged in order,
      with the file's own keys where ``_self_`` stands (last when it is not listed),
      as Hydra composes them.

    Raises:
        MeshFileError: the file cannot be read or parsed.
        JtetError: it is not a mapping, names unknown fields, or holds invalid values.
    """
    from pathlib import Path

    data = _options_mapping(Path(path), ())
    unknown = sorted(set(data) - _FIELDS)
    if unknown:
        raise JtetError(f"{path}: unknown option(s) {unknown}; options are {sorted(_FIELDS)}")
    try:
        return Options(**data)
    except JtetError as e:
        raise JtetError(f"{path}: {e}") from None


def _options_mapping(path, seen: tuple) -> dict:
    """The option values of the file ``path`` (see ``load_options``), its ``defaults``
    resolved; ``seen``: the files that include it (a cycle is an error)."""
    import json

    from ._errors import MeshFileError

    if path.resolve() in seen:
        raise JtetError(f"{path}: the defaults lists include each other")
    suffix = path.suffix.lower()
    if suffix not in (".json", ".yaml", ".yml"):
        raise MeshFileError(f"{path}: options files are .json, .yaml or .yml")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise MeshFileError(
            f"{path}: cannot read options ({getattr(e, 'strerror', e) or e})"
        ) from None
    try:
        if suffix == ".json":
            data = json.loads(text)
        else:
            import yaml

            data = yaml.safe_load(text)
    except Exception as e:  # json / yaml syntax errors: one line naming the file
        reason = " ".join(str(e).split())
        raise MeshFileError(f"{path}: not a readable options file ({reason})") from None
    if data is None:  # an empty YAML file: the defaults
        data = {}
    if not isinstance(data, dict):
        raise JtetError(f"{path}: expected a mapping of option names to values")
    if isinstance(data.get("options"), dict) and not set(data) & _FIELDS:
        return dict(data["options"])  # a report
    data = dict(data)
    defaults = data.pop("defaults", None)
    if defaults is None:
        return data
    if not isinstance(defaults, list):
        raise JtetError(f"{path}: 'defaults' must be a list of file names")
    merged, placed = {}, False
    for entry in defaults:
        if entry == "_self_":
            merged.update(data)
            placed = True
        elif isinstance(entry, str) and entry and "/" not in entry and ":" not in entry:
            merged.update(
                _options_mapping(path.with_name(f"{entry}.yaml"), (*seen, path.resolve()))
            )
        else:
            raise JtetError(
                f"{path}: defaults entry {entry!r}: only names of files beside it and "
                "_self_ are read"
            )
    if not placed:
        merged.update(data)
    return merged
