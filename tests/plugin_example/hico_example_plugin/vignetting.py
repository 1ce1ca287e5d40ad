"""An effect from outside: ``vignetting``, the lens's brightness fall-off toward the image corners.

The effect answers a finding of its own (no built-in analysis measures it): the median ratio of the
brightness of the image's corner regions to its centre over the sampled photos. Its module is a
learned radial gain, ``rgb * (1 + k1 r^2 + k2 r^4)`` with ``r`` the distance from the principal point
over the half-diagonal, applied to the scene's image before the camera's exposure.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding, sampled_views
from hico_plugin.cameras import Camera
from hico_plugin.engine.optimizers import ParamGroupOptimizerConfig
from hico_plugin.model.effects import EFFECTS, Effect, EffectInputs
from hico_plugin.rasterizer import RenderOutputs

MAX_CORNER_RATIO = 0.85  # corners darker than this share of the centre's brightness: vignetting


@EFFECTS.register("vignetting")
class VignettingEffect(Effect):
    """Lens vignetting: a learned radial fall-off of the image's brightness."""

    finding = "vignetting"
    stage = 5  # a property of the lens: after the scene, before the exposure of the whole image

    def detect(self, evidence: DatasetEvidence) -> EffectFinding:
        dataset = evidence.dataset
        ratios = []
        for view in sampled_views(dataset):
            image = dataset.image(int(view)).numpy().astype(np.float64).mean(axis=2)
            h, w = image.shape
            ch, cw = max(1, h // 8), max(1, w // 8)
            centre = image[h // 2 - ch: h // 2 + ch, w // 2 - cw: w // 2 + cw].mean()
            corners = np.mean([image[:ch, :cw].mean(), image[:ch, -cw:].mean(), image[-ch:, :cw].mean(), image[-ch:, -cw:].mean()])
            if centre > 0:
                ratios.append(corners / centre)
        ratio = float(np.median(ratios)) if ratios else 1.0
        return EffectFinding(ratio < MAX_CORNER_RATIO, f"corners at {ratio:.2f} of the centre's brightness "
                             f"(threshold {MAX_CORNER_RATIO})", {"corner_ratio": round(ratio, 4)})

    def build(self, inputs: EffectInputs) -> "RadialGain":
        return RadialGain()

    def default_lrs(self) -> dict[str, ParamGroupOptimizerConfig]:
        return {"vignetting": ParamGroupOptimizerConfig(1e-3)}

    def apply(self, module: "RadialGain", out: RenderOutputs, camera: Camera) -> Tensor:
        return module(out.rgb, camera)


class RadialGain(nn.Module):
    """rgb [H,W,3] * (1 + k1 r^2 + k2 r^4), k = 0 at the start (no fall-off)."""

    def __init__(self):
        super().__init__()
        self.k = nn.Parameter(torch.zeros(2))

    def forward(self, rgb: Tensor, camera: Camera) -> Tensor:
        height, width = rgb.shape[:2]
        ys = torch.arange(height, dtype=rgb.dtype, device=rgb.device) + 0.5 - camera.K[1, 2]
        xs = torch.arange(width, dtype=rgb.dtype, device=rgb.device) + 0.5 - camera.K[0, 2]
        r2 = (ys[:, None] ** 2 + xs[None, :] ** 2) / (0.25 * (height**2 + width**2))
        return rgb * (1.0 + self.k[0] * r2 + self.k[1] * r2**2)[..., None]
