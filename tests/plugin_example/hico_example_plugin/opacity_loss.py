"""A loss from outside: ``opacity-entropy`` pushes every pixel's accumulated opacity towards 0 or 1
(a common regulariser against semi-transparent floaters).

Registering the config is all it takes: ``hico-train`` then offers ``--model.losses.opacity-entropy.enabled``
and ``--model.losses.opacity-entropy.weight`` on every preset (switched off unless asked for), the
model renders alpha while it is on, and its term is logged as ``loss/opacity_entropy``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.losses.base import LOSSES, LossConfig, require_images
from hico_plugin.rasterizer.base import RenderOutputs

EPS = 1e-6  # keeps log() finite at alpha = 0 or 1


class OpacityEntropyLoss:
    """``opacity_entropy`` = weight * mean over pixels of the binary entropy of alpha."""

    def __init__(self, weight: float):
        self.weight = weight

    def required_outputs(self, step: int) -> set[str]:
        return {"alpha"}

    def __call__(self, outputs: RenderOutputs, target: Tensor, step: int) -> dict[str, Tensor]:
        alpha = require_images(outputs, {"alpha"}, "opacity-entropy")["alpha"].clamp(EPS, 1.0 - EPS)  # [..., H, W, 1]
        entropy = -(alpha * alpha.log() + (1.0 - alpha) * (1.0 - alpha).log())
        return {"opacity_entropy": self.weight * entropy.mean()}


@LOSSES.register("opacity-entropy")
@dataclass
class OpacityEntropyLossConfig(LossConfig):
    """Binary-entropy regulariser on the accumulated opacity (alpha) of every pixel."""

    weight: float = 0.01
    """Weight of the mean binary entropy of alpha."""

    def setup(self, schedule_scale: float = 1.0, **kwargs: Any) -> OpacityEntropyLoss:
        if self.weight < 0:
            raise HicoError(f"losses.opacity-entropy.weight must be >= 0, got {self.weight}")
        return OpacityEntropyLoss(self.weight)
