"""Per-image appearance: an affine colour transform of each training photo's render.

Auto-exposure and white balance give ``photo = A_i @ radiance + b_i`` (A_i near a diagonal gain). As in
VastGaussian / Hierarchical-3DGS it acts on the render in training only, so the scene keeps the photos' common
look and their disagreement goes into 12 numbers a photo (not gsplat's bilateral grid, thousands a photo, nor the
appearance embedding, which can leak into view-dependent colour); test and viewer views render without it. It
starts from the measured gains (``analysis.photo_gains``), else the scene learns part of the disagreement.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding
from hico_plugin.analysis.photo_gains import exposure_finding, photo_gains
from hico_plugin.cameras import Camera
from hico_plugin.engine.optimizers import ParamGroupOptimizerConfig
from hico_plugin.model.effects.base import EFFECTS, Effect, EffectInputs
from hico_plugin.rasterizer import RenderOutputs


@EFFECTS.register("exposure")
class ExposureEffect(Effect):
    """Per-photo exposure and white balance (``analysis.photo_gains``): an affine colour transform of
    each training photo's render, starting from the gains the analysis measured."""

    finding = "exposure"
    stage = 10  # the camera's response to the whole image, after everything in the scene

    def detect(self, evidence: DatasetEvidence) -> EffectFinding:
        return exposure_finding(evidence)

    def build(self, inputs: EffectInputs) -> "AffineColour":
        # measured once per evidence: the analysis's own gains, or measured here when every effect was forced
        gains = photo_gains(inputs.evidence)[0][inputs.train_ids.numpy()]  # [C,3] log2, NaN = unknown
        return AffineColour(len(inputs.train_ids), torch.from_numpy(gains))

    def default_lrs(self) -> dict[str, ParamGroupOptimizerConfig]:
        return {"exposure": ParamGroupOptimizerConfig(2e-3, 1e-4)}  # settles a 0.35-stop gain within a few hundred steps

    def apply(self, module: "AffineColour", out: RenderOutputs, camera: Camera) -> Tensor:
        return module(out.rgb, camera.index)  # the photo's exposure (training views only)

    def bake_colors(self, module: "AffineColour", colors: Tensor, camera: Camera) -> Tensor:
        # An affine map passes through alpha blending (sum w_i (A c_i + b) = A sum w_i c_i + alpha b):
        # exact wherever the Gaussians cover the pixel.
        return module(colors, camera.index)


class AffineColour(nn.Module):
    """rgb' = rgb @ A[slot]^T + b[slot] for training slot ``slot`` (identity for slot < 0)."""

    def __init__(self, num_train_views: int, log2_gains: Tensor | None = None):
        """``log2_gains`` [C,3]: measured per-channel gain of each training photo (NaN = unknown,
        starts at identity)."""
        super().__init__()
        count = max(1, num_train_views)
        gains = torch.ones(count, 3)
        if log2_gains is not None:
            gains[: len(log2_gains)] = torch.nan_to_num(2.0 ** log2_gains.float(), nan=1.0)
        self.matrix = nn.Parameter(torch.diag_embed(gains))  # [C,3,3]
        self.bias = nn.Parameter(torch.zeros(count, 3))  # [C,3]

    def forward(self, rgb: Tensor, slot: int) -> Tensor:
        """rgb [..., 3] (an image [H,W,3], or colours [N,3]) -> the same shape."""
        if slot < 0 or slot >= self.matrix.shape[0]:
            return rgb
        # one affine matmul (bias added inside it): a third faster than matmul then add on a 540x960 image
        return F.linear(rgb, self.matrix[slot], self.bias[slot])
