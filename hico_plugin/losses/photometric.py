"""Photometric loss of 3DGS / Octree-GS / CityGS-X: (1 - lambda) * L1 + lambda * (1 - SSIM)."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.losses.base import LOSSES, LossConfig, require_images
from hico_plugin.metrics.image import ssim
from hico_plugin.rasterizer.base import RenderOutputs


def photometric_terms(rgb: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """Unweighted (L1, 1 - SSIM) of a rendered image against its target.

    rgb, target: [H, W, 3] or [C, H, W, 3] in [0, 1]; L1 is the mean over pixels and channels, SSIM the
    mean over cameras (11x11 Gaussian window, sigma 1.5, pytorch-msssim).
    """
    if rgb.shape != target.shape:
        raise HicoError(f"photometric loss: rendered rgb {tuple(rgb.shape)} and target image {tuple(target.shape)} differ in shape")
    l1 = (rgb - target).abs().mean()
    return l1, 1.0 - ssim(rgb, target).mean()


class PhotometricLoss:
    """``rgb_l1`` = (1 - lambda) L1 and ``rgb_dssim`` = lambda (1 - SSIM)."""

    def __init__(self, config: "PhotometricLossConfig"):
        self.config = config

    def required_outputs(self, step: int) -> set[str]:
        return {"rgb"}

    def __call__(self, outputs: RenderOutputs, target: Tensor, step: int) -> dict[str, Tensor]:
        rgb = require_images(outputs, {"rgb"}, "rgb")["rgb"]
        l1, dssim = photometric_terms(rgb, target)
        weight = self.config.ssim_lambda
        return {"rgb_l1": (1.0 - weight) * l1, "rgb_dssim": weight * dssim}


@LOSSES.register("rgb")
@dataclass
class PhotometricLossConfig(LossConfig):
    """Photometric reconstruction loss (1 - lambda) L1 + lambda D-SSIM."""

    ssim_lambda: float = 0.2
    """lambda: weight of the D-SSIM term (1 - lambda goes to L1); 0.2 as 3DGS and CityGS-X."""

    def setup(self, **kwargs) -> PhotometricLoss:
        if not 0.0 <= self.ssim_lambda <= 1.0:
            raise HicoError(f"losses.rgb.ssim_lambda must lie in [0, 1], got {self.ssim_lambda}")
        return PhotometricLoss(self)
