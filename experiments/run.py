"""One experiment run: generate (or load) a mesh, improve it with jtet, record everything.

    python experiments/run.py                                  # cube, jtet defaults
    python experiments/run.py mesh=sphere quality=radius_ratio optimizer=edge
    python experiments/run.py mesh=file mesh.params.path=in.vtu
    python experiments/run.py -m mesh=cube,sphere quality=min_sine,radius_ratio   # sweep
    python experiments/run.py -m experiment=reference hydra/launcher=submitit_slurm

Configs live in ``configs/`` (see ``experiments/README.md``). Each run writes into its Hydra
run directory (``outputs/runs/...`` or ``outputs/sweeps/<time>/<job number>``):

- ``improved.vtu``: the improved mesh with per-tet quality arrays (``save_mesh``; another
  format with ``mesh_format``, e.g. ``mesh_format=xdmf`` for dolfinx, ``msh`` for Gmsh),
- ``input.vtu``: the generated input mesh (``save_input``),
- ``report.json``: jtet's JSON report (options, statistics before / after, history),
- ``history.csv``: one row per operation of each pass,
- ``histograms.png``: before / after histograms (``plot``),
- ``metrics.json``: one flat row of numbers for ``experiments/aggregate.py``,
- ``.hydra/``: the composed config and the overrides (Hydra's own record).
"""

from __future__ import annotations

import csv
import io
import json
import os
import sys
import time
import traceback
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

HERE = str(Path(__file__).resolve().parent)
sys.path.insert(0, HERE)
# Launchers that start fresh interpreters (submitit: local processes or SLURM tasks) unpickle
# the config, whose schema classes live in config_schema: let them import it too.
os.environ["PYTHONPATH"] = os.pathsep.join(
    [HERE, *(p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p)]
)

import config_schema  # noqa: E402
import meshgen  # noqa: E402

import jtet  # noqa: E402
from jtet import _helper_process  # noqa: E402
from jtet._driver import _gave_up, _kept, _kept_rounds, _kicks  # noqa: E402
from jtet._io import output_format  # noqa: E402
from jtet._report import quality_cell_data, write_report, write_text_atomic  # noqa: E402

config_schema.register()

GROUPS = ("mesh", "optimizer", "quality", "smoothing", "experiment")


def mesh_params(cfg: DictConfig) -> dict:
    """``cfg.mesh.params`` as a dict, with a ``path`` made absolute (from the launch dir)."""
    params = OmegaConf.to_container(cfg.mesh.params, resolve=True)
    if "path" in params:
        params["path"] = hydra.utils.to_absolute_path(str(params["path"]))
    return params


def history_csv(history: list[dict]) -> str:
    """CSV text of jtet's history: union of the keys in order of appearance, nested
    values (lists, dicts) as JSON."""
    keys = list(dict.fromkeys(k for entry in history for k in entry))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys, lineterminator="\n")
    w.writeheader()
    for entry in history:
        w.writerow(
            {k: json.dumps(v) if isinstance(v, list | dict) else v for k, v in entry.items()}
        )
    return buf.getvalue()


def _stats_columns(s, suffix: str, measure: str) -> dict:
    return {
        f"tets_{suffix}": s.n_tets,
        f"min_dihedral_{suffix}": s.min_dihedral,
        f"max_dihedral_{suffix}": s.max_dihedral,
        **{f"below_{a}_{suffix}": int(s.small_dihedral[a]) for a in (10, 20, 30)},
        **{f"above_{a}_{suffix}": int(s.large_dihedral[a]) for a in (150, 160, 170)},
        f"worst_quality_{suffix}": s.quality_min[measure],
        f"mean_quality_{suffix}": s.quality_mean[measure],
        f"inverted_{suffix}": s.n_inverted,
    }


def revision() -> str:
    """``git describe --always --dirty`` of the checkout (which code made the numbers)."""
    import subprocess

    try:
        proc = subprocess.run(
            ["git", "describe", "--always", "--dirty"],
            cwd=HERE,
            capture_output=True,
            text=True,
            timeout=30,
        )
    except OSError:
        return "?"
    return proc.stdout.strip() or "?"


