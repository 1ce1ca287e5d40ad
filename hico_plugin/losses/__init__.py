"""Losses: photometric (L1 + D-SSIM) and depth-normal geometric consistency (DNGC).

``LossesConfig().setup()`` builds the method's loss set; the model asks it which render outputs a step
needs and sums the named terms it returns::

    losses = LossesConfig().setup()
    outputs = rasterize(..., outputs=tuple(losses.required_outputs(step)))
    terms = losses(outputs, target_rgb, step)      # {"rgb_l1": ..., "rgb_dssim": ..., "dngc_nc": ...}
    loss = sum(terms.values())
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from torch import Tensor

from hico_plugin.config import InstantiateConfig
from hico_plugin.losses.base import LOSSES, LossComponent, require_images
from hico_plugin.losses.dngc import (
    DNGCLoss,
    DNGCLossConfig,
    dngc_losses,
    edge_aware_smoothness,
    edge_weights,
    normal_consistency_loss,
    warmup_weight,
)
from hico_plugin.losses.photometric import PhotometricLoss, PhotometricLossConfig, photometric_terms
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


@dataclass
class LossesConfig(InstantiateConfig):
    """The method's losses; each field is one registered loss component's config."""

    rgb: PhotometricLossConfig = field(default_factory=PhotometricLossConfig)
    """Photometric loss."""
    dngc: DNGCLossConfig = field(default_factory=DNGCLossConfig)
    """Depth-normal geometric consistency."""

    def setup(self, **kwargs) -> Losses:
        return Losses({f.name: getattr(self, f.name).setup() for f in fields(self)})


__all__ = [
    "DNGCLoss", "DNGCLossConfig", "LOSSES", "LossComponent", "Losses", "LossesConfig", "PhotometricLoss",
    "PhotometricLossConfig", "dngc_losses", "edge_aware_smoothness", "edge_weights", "normal_consistency_loss",
    "photometric_terms", "require_images", "warmup_weight",
]
