"""Mesh quality statistics: ``mesh_stats(mesh) -> MeshStats`` and a before/after table.

Angles are in degrees, volumes in the mesh's length unit cubed. Dihedral angles and every
quality measure come from ``jtet._quality.tet_all_measures`` (one jitted SoA pass over the
whole mesh); orientation signs come from the robust predicate used by the validity check.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ._quality import MEASURES, get_measure, tet_all_measures
from ._validity import orientation_signs

SMALL_ANGLES = (5, 10, 20, 30)  # count tets whose smallest dihedral angle is below these
LARGE_ANGLES = (150, 160, 170)  # count tets whose largest dihedral angle is above these
DIHEDRAL_BINS = 180  # 1-degree bins over [0, 180]
QUALITY_BINS = 100  # bins over [-1, 1]


@dataclass(frozen=True, eq=False)
class MeshStats:
    """Summary statistics of a mesh's quality.

    Attributes:
        n_points, n_tets: sizes.
        min_dihedral, max_dihedral: extreme dihedral angles over all tets (degrees).
        small_dihedral: {threshold: number of tets whose min dihedral < threshold}, for
            thresholds ``SMALL_ANGLES`` (degrees).
        large_dihedral: {threshold: number of tets whose max dihedral > threshold}, for
            thresholds ``LARGE_ANGLES``.
        quality_min, quality_mean: {measure name: worst / mean quality over the tets}.
        volume: total signed volume.
        n_inverted, n_degenerate: tets with negative / zero volume (robust orientation).
        dihedral_hist: (180,) int64 counts of all 6 m dihedral angles in 1-degree bins
            [k, k+1), the last bin closed.
        quality_hist: {measure name: (100,) int64 counts of the quality clipped to [-1, 1]
            in bins of width 0.02}.
    """

    n_points: int
    n_tets: int
    min_dihedral: float
    max_dihedral: float
    small_dihedral: dict
    large_dihedral: dict
    quality_min: dict
    quality_mean: dict
    volume: float
    n_inverted: int
    n_degenerate: int
    dihedral_hist: np.ndarray
    quality_hist: dict

    def as_dict(self) -> dict:
        """JSON-friendly dict (string keys, lists instead of arrays, Python scalars)."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["small_dihedral"] = {str(k): int(v) for k, v in self.small_dihedral.items()}
        d["large_dihedral"] = {str(k): int(v) for k, v in self.large_dihedral.items()}
        d["quality_min"] = {k: float(v) for k, v in self.quality_min.items()}
        d["quality_mean"] = {k: float(v) for k, v in self.quality_mean.items()}
        d["dihedral_hist"] = [int(v) for v in self.dihedral_hist]
        d["quality_hist"] = {k: [int(x) for x in v] for k, v in self.quality_hist.items()}
        return d


def mesh_stats(mesh, measures: Iterable[str] | None = None, *, per_tet=None) -> MeshStats:
    """Statistics of ``mesh`` (a ``TetMesh``) for the quality ``measures`` (default: all).

    ``per_tet``: ``tet_all_measures(mesh.points, mesh.tets)`` if the caller has it already
    (``improve`` needs it too), else computed here."""
    names = list(MEASURES) if measures is None else list(measures)
    for name in names:
        get_measure(name)  # unknown names fail here, with the list of valid ones
    points, tets = mesh.points, mesh.tets
    if per_tet is None:
        per_tet = tet_all_measures(points, tets)
    angles, lo, hi, qualities = per_tet
    qmin, qmean, qhist = {}, {}, {}
    for name in names:
        q = qualities[name]
        qmin[name] = float(q.min())
        qmean[name] = float(q.mean())
        qhist[name] = np.histogram(np.clip(q, -1.0, 1.0), QUALITY_BINS, (-1.0, 1.0))[0]
    sign, _ = orientation_signs(points, tets)
    return MeshStats(
        n_points=len(points),
        n_tets=len(tets),
        min_dihedral=float(lo.min()),
        max_dihedral=float(hi.max()),
        small_dihedral={a: int((lo < a).sum()) for a in SMALL_ANGLES},
        large_dihedral={a: int((hi > a).sum()) for a in LARGE_ANGLES},
        quality_min=qmin,
        quality_mean=qmean,
        volume=float(np.sum(mesh.volumes)),
        n_inverted=int((sign < 0).sum()),
        n_degenerate=int((sign == 0).sum()),
        dihedral_hist=np.histogram(angles.reshape(-1), DIHEDRAL_BINS, (0.0, 180.0))[0],
        quality_hist=qhist,
    )


# ``region_stats`` refuses more regions than this: a table column each (random labels
# per tet would make thousands)
MAX_REGION_COLUMNS = 16