def run(cfg: DictConfig, out: Path, choices: dict) -> dict:
    """Do one run into directory ``out``; returns the metrics row (also in metrics.json)."""
    # configuration errors (unknown keys, bad values) raise here, before any work
    opts = config_schema.to_options(cfg.optimizer)
    params = mesh_params(cfg)
    meshgen.check(cfg.mesh.generator, params)
    ext = "." + str(cfg.get("mesh_format", "vtu")).lstrip(".")
    output_format(out / f"improved{ext}")  # an unknown format fails before the work
    row: dict = {
        **{g: choices.get(g) for g in GROUPS},
        "mesh_name": cfg.mesh.name,
        "generator": cfg.mesh.generator,
        "ops": "+".join(opts.ops),
        "quality": opts.quality,
        "max_ring": opts.max_ring,
        "max_faces": opts.max_faces,
        "boundary": opts.boundary,
        "seed": opts.seed,
        "mesh_seed": params.get("seed"),
        "revision": revision(),
        # whether a perturbation helper process may run beside this one (timings differ)
        "perturb_helper": _helper_process.enabled(),
    }
    try:
        t0 = time.perf_counter()
        mesh = meshgen.generate(cfg.mesh.generator, params)
        row["mesh_seconds"] = time.perf_counter() - t0
        if cfg.save_input:
            jtet.save(mesh, out / f"input{ext}", cell_data=quality_cell_data(mesh))
        result = jtet.improve(mesh, opts)
        report = result.mesh.is_valid()
        kicks = _kicks(result.history)
        row.update(
            _stats_columns(result.stats_before, "before", opts.quality)
            | _stats_columns(result.stats_after, "after", opts.quality)
        )
        row.update(
            seconds=result.seconds,
            status=result.status,
            valid=bool(report.ok),
            passes=1 + max((e["pass"] for e in result.history), default=-1),
            # the limit of kept perturbation rounds (perturb, or auto's count for the mesh)
            perturb_rounds=result.perturb_rounds,
            # the rounds' attempts: kept, tried, and those whose climb was given up
            perturb_kept=_kept(kicks),
            perturb_kept_rounds=_kept_rounds(kicks),
            perturb_tried=len(kicks),
            perturb_gave_up=_gave_up(kicks),
            regions=int(len(set(result.mesh.region.tolist()))),
        )
        if cfg.save_mesh:
            cells = quality_cell_data(result.mesh)
            jtet.save(result.mesh, out / f"improved{ext}", cell_data=cells)
        write_report(result, out / "report.json")
        write_text_atomic(out / "history.csv", history_csv(result.history))
        if cfg.plot:
            from jtet._report import plot_run

            plot_run(result, out / "histograms.png")
    except Exception as e:
        # a failed run is a row too (status "error"), so one bad configuration does not
        # sink a whole sweep; fail_fast=true re-raises instead
        row.update(status=f"error: {type(e).__name__}: {e}", valid=False)
        write_text_atomic(out / "error.txt", traceback.format_exc())
        write_text_atomic(out / "metrics.json", json.dumps(row, indent=1))
        if cfg.get("fail_fast", False):
            raise
        print(f"run failed ({out}): {row['status']}", file=sys.stderr)
        return row
    write_text_atomic(out / "metrics.json", json.dumps(row, indent=1))
    return row


def jobs_side_by_side(launcher: DictConfig) -> bool:
    """Whether a sweep's launcher runs several jobs at once on this machine: joblib
    unless ``n_jobs`` is 1 (its -1, Hydra's default, means one per core), and submitit's
    local mode (the array at once). The basic launcher runs them one after the other,
    and SLURM gives each its own cores."""
    target = str(launcher.get("_target_", ""))
    if target.endswith(".JoblibLauncher"):
        n_jobs = launcher.get("n_jobs")
        return n_jobs is not None and int(n_jobs) != 1
    return target.endswith("submitit_launcher.LocalLauncher")


@hydra.main(version_base=None, config_path="../configs", config_name="config")
def main(cfg: DictConfig) -> dict:
    hc = HydraConfig.get()
    if hc.mode.name == "MULTIRUN" and jobs_side_by_side(hc.launcher):
        # jobs side by side already use the cores: a helper process per job for the
        # perturbation rounds (jtet._helper_process) would only compete with them
        os.environ["JTET_HELPER"] = "0"
    out = Path(hc.runtime.output_dir)
    choices = {k: v for k, v in hc.runtime.choices.items() if not k.startswith("hydra/")}
    row = run(cfg, out, choices)
    row["job"] = hc.job.num if hc.mode.name == "MULTIRUN" else None
    row["overrides"] = " ".join(hc.overrides.task)
    write_text_atomic(out / "metrics.json", json.dumps(row, indent=1))
    print(
        f"{row['mesh_name']} [{row['ops']}, {row['quality']}]: "
        f"{row.get('min_dihedral_before', float('nan')):.2f} -> "
        f"{row.get('min_dihedral_after', float('nan')):.2f} deg worst dihedral, "
        f"{row['status']}, {row.get('seconds', 0.0):.1f} s -> {out}"
    )
    return row


if __name__ == "__main__":
    main()
