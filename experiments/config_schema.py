"""Structured-config schema of the experiments, derived from ``jtet.Options``.

``register()`` stores ``RunConfig`` in Hydra's ConfigStore as ``run_schema``;
``configs/config.yaml`` lists it first in its defaults, so every composed config is typed
and closed: a key that is not a field of ``jtet.Options`` (``optimizer.max_rng=5``) or a
value of the wrong type (``optimizer.max_ring=seven``) is an error at composition time,
never a silent default. ``OptimizerConfig`` is generated from ``jtet.Options``' fields
(names, types and defaults), so the schema cannot drift from the options object, and
``to_options(cfg.optimizer)`` builds the ``jtet.Options`` itself, which raises on unknown
keys and checks the values (``max_ring`` in 3..16, known measure, ...).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Optional

from omegaconf import MISSING, DictConfig, OmegaConf

import jtet


def _omegaconf_type(tp):
    """The OmegaConf-compatible version of a ``jtet.Options`` field annotation.

    ``tuple[str, ...]`` -> ``list[str]`` (YAML lists); ``X | None`` -> ``Optional[X]``;
    ``int | str`` (``perturb``: a count or "auto") -> ``Any``.
    """
    origin = typing.get_origin(tp)
    if origin in (types.UnionType, typing.Union):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) != 1:
            # OmegaConf types no unions but Optional; jtet.Options checks the value
            return Any
        return Optional[_omegaconf_type(args[0])]  # noqa: UP045 (OmegaConf wants Optional)
    if origin is tuple:
        item = typing.get_args(tp)[0]
        if typing.get_origin(item) in (types.UnionType, typing.Union):
            # region labels or names: OmegaConf takes no unions inside containers, and
            # jtet.Options checks the values anyway
            return list[Any]
        return list[item]
    if tp in (int, float, bool, str):
        return tp
    raise TypeError(f"unsupported option type {tp}")


def _optimizer_fields() -> list[tuple[str, Any, Any]]:
    hints = typing.get_type_hints(jtet.Options)
    out = []
    for f in dataclasses.fields(jtet.Options):
        default = f.default
        if isinstance(default, tuple):
            spec = field(default_factory=lambda d=default: list(d))
        else:
            spec = field(default=default)
        out.append((f.name, _omegaconf_type(hints[f.name]), spec))
    return out


OptimizerConfig = dataclasses.make_dataclass("OptimizerConfig", _optimizer_fields())
OptimizerConfig.__doc__ = "Schema of ``cfg.optimizer``: exactly the fields of ``jtet.Options``."


@dataclass
class MeshConfig:
    """Schema of ``cfg.mesh``: a generator of ``experiments/meshgen.py`` and its arguments.

    ``params`` is open (each generator has its own arguments); ``meshgen.check`` validates
    it against the generator's signature.
    """

    name: str = MISSING
    generator: str = MISSING
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class RunConfig:
    """Schema of the whole run config (``configs/config.yaml``)."""

    mesh: MeshConfig = field(default_factory=MeshConfig)
    optimizer: OptimizerConfig = field(default_factory=OptimizerConfig)
    save_input: bool = False  # also write the generated input mesh (input.vtu)
    save_mesh: bool = True  # write the improved mesh with per-tet quality arrays
    mesh_format: str = (
        "vtu"  # of improved.* / input.*: vtu, xdmf (dolfinx), msh, mesh, inp, vol (NGSolve), ...
    )
    plot: bool = True  # write before/after histograms (histograms.png)
    fail_fast: bool = False  # re-raise a run's error (default: record it in metrics.json)


def register() -> None:
    """Store the schema in Hydra's ConfigStore (name ``run_schema``); idempotent."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name="run_schema", node=RunConfig)


def to_options(optimizer: DictConfig | dict) -> jtet.Options:
    """``jtet.Options`` from ``cfg.optimizer``; raises ``TypeError`` on unknown keys and
    ``jtet.JtetError`` on bad values."""
    if isinstance(optimizer, DictConfig):
        optimizer = OmegaConf.to_container(optimizer, resolve=True)
    return jtet.Options(**optimizer)
