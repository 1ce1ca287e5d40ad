"""Method presets: each a named, fully filled training config (``hico-train NAME``).

``hico-gs`` is the paper's setting; the others are the paper's ablation rows (Table 5) and a preset
sized for a 2-core CPU. Any field can still be overridden from the command line, e.g.
``hico-train hico-gs --model.field.context.kind max --model.renderer.backend gsplat``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field as dataclass_field
from typing import Annotated, Any

import torch
import tyro

from hico_plugin.data.sources import DataSourceConfig
from hico_plugin.engine.resolution import ResolutionSchedule
from hico_plugin.engine.trainer import TrainerConfig
from hico_plugin.losses import with_every_loss
from hico_plugin.model.hico import HiCoModelConfig
from hico_plugin.registry import load_plugins
from hico_plugin.viewer.config import ViewerConfig


@dataclass
class HiCoTrainerConfig(TrainerConfig):
    """A HiCo-GS training run."""

    data: Annotated[DataSourceConfig, tyro.conf.OmitArgPrefixes] = dataclass_field(
        default_factory=DataSourceConfig)
    """Training data: --data DIR (COLMAP) or, without it, the built-in --scene."""
    model: HiCoModelConfig = dataclass_field(default_factory=HiCoModelConfig)
    """The model and its components."""
    viewer: ViewerConfig = dataclass_field(default_factory=ViewerConfig)
    """Live viewer (started when --vis is viewer, or auto on a terminal)."""

    def build_model(self, dataset: Any, device: torch.device) -> Any:
        # The model needs the run length to scale its schedules (levels, densification, DNGC t0 / T).
        return self.model.setup(dataset=dataset, total_steps=self.max_steps).to(device)


def _with(config: HiCoTrainerConfig, method_name: str, *, context: str | None = None, dngc: bool | None = None,
          parent_rule: str | None = None, **trainer_fields: Any) -> HiCoTrainerConfig:
    """A copy of ``config`` with a method name, a context aggregator kind / parent rule and DNGC on/off."""
    model = config.model
    changes = {k: v for k, v in (("kind", context), ("parent_rule", parent_rule)) if v is not None}
    if changes:
        model = dataclasses.replace(model, field=dataclasses.replace(
            model.field, context=dataclasses.replace(model.field.context, **changes)))
    if dngc is not None:
        model = dataclasses.replace(model, losses={
            **model.losses, "dngc": dataclasses.replace(model.losses["dngc"], enabled=dngc)})
    return dataclasses.replace(config, method_name=method_name, model=model, **trainer_fields)


def _paper() -> HiCoTrainerConfig:
    """The paper's setting (Sec. 4.1): 30k steps, CLCA (mean) + DNGC with t0 = 10k, T = 10k."""
    return HiCoTrainerConfig(method_name="hico-gs", max_steps=30_000, eval_every=5_000, save_every=5_000)


def _lite() -> HiCoTrainerConfig:
    """HiCo-GS sized for a 2-core CPU: the paper's method and proportions on a 3,500-step schedule.

    Besides the length (figures: benchmarks/RESULTS.md, "Figures behind the defaults"): anchors adjusted every 750
    reference steps, not 100 (scaled down, a decision would average a handful of views); photos over 320 px train
    coarse to fine (``ResolutionSchedule``, pixels rising with the cube of progress); octree levels only where
    they beat one flat level (``lod_rule="measured"``); every level on by a sixth of the run (``coarse_steps``
    5,000), not CityGS-X's third; final LPIPS with AlexNet, faster than VGG (``--model.eval-lpips vgg``: the
    paper's)."""
    config = _with(_paper(), "hico-gs-lite", max_steps=3_500, steps_photos=64, eval_every=0, save_every=500,
                   resolution=ResolutionSchedule(start_scale=0.25, full_at=1.0, min_long_side=320,
                                                  ramp_power=3.0))
    field = config.model.field
    field = dataclasses.replace(field, densify=dataclasses.replace(field.densify, interval=750), coarse_steps=5_000,
                                sparse_grad=True)
    return dataclasses.replace(config, model=dataclasses.replace(config.model, field=field, lod_rule="measured",
                                                                 eval_lpips="alex"))


PRESETS: dict[str, tuple[str, HiCoTrainerConfig]] = {
    "hico-gs": ("HiCo-GS with the paper's defaults (CLCA mean + DNGC).", _paper()),
    "hico-gs-lite": ("HiCo-GS sized for a 2-core CPU (the README's main command).", _lite()),
    "octree-gs": ("Baseline: octree anchors without CLCA and without DNGC.",
                  _with(_paper(), "octree-gs", context="none", dngc=False)),
    "hico-gs-clca": ("Ablation: CLCA only (no DNGC).", _with(_paper(), "hico-gs-clca", dngc=False)),
    "hico-gs-clca-paper": ("Ablation: CLCA only, with the paper's literal parent lookup (round, self fallback).",
                           _with(_paper(), "hico-gs-clca-paper", dngc=False, parent_rule="paper")),
    "hico-gs-dngc": ("Ablation: DNGC only (no CLCA).", _with(_paper(), "hico-gs-dngc", context="none")),
    "hico-gs-max": ("Ablation: CLCA with max pooling instead of the MLP-mean triplet.",
                    _with(_paper(), "hico-gs-max", context="max")),
    "hico-gs-attn": ("Ablation: CLCA with attention over the triplet.",
                     _with(_paper(), "hico-gs-attn", context="attention")),
}
"""Preset name -> (description, config); plug-ins add theirs with ``register_preset``."""

_BUILT_IN = tuple(PRESETS)


def register_preset(name: str, description: str, config: HiCoTrainerConfig) -> None:
    """Make ``config`` trainable as ``hico-train NAME`` and listed by ``hico-train --help``; called by a
    plug-in module named in the ``hico_plugin.components`` entry-point group."""
    if name in PRESETS and PRESETS[name][1] is not config:
        raise ValueError(f"preset '{name}' is already registered")
    PRESETS[name] = (description, config)


def all_presets() -> dict[str, tuple[str, HiCoTrainerConfig]]:
    """The built-in presets and those of every installed plug-in, each offering every registered loss
    (those it does not name switched off)."""
    load_plugins()
    return {name: (description, dataclasses.replace(config, model=dataclasses.replace(
        config.model, losses=with_every_loss(config.model.losses)))) for name, (description, config) in PRESETS.items()}


def write_preset_files(directory: str) -> None:
    """Write every preset as ``DIRECTORY/<name>.yml`` (the repository's ``configs/``): the resolved
    configs, readable and loadable with ``hico_plugin.engine.load_config``. Regenerate them with
    ``python -c "from hico_plugin.presets import write_preset_files; write_preset_files('configs')"``."""
    from pathlib import Path

    from hico_plugin.engine.config_io import save_config

    for name in _BUILT_IN:
        config = PRESETS[name][1]
        save_config(config, Path(directory) / f"{name}.yml")