def region_stats(mesh, measures: Iterable[str] | None = None, *, per_tet=None) -> dict:
    """{region label: ``MeshStats`` of the tets of that region} (ascending labels; the
    points of a region are the vertices of its tets). ``per_tet`` as for ``mesh_stats``.
    Raises ``JtetError`` for a mesh of more than ``MAX_REGION_COLUMNS`` regions."""
    from ._errors import JtetError

    labels = np.unique(mesh.region)
    if len(labels) > MAX_REGION_COLUMNS:
        raise JtetError(
            f"the mesh has {len(labels)} regions; statistics by region are given for at "
            f"most {MAX_REGION_COLUMNS}"
        )
    if per_tet is None:
        per_tet = tet_all_measures(mesh.points, mesh.tets)
    angles, lo, hi, qualities = per_tet
    out = {}
    for label in labels.tolist():
        sel = mesh.region == label
        part = (angles[sel], lo[sel], hi[sel], {k: v[sel] for k, v in qualities.items()})
        out[label] = mesh_stats(mesh._part(sel)[0], measures, per_tet=part)
    return out


def _fmt_q(q: float) -> str:
    # worst qualities of bad meshes are tiny: keep their significant digits visible
    return f"{q:.4f}" if q == 0 or abs(q) >= 1e-3 else f"{q:.2e}"


def _rows(s: MeshStats) -> list[tuple[str, str]]:
    rows = [
        ("tets", f"{s.n_tets}"),
        ("points", f"{s.n_points}"),
        ("volume", f"{s.volume:.6g}"),
        ("min dihedral (deg)", f"{s.min_dihedral:.3f}"),
        ("max dihedral (deg)", f"{s.max_dihedral:.3f}"),
    ]
    rows += [(f"tets with min dihedral < {a}", f"{n}") for a, n in s.small_dihedral.items()]
    rows += [(f"tets with max dihedral > {a}", f"{n}") for a, n in s.large_dihedral.items()]
    for name in s.quality_min:
        rows.append((f"worst {name}", _fmt_q(s.quality_min[name])))
        rows.append((f"mean {name}", _fmt_q(s.quality_mean[name])))
    rows += [("inverted tets", f"{s.n_inverted}"), ("degenerate tets", f"{s.n_degenerate}")]
    return rows


def format_table(
    *stats: MeshStats | None,
    time_s: float | None = None,
    labels: tuple[str, ...] | None = None,
) -> str:
    """A plain-text table of statistics side by side, one column per ``MeshStats``.

    ``format_table(before, after)`` is the before/after table of ``improve`` (default
    labels "before", "after"); ``format_table(a, b, c, labels=("gmsh", "tetgen", "jtet"))``
    compares any number of meshes (default labels "mesh 1", "mesh 2", ...). ``None``
    entries are skipped (``format_table(before, None)`` is one column).
    ``time_s``, when given, adds a row with the time the improvement took (seconds), in
    the last column. Rows present in only some columns (different measures) show "-".
    """
    stats = tuple(s for s in stats if s is not None)
    if not stats:
        raise ValueError("format_table needs at least one MeshStats")
    if labels is None:
        labels = ("before", "after") if len(stats) <= 2 else ()
    labels = tuple(labels)[: len(stats)]
    labels += tuple(f"mesh {i + 1}" for i in range(len(labels), len(stats)))
    cols = [dict(_rows(s)) for s in stats]
    keys = list(dict.fromkeys(k for c in cols for k in c))
    body = [[k] + [c.get(k, "-") for c in cols] for k in keys]
    if time_s is not None:
        body.append(["time (s)"] + [""] * (len(cols) - 1) + [f"{time_s:.3f}"])
    return text_table(["", *labels], body)


def mesh_groups(mesh) -> list[dict]:
    """What a mesh file's groups became, for ``jtet stats --groups``: one dict per region,
    label of protected faces, edges and vertices, node set, point data and cell data
    array, with its kind ("region", "surface", "curve", "point", "node set", "point
    data", "cell data"), label (None for a node set without an id and for data arrays),
    name ("" without) and count (tets, faces, edges, vertices; values per component);
    data arrays also with their "components" and the "min" and "max" of their finite
    values (None without)."""
    names = mesh.label_names
    out = []
    for kind, dim, labels in (
        ("region", 3, mesh.region),
        ("surface", 2, mesh.protected_face_labels),
        ("curve", 1, mesh.protected_edge_labels),
        ("point", 0, mesh.protected_vertex_labels),
    ):
        found, counts = np.unique(labels, return_counts=True)
        out += [
            {"kind": kind, "label": int(k), "name": names.get((dim, int(k)), ""), "count": int(c)}
            for k, c in zip(found.tolist(), counts.tolist(), strict=True)
        ]
    out += [
        {"kind": "node set", "label": ns.label, "name": ns.name, "count": len(ns.ids)}
        for ns in mesh.node_sets
    ]
    arrays = [("point data", mesh.point_data), ("cell data", mesh.cell_data)]
    for kind, name, a in ((k, n, a) for k, data in arrays for n, a in data.items()):
        finite = a[np.isfinite(a)] if a.dtype.kind == "f" else a
        out.append({
            "kind": kind, "label": None, "name": name, "count": len(a),
            "components": 1 if a.ndim == 1 else int(a.shape[1]),
            "min": float(finite.min()) if finite.size else None,
            "max": float(finite.max()) if finite.size else None,
        })  # fmt: skip
    return out


