"""Losses: photometric (L1 + D-SSIM), depth-normal geometric consistency (DNGC), and any loss a plug-in registers
in ``LOSSES``.

A model's losses are ``{name: LossConfig}`` (``default_losses()``: every registered loss at its defaults);
``Losses.setup(configs, schedule_scale=run_steps / reference_steps)`` builds the enabled ones, which name the
render outputs a step needs (``losses.required_outputs(step)``) and return named terms the model sums
(``losses(outputs, target_rgb, step)`` -> {"rgb_l1": ..., "rgb_dssim": ..., "dngc_nc": ...}).
"""

from __future__ import annotations

import importlib
import pkgutil

from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.losses.base import LOSSES, LossComponent, LossConfig, require_images
# Photometric first: import order is registration order, the order of default_losses() and of the summed terms.
from hico_plugin.losses.photometric import PhotometricLoss, PhotometricLossConfig, photometric_terms  # isort: skip
from hico_plugin.losses.dngc import (
    DNGCLoss,
    DNGCLossConfig,
    dngc_losses,
    edge_aware_smoothness,
    edge_weights,
    normal_consistency_loss,
    warmup_weight,
)
from hico_plugin.rasterizer.base import RenderOutputs


class Losses:
    """Several loss components behind the single-component contract."""

    def __init__(self, components: dict[str, LossComponent]):
        self.components = components

    @classmethod
    def setup(cls, configs: dict[str, LossConfig], schedule_scale: float = 1.0) -> Losses:
        """The components of the enabled ``configs``, in their order (the order the terms are summed);
        ``schedule_scale`` (run length / reference length) scales their step schedules."""
        for name, config in configs.items():
            if not isinstance(config, LossConfig):
                raise HicoError(f"model.losses.{name}: expected a loss config (registered: "
                                f"{', '.join(LOSSES.names())}), got {type(config).__name__}")
        return cls({name: config.setup(schedule_scale=schedule_scale)
                    for name, config in configs.items() if config.enabled})

    def required_outputs(self, step: int) -> set[str]:
        """Union of the render outputs every component reads at ``step``."""
        return set().union(*(c.required_outputs(step) for c in self.components.values()))

    def __call__(self, outputs: RenderOutputs, target: Tensor, step: int) -> dict[str, Tensor]:
        terms: dict[str, Tensor] = {}
        for component in self.components.values():
            terms.update(component(outputs, target, step))
        return terms

    def metrics(self, step: int) -> dict[str, float]:
        """What the components report about their schedules at ``step`` (e.g. DNGC's w(t))."""
        out: dict[str, float] = {}
        for component in self.components.values():
            out.update(getattr(component, "metrics", lambda step: {})(step))
        return out


# Every module of this package registers its loss on import, so a new loss is one file here (after the
# built-ins imported above).
for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")


def default_losses() -> dict[str, LossConfig]:
    """Every loss registered so far, at its defaults, in registration order (a model config's default;
    built while this package may still be importing, so it does not load plug-ins itself)."""
    return {name: config() for name, config in LOSSES.registered()}


def with_every_loss(losses: dict[str, LossConfig]) -> dict[str, LossConfig]:
    """``losses`` and, switched off, every registered loss (installed plug-ins' too) it does not name:
    each is then a ``--model.losses.NAME...`` option, and installing a plug-in changes no config."""
    return {**losses, **{name: config(enabled=False) for name, config in LOSSES.items() if name not in losses}}


__all__ = [
    "DNGCLoss", "DNGCLossConfig", "LOSSES", "LossComponent", "LossConfig", "Losses", "PhotometricLoss",
    "PhotometricLossConfig", "default_losses", "dngc_losses", "edge_aware_smoothness", "edge_weights",
    "normal_consistency_loss", "photometric_terms", "require_images", "warmup_weight", "with_every_loss",
]
