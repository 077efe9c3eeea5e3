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


def plot_run(result, path: str | os.PathLike, measure: str | None = None) -> None:
    """The figure of an ``ImproveResult`` (PNG/PDF/SVG, written atomically): before /
    after histograms of dihedral angles and of the optimized quality and, below them,
    the run (``history_curve``): the smallest and largest dihedral angle after each
    operation against the seconds spent in operations."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    measure = measure or (result.options.quality if result.options else "min_sine")
    stats, labels = [result.stats_before, result.stats_after], ["before", "after"]
    _check_measure(stats, labels, measure)
    # a regions / protected-tets run's history is about the tets it could change
    before = result.selected_stats[0] if result.selected_stats else result.stats_before
    curve = history_curve(result.history, before)
    if curve is None:  # no operation ran (a goal held from the start, max_passes 0)
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    else:
        fig = plt.figure(figsize=(11, 7.5), constrained_layout=True)
        grid = fig.add_gridspec(2, 2, height_ratios=(1, 0.9))
        ax1, ax2 = fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 1])
        _draw_run(fig.add_subplot(grid[1, :]), curve)
    _draw_histograms(ax1, ax2, stats, labels, measure)
    _save_figure(fig, path)


#: how each operation's points are drawn in the run panel
_OP_MARKERS = {"edge": "o", "face": "s", "smooth": "^", "perturb": "D"}


def history_curve(history: list[dict], before) -> dict[str, np.ndarray] | None:
    """The run of an ``ImproveResult`` as curves, one point per history entry plus the
    start: ``seconds`` (m+1,) cumulative seconds spent in operations (0 at the start),
    ``min_dihedral`` and ``max_dihedral`` (m+1,) degrees of the mesh after each entry
    (the input's first, from ``before``: its ``MeshStats``), ``op`` (m,) the entry's
    operation, ``kept`` (m,) whether it changed the mesh (a perturbation attempt that
    kept nothing, a pass without a success: False). None for an empty history.
    """
    if not history:
        return None
    seconds = np.array([float(e.get("seconds", 0.0)) for e in history])
    return {
        "seconds": np.concatenate([[0.0], np.cumsum(seconds)]),
        "min_dihedral": np.array(
            [before.min_dihedral, *(e["min_dihedral"] for e in history)], np.float64
        ),
        "max_dihedral": np.array(
            [before.max_dihedral, *(e["max_dihedral"] for e in history)], np.float64
        ),
        "op": np.array([str(e.get("op", "")) for e in history]),
        "kept": np.array([int(e.get("successes", 0)) > 0 for e in history]),
    }


def _draw_run(ax, curve: dict[str, np.ndarray]) -> None:
    """The run panel: smallest dihedral angle (left axis) and largest (right axis) after
    each operation; filled markers changed the mesh, hollow ones did not."""
    t = curve["seconds"]
    right = ax.twinx()
    for axis, key, colour in ((ax, "min_dihedral", "tab:blue"), (right, "max_dihedral", "tab:red")):
        axis.step(t, curve[key], where="post", color=colour, lw=1.2)
        for op, marker in _OP_MARKERS.items():
            for kept in (True, False):
                at = np.flatnonzero((curve["op"] == op) & (curve["kept"] == kept)) + 1
                if len(at):
                    axis.scatter(
                        t[at],
                        curve[key][at],
                        marker=marker,
                        s=22,
                        color=colour,
                        facecolors=colour if kept else "none",
                        zorder=3,
                        label=op if (kept and key == "min_dihedral") else None,
                    )
        axis.set_ylabel(f"{key.replace('_', ' ')} (degrees)", color=colour)
        axis.tick_params(axis="y", colors=colour)
    perturb = np.flatnonzero(curve["op"] == "perturb")
    if len(perturb):  # the climb converged here; the perturbation rounds follow
        ax.axvline(t[perturb[0]], color="grey", ls=":", lw=1)
    ax.set_xlabel("seconds in operations (cumulative)")
    ax.set_title(
        f"the run: smallest {curve['min_dihedral'][0]:.1f} -> {curve['min_dihedral'][-1]:.1f}, "
        f"largest {curve['max_dihedral'][0]:.1f} -> {curve['max_dihedral'][-1]:.1f} degrees "
        "(hollow: no change; dotted: perturbation rounds)"
    )
    ax.legend(loc="center right", fontsize="small")


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
    _check_measure(stats, labels, measure)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    _draw_histograms(ax1, ax2, stats, labels, measure)
    _save_figure(fig, path)


def _check_measure(stats, labels, measure: str) -> None:
    missing = [lb for s, lb in zip(stats, labels, strict=True) if measure not in s.quality_hist]
    if missing:
        raise ValueError(f"the statistics of {', '.join(missing)} hold no {measure!r}")


def _draw_histograms(ax1, ax2, stats, labels, measure: str) -> None:
    """Dihedral angles in ``ax1``, ``measure`` in ``ax2``: one outline per mesh."""
    colours = [_COLOURS[i % len(_COLOURS)] for i in range(len(stats))]
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


def _save_figure(fig, path: str | os.PathLike) -> None:
    """Write ``fig`` to ``path`` atomically and close it (also when writing fails)."""
    import matplotlib.pyplot as plt

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