def format_groups(groups: list[dict]) -> str:
    """``mesh_groups`` as a plain-text table."""
    units = {"region": "tets", "surface": "faces", "curve": "edges"}

    def size(g: dict) -> str:
        if g["kind"] not in ("point data", "cell data"):
            return f"{g['count']} {units.get(g['kind'], 'vertices')}"
        k = g["components"]
        values = f"{g['count']} x {k} values" if k > 1 else f"{g['count']} values"
        if g["min"] is None:
            return values
        return f"{values} in [{g['min']:.6g}, {g['max']:.6g}]"

    body = [
        [g["kind"], "" if g["label"] is None else str(g["label"]), g["name"], size(g)]
        for g in groups
    ]
    return text_table(["group", "label", "name", "size"], body, left=3)


def text_table(head: list[str], body: list[list[str]], left: int = 1) -> str:
    """Rows of strings as plain-text columns padded to their widest cell, a rule under
    ``head``; the first ``left`` columns are left-aligned, the others right-aligned."""
    widths = [max(len(r[i]) for r in [head, *body]) for i in range(len(head))]

    def line(r):
        cells = [
            c.ljust(w) if i < left else c.rjust(w)
            for i, (c, w) in enumerate(zip(r, widths, strict=True))
        ]
        return "  ".join(cells).rstrip()

    return "\n".join([line(head), "  ".join("-" * w for w in widths), *map(line, body)])


def worst_tets(mesh, n: int = 10, measure: str = "biased_min_sine", *, per_tet=None) -> list[dict]:
    """The ``n`` tets of lowest ``measure``, worst first (ties in tet order), to find them:

    ``tet`` (index; the cell id in ParaView of a ``.vtu`` jtet wrote), ``quality``,
    ``min_dihedral`` / ``max_dihedral`` (degrees), ``region``, ``centroid`` ([x, y, z]) and
    ``fixed_vertices``: how many of its four vertices lie on the boundary, an interface
    or a protected entity (with ``boundary="fixed"`` they never move, so such a tet can
    only change by flips; None when the mesh is too broken for a topology).
    ``per_tet``: ``tet_all_measures(mesh.points, mesh.tets)`` if the caller has it.
    """
    from ._errors import JtetError
    from ._topology import FREE

    get_measure(measure)
    if per_tet is None:
        per_tet = tet_all_measures(mesh.points, mesh.tets)
    _, lo, hi, qualities = per_tet
    q = qualities[measure]
    order = np.argsort(q, kind="stable")[: max(int(n), 0)]
    try:
        fixed = (mesh.topology.vertex_kind[mesh.tets[order]] != FREE).sum(axis=1).tolist()
    except JtetError:  # non-conforming: no topology, the rest still says where
        fixed = [None] * len(order)
    centroids = mesh.points[mesh.tets[order]].mean(axis=1)
    return [
        {
            "tet": int(t),
            "quality": float(q[t]),
            "min_dihedral": float(lo[t]),
            "max_dihedral": float(hi[t]),
            "region": int(mesh.region[t]),
            "centroid": [float(c) for c in centroid],
            "fixed_vertices": f,
        }
        for t, centroid, f in zip(order, centroids, fixed, strict=True)
    ]


def format_worst(rows: list[dict], measure: str) -> str:
    """A plain-text table of ``worst_tets`` rows."""
    head = ["tet", measure, "min dih", "max dih", "region", "fixed verts", "centroid"]
    body = [
        [
            str(r["tet"]),
            _fmt_q(r["quality"]),
            f"{r['min_dihedral']:.2f}",
            f"{r['max_dihedral']:.2f}",
            str(r["region"]),
            "-" if r["fixed_vertices"] is None else str(r["fixed_vertices"]),
            " ".join(f"{c:.6g}" for c in r["centroid"]),
        ]
        for r in rows
    ]
    return text_table(head, body, left=0)
