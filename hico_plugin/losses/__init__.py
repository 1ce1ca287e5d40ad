"""Losses: photometric (L1 + D-SSIM) and depth-normal geometric consistency (DNGC).

``LossesConfig().setup()`` builds the method's loss set; the model asks it which render outputs a step
needs and sums the named terms it returns::

    losses = LossesConfig().setup(schedule_scale=run_steps / reference_steps)
    outputs = rasterize(..., outputs=tuple(losses.required_outputs(step)))
    terms = losses(outputs, target_rgb, step)      # {"rgb_l1": ..., "rgb_dssim": ..., "dngc_nc": ...}
    loss = sum(terms.values())
"""

from __future__ import annotations

import importlib
import pkgutil
from dataclasses import field, fields, make_dataclass

from torch import Tensor

from hico_plugin.config import InstantiateConfig
from hico_plugin.losses.base import LOSSES, LossComponent, require_images
# Photometric first: import order is registration order, the order of the config fields and summed terms.
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


def _setup(self, schedule_scale: float = 1.0, **kwargs) -> Losses:
    """Build every loss; ``schedule_scale`` (run length / reference length) scales their step schedules."""
    return Losses({f.name: getattr(self, f.name).setup(schedule_scale=schedule_scale) for f in fields(self)})


LossesConfig = make_dataclass(
    "LossesConfig", [(name, config, field(default_factory=config)) for name, config in LOSSES.registered()],
    bases=(InstantiateConfig,), namespace={"setup": _setup})
LossesConfig.__module__ = __name__
LossesConfig.__doc__ = "The method's losses: one field per registered loss (LOSSES), by its name."


__all__ = [
    "DNGCLoss", "DNGCLossConfig", "LOSSES", "LossComponent", "Losses", "LossesConfig", "PhotometricLoss",
    "PhotometricLossConfig", "dngc_losses", "edge_aware_smoothness", "edge_weights", "normal_consistency_loss",
    "photometric_terms", "require_images", "warmup_weight",
]
