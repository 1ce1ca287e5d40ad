"""Per-image photometric metrics on [0, 1] images: PSNR and SSIM (3DGS convention)."""

from __future__ import annotations

import pytorch_msssim
import torch
from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.metrics.lpips_net import lpips
from hico_plugin.metrics.ssim_fused import ssim_fused, ssim_fused_available


def _as_batch(pred: Tensor, target: Tensor, name: str) -> tuple[Tensor, Tensor, bool]:
    """Check shapes and lift [H, W, C] to [1, H, W, C]; returns (pred, target, was_batched)."""
    if pred.shape != target.shape:
        raise HicoError(f"{name}: prediction {tuple(pred.shape)} and target {tuple(target.shape)} differ in shape")
    if pred.dim() not in (3, 4) or pred.shape[-3] == 0 or pred.shape[-2] == 0:
        raise HicoError(f"{name}: expected non-empty images [H, W, C] or [B, H, W, C], got {tuple(pred.shape)}")
    if not (pred.is_floating_point() and target.is_floating_point()):
        raise HicoError(f"{name}: expected floating-point images in [0, 1], got {pred.dtype} and {target.dtype}")
    target = target.to(pred.dtype)  # pytorch-msssim refuses mixed dtypes
    batched = pred.dim() == 4
    return (pred, target, True) if batched else (pred[None], target[None], False)


def psnr(pred: Tensor, target: Tensor) -> Tensor:
    """Peak signal-to-noise ratio in dB for images with values in [0, 1].

    pred, target: [H, W, C] or [B, H, W, C]. Returns [] (or [B], one value per image: a dataset's PSNR
    is the mean of per-image values, as 3DGS / CityGS-X report it). Identical images give ``inf``.
    """
    pred_b, target_b, batched = _as_batch(pred, target, "psnr")
    mse = (pred_b.float() - target_b.float()).square().flatten(1).mean(dim=1)
    # mse = 0 -> -10 log10(0) = +inf, which is the honest answer for identical images.
    values = -10.0 * torch.log10(mse)
    return values if batched else values[0]


def ssim(pred: Tensor, target: Tensor) -> Tensor:
    """Structural similarity (pytorch-msssim; 11x11 Gaussian window, sigma 1.5, K = (0.01, 0.03)).

    pred, target: [H, W, C] or [B, H, W, C] in [0, 1]. Returns [] (or [B]); differentiable, so the photometric
    loss uses it too. float32 / float64 CPU images whose target needs no gradient use the fused C++ kernel
    ``ssim_fused`` (same values and gradient w.r.t. pred, to float rounding), the rest pytorch-msssim. Its 'valid'
    borders differ from the 3DGS reference's zero padding only in a window-wide band at the border.
    """
    pred_b, target_b, batched = _as_batch(pred, target, "ssim")
    fused = (pred_b.device.type == "cpu" and pred_b.dtype in (torch.float32, torch.float64)
             and not target_b.requires_grad and ssim_fused_available())
    if fused:
        values = ssim_fused(pred_b, target_b)
    else:
        values = pytorch_msssim.ssim(
            pred_b.permute(0, 3, 1, 2), target_b.permute(0, 3, 1, 2), data_range=1.0, size_average=False,
            win_size=11, win_sigma=1.5,
        )
    return values if batched else values[0]


def image_metrics(pred: Tensor, target: Tensor, lpips_nets: tuple[str, ...] = ("vgg",)) -> dict[str, float | None]:
    """PSNR, SSIM and LPIPS of one image pair as floats: {"psnr", "ssim", "lpips_<net>"}.

    pred, target: [H, W, 3] in [0, 1]. LPIPS defaults to VGG (the CityGS-X / Octree-GS protocol); an
    LPIPS whose weights cannot be loaded is None, never 0. Dataset scores are means of these values.
    """
    scores: dict[str, float | None] = {"psnr": float(psnr(pred, target)), "ssim": float(ssim(pred, target))}
    for net in lpips_nets:
        distance = lpips(pred, target, net)
        scores[f"lpips_{net}"] = None if distance is None else float(distance)
    return scores
