"""PSNR after fitting a per-view affine colour transform of the render to the photo.

A test photo's exposure and white balance cannot be known from the training photos; raw PSNR
charges the model for it. ``cc_psnr`` (gsplat's colour-corrected PSNR) first fits, by least squares,
``photo ~ [render, 1] @ W`` (W [4,3]) over the whole view, then scores; ``nerfw_psnr`` is the NeRF-W
protocol: the transform is fitted on the left half and the right half is scored, so the fit cannot
absorb what it scores.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hico_plugin.metrics.image import psnr


def fit_affine_colour(pred: Tensor, target: Tensor) -> Tensor:
    """Least-squares W [4,3] with target ~ [pred, 1] @ W: pred, target [H,W,3] (float64 solve)."""
    x = torch.cat([pred.reshape(-1, 3), torch.ones_like(pred.reshape(-1, 3)[:, :1])], dim=1).double()
    return torch.linalg.lstsq(x, target.reshape(-1, 3).double()).solution


def apply_affine_colour(pred: Tensor, weights: Tensor) -> Tensor:
    """[H,W,3] -> [pred, 1] @ W, clamped to [0, 1]."""
    flat = pred.reshape(-1, 3).double()
    out = flat @ weights[:3] + weights[3]
    return out.reshape(pred.shape).clamp(0.0, 1.0).to(pred.dtype)


def cc_psnr(pred: Tensor, target: Tensor) -> Tensor:
    """PSNR of the colour-corrected render: pred, target [H,W,3] in [0,1] -> []."""
    return psnr(apply_affine_colour(pred, fit_affine_colour(pred, target)), target)


def nerfw_psnr(pred: Tensor, target: Tensor) -> Tensor:
    """PSNR of the right half after a colour fit on the left half: [H,W,3] -> []."""
    half = pred.shape[1] // 2
    weights = fit_affine_colour(pred[:, :half], target[:, :half])
    return psnr(apply_affine_colour(pred[:, half:], weights), target[:, half:])
