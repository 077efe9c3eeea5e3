"""Outputs people read or open: JSON reports, per-tet arrays for ParaView, histograms."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ._errors import MeshFileError
from ._io import move_into_place, new_temp_file
from ._mesh import TetMesh
from ._quality import tet_all_measures


def quality_cell_data(mesh: TetMesh) -> dict[str, np.ndarray]:
    """Per-tet arrays written with an output mesh: every measure and the dihedral range.

    Named so ParaView lists them plainly: ``quality_min_sine``, ..., ``min_dihedral``,
    ``max_dihedral`` (degrees), ``volume``.
    """
    _, lo, hi, qualities = tet_all_measures(mesh.points, mesh.tets)
    data = {f"quality_{name}": q for name, q in qualities.items()}
    data["min_dihedral"] = lo
    data["max_dihedral"] = hi
    data["volume"] = np.asarray(mesh.volumes)
    return data


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and a rename (no partial file)."""
    path = Path(path)
    tmp = None
    try:
        tmp = new_temp_file(path.parent, f".{path.name}.", ".tmp")
        tmp.write_text(text)
        move_into_place(tmp, path)
        tmp = None
    except OSError as e:
        raise MeshFileError(f"{path}: cannot write ({e.strerror or e})") from None
    finally:  # also on Ctrl-C: no temporary file is left behind
        if tmp is not None and tmp.exists():
            tmp.unlink()


def write_report(result, path: str | os.PathLike) -> None:
    """The JSON report of an ``ImproveResult``: options, stats before/after, history."""
    write_text_atomic(path, json.dumps(result.as_dict(), indent=1))


def plot_histograms(result, path: str | os.PathLike, measure: str | None = None) -> None:
    """Before/after histograms of dihedral angles and of the optimized quality (PNG/PDF/SVG)
    of an ``ImproveResult``."""
    measure = measure or (result.options.quality if result.options else "min_sine")
    plot_stats([result.stats_before, result.stats_after], path, ("before", "after"), measure)


# before / after keep the colours of the improve plot; further meshes take matplotlib's
_COLOURS = ("tab:red", "tab:blue", "tab:green", "tab:orange", "tab:purple", "tab:brown")


def plot_stats(
    stats, path: str | os.PathLike, labels=None, measure: str = "biased_min_sine"
) -> None:
    """Histograms of dihedral angles and of ``measure`` for several meshes, overlaid
    (PNG/PDF/SVG, chosen by the suffix of ``path``; written atomically).

    ``stats``: a list of ``MeshStats`` (``jtet.stats(mesh)``), e.g. one mesh's, the
    before / after of a run, or the outputs of several tools on one input; ``labels``
    name them in the legends (default "mesh 1", "mesh 2", ...). Counts are on a log
    scale: the few worst tets are what matters, and they would not show on a linear one.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stats = list(stats)
    if not stats:
        raise ValueError("plot_stats needs at least one MeshStats")
    labels = list(labels or [])[: len(stats)]
    labels += [f"mesh {i + 1}" for i in range(len(labels), len(stats))]
    missing = [lb for s, lb in zip(stats, labels, strict=True) if measure not in s.quality_hist]
    if missing:
        raise ValueError(f"the statistics of {', '.join(missing)} hold no {measure!r}")
    colours = [_COLOURS[i % len(_COLOURS)] for i in range(len(stats))]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    edges = np.linspace(0.0, 180.0, len(stats[0].dihedral_hist) + 1)
    for s, label, colour in zip(stats, labels, colours, strict=True):
        legend = f"{label}: {s.min_dihedral:.1f}-{s.max_dihedral:.1f}"
        ax1.stairs(np.maximum(s.dihedral_hist, 0.5), edges, label=legend, color=colour, fill=False)
    ax1.set_yscale("log")
    ax1.set_ylim(bottom=0.8)  # empty bins are drawn at 0.5 and hidden: log(0) is undefined
    ax1.set_xlim(0, 180)
    ax1.set_xlabel("dihedral angle (degrees)")
    ax1.set_ylabel("number of angles (log)")
    ax1.set_title(
        "dihedral angles: "
        + " -> ".join(f"{s.min_dihedral:.1f}-{s.max_dihedral:.1f}" for s in stats)
        if len(stats) <= 2
        else "dihedral angles (smallest-largest)"
    )
    ax1.legend()
    qedges = np.linspace(-1.0, 1.0, len(stats[0].quality_hist[measure]) + 1)
    for s, label, colour in zip(stats, labels, colours, strict=True):
        h = np.maximum(s.quality_hist[measure], 0.5)
        legend = f"{label}: worst {s.quality_min[measure]:.3f}"
        ax2.stairs(h, qedges, label=legend, color=colour, fill=False)
    ax2.set_yscale("log")
    ax2.set_ylim(bottom=0.8)
    lo = min(0.0, *(s.quality_min[measure] for s in stats))
    ax2.set_xlim(max(-1.0, lo), 1.0)
    ax2.set_xlabel(f"{measure} (1 = regular tet)")
    ax2.set_ylabel("number of tets (log)")
    ax2.set_title(
        f"{measure}: worst " + " -> ".join(f"{s.quality_min[measure]:.3f}" for s in stats)
        if len(stats) <= 2
        else f"{measure} (worst)"
    )
    ax2.legend()
    path = Path(path)
    tmp = None
    try:
        # a name of its own: two runs plotting to one path never write the same file
        tmp = new_temp_file(path.parent, f".{path.stem}.tmp-", path.suffix)
        fig.savefig(tmp, dpi=110)
        move_into_place(tmp, path)
        tmp = None
    except (OSError, ValueError) as e:
        raise MeshFileError(f"{path}: cannot write plot ({e})") from None
    finally:  # also on Ctrl-C: no temporary file is left behind
        plt.close(fig)
        if tmp is not None and tmp.exists():
            tmp.unlink()
