"""Collect a sweep (a Hydra multirun directory) into one tidy table, a summary and plots.

    python experiments/aggregate.py outputs/sweeps/2026-01-01_12-00-00 [--out DIR]

Reads every ``metrics.json`` below the directory (one per run, written by
``experiments/run.py``) and writes into ``--out`` (default: the sweep directory):

- ``results.csv`` (and ``results.parquet`` when pyarrow is installed): one row per run,
- ``summary.md``: a markdown table per configuration and the plots below,
- ``worst_vs_time.png``: worst dihedral angle after improvement vs time, one point per run,
- ``histograms.png``: dihedral-angle histograms before / after, one panel per mesh.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

GROUPS = ("mesh", "optimizer", "quality", "smoothing", "experiment")


def collect(sweep: Path) -> pd.DataFrame:
    """One row per ``metrics.json`` under ``sweep``; adds ``run_dir`` and ``label``.

    ``label`` names a run's configuration by the config-group choices that vary across
    the sweep (all of them when nothing varies), e.g. ``mesh=cube quality=radius_ratio``.
    """
    rows = []
    for path in sorted(sweep.rglob("metrics.json")):
        row = json.loads(path.read_text())
        row["run_dir"] = str(path.parent.relative_to(sweep))
        rows.append(row)
    if not rows:
        raise SystemExit(f"aggregate: no metrics.json under {sweep}")
    df = pd.DataFrame(rows)
    groups = [g for g in GROUPS if g in df.columns]
    varying = [g for g in groups if df[g].astype(str).nunique() > 1] or ["mesh"]
    df["label"] = (
        df[varying]
        .astype(str)
        .apply(lambda r: " ".join(f"{g}={v}" for g, v in zip(varying, r, strict=True)), axis=1)
    )
    if "job" in df.columns and df["job"].notna().all():
        df = df.sort_values("job", kind="stable")
    return df.reset_index(drop=True)


def sweep_command(sweep: Path) -> str | None:
    """The ``run.py -m ...`` command of a Hydra sweep (from its ``multirun.yaml``)."""
    path = sweep / "multirun.yaml"
    if not path.exists():
        return None
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(path)
    task = list(OmegaConf.select(cfg, "hydra.overrides.task", default=[]) or [])
    own = OmegaConf.select(cfg, "hydra.overrides.hydra", default=[]) or []
    own = [o for o in own if not o.startswith("hydra.mode=")]  # Hydra adds it for -m
    return " ".join(["python experiments/run.py -m", *task, *own])


def _fmt(x, digits=2) -> str:
    if isinstance(x, float | np.floating):
        return "-" if np.isnan(x) else f"{x:.{digits}f}"
    return str(x)


def markdown_table(df: pd.DataFrame) -> str:
    """A markdown table: one line per run, the numbers people compare."""
    cols = [
        ("configuration", "label"),
        ("tets", "tets_after"),
        ("worst dihedral before", "min_dihedral_before"),
        ("worst dihedral after", "min_dihedral_after"),
        ("max dihedral after", "max_dihedral_after"),
        ("< 10 deg", "below_10_after"),
        ("< 20 deg", "below_20_after"),
        ("< 30 deg", "below_30_after"),
        ("seconds", "seconds"),
        ("status", "status"),
        ("valid", "valid"),
    ]
    cols = [(h, c) for h, c in cols if c in df.columns]
    lines = [
        "| " + " | ".join(h for h, _ in cols) + " |",
        "|" + "---|" * len(cols),
    ]
    for _, r in df.iterrows():
        lines.append("| " + " | ".join(_fmt(r[c]) for _, c in cols) + " |")
    return "\n".join(lines)


def plot_worst_vs_time(df: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = df.dropna(subset=["min_dihedral_after", "seconds"])
    fig, ax = plt.subplots(figsize=(7.5, 4.5), constrained_layout=True)
    # marker = mesh, colour = the rest of the configuration
    meshes = list(dict.fromkeys(ok["mesh_name"]))
    rest = ok["label"].map(lambda t: " ".join(w for w in t.split() if not w.startswith("mesh=")))
    colours = {c: f"C{i % 10}" for i, c in enumerate(dict.fromkeys(rest))}
    markers = "osD^vP*Xph"
    for (mesh, other), g in ok.groupby([ok["mesh_name"], rest], sort=False):
        ax.scatter(
            g["seconds"],
            g["min_dihedral_after"],
            s=40,
            color=colours[other],
            marker=markers[meshes.index(mesh) % len(markers)],
            label=f"{mesh} {other}".strip(),
        )
    ax.set_xlabel("improvement time (s)")
    ax.set_ylabel("worst dihedral angle after (degrees)")
    ax.set_title("worst dihedral angle vs time, one point per run")
    ax.grid(alpha=0.3)
    if ok["label"].nunique() <= 16:
        ax.legend(fontsize=7, loc="best")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_histograms(df: pd.DataFrame, sweep: Path, path: Path) -> None:
    """Dihedral histograms per mesh: the input (dashed) and every run's output."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meshes = list(dict.fromkeys(df["mesh_name"]))
    fig, axes = plt.subplots(
        1, len(meshes), figsize=(4.5 * len(meshes), 3.6), squeeze=False, constrained_layout=True
    )
    for ax, mesh in zip(axes[0], meshes, strict=True):
        drawn_input = False
        for _, r in df[df["mesh_name"] == mesh].iterrows():
            report = sweep / r["run_dir"] / "report.json"
            if not report.exists():
                continue
            rep = json.loads(report.read_text())
            before = np.asarray(rep["stats_before"]["dihedral_hist"], float)
            after = np.asarray(rep["stats_after"]["dihedral_hist"], float)
            edges = np.linspace(0.0, 180.0, len(after) + 1)
            if not drawn_input:
                ax.stairs(np.maximum(before, 0.5), edges, color="k", ls="--", label="input")
                drawn_input = True
            # the panel names the mesh already
            label = " ".join(w for w in r["label"].split() if not w.startswith("mesh="))
            ax.stairs(np.maximum(after, 0.5), edges, label=label or "output")
        ax.set_yscale("log")
        ax.set_ylim(bottom=0.8)
        ax.set_xlim(0, 180)
        ax.set_title(mesh)
        ax.set_xlabel("dihedral angle (degrees)")
        ax.legend(fontsize=6)
    axes[0][0].set_ylabel("number of angles (log)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def aggregate(sweep: Path, out: Path | None = None) -> pd.DataFrame:
    """Write results.csv (+ .parquet), summary.md and the plots; returns the table."""
    out = out or sweep
    out.mkdir(parents=True, exist_ok=True)
    df = collect(sweep)
    df.to_csv(out / "results.csv", index=False)
    wrote = ["results.csv"]
    try:
        import pyarrow  # noqa: F401

        df.to_parquet(out / "results.parquet", index=False)
        wrote.append("results.parquet")
    except ImportError:
        pass
    done = df[~df["status"].astype(str).str.startswith("error")]
    plots = []
    if len(done):
        plot_worst_vs_time(done, out / "worst_vs_time.png")
        plot_histograms(done, sweep, out / "histograms.png")
        plots = ["worst_vs_time.png", "histograms.png"]
    n_err = len(df) - len(done)
    md = [f"# Sweep {sweep.name}", ""]
    command = sweep_command(sweep)
    if command:
        md += [
            "Made by:",
            "",
            f"    {command}",
            f"    python experiments/aggregate.py {sweep}"
            + (f" --out {out}" if out != sweep else ""),
            "",
        ]
    md += [
        f"{len(df)} runs ({n_err} failed); angles in degrees, time in seconds "
        "(jtet.improve only, not mesh generation; the first run in each worker process "
        "also pays JIT compilation unless the persistent compilation cache is warm). "
        "Counts are tets whose smallest dihedral angle is below the threshold, after "
        "improvement.",
        "",
        "jtet revision(s): "
        + ", ".join(f"`{r}`" for r in dict.fromkeys(df.get("revision", pd.Series(["?"])))),
        "",
        markdown_table(df),
        "",
    ]
    md += [f"![{p}]({p})\n" for p in plots]
    (out / "summary.md").write_text("\n".join(md))
    wrote += ["summary.md", *plots]
    print(f"aggregate: {len(df)} runs -> {out}: {', '.join(wrote)}")
    return df


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweep", type=Path, help="a multirun directory (or any run directory)")
    ap.add_argument("--out", type=Path, help="output directory (default: the sweep directory)")
    args = ap.parse_args(argv)
    if not args.sweep.is_dir():
        print(f"aggregate: {args.sweep} is not a directory", file=sys.stderr)
        return 2
    aggregate(args.sweep, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
