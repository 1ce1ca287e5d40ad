"""Fused CPU SSIM: csrc/ssim_cpu.cpp, a plain C++ library built on first use (``hico_plugin.native``).

``ssim_fused`` has ``metrics.image.ssim``'s contract and pytorch-msssim's values (11-tap Gaussian window, sigma
1.5, K = (0.01, 0.03), 'valid' borders), forward and gradient w.r.t. the prediction in one pass each, bitwise
independent of the thread count. Along a dimension shorter than the window it skips the smoothing with
pytorch-msssim's warning, down to one pixel (which pytorch-msssim refuses).
"""

from __future__ import annotations

import warnings
from ctypes import c_double, c_int, c_int64, c_void_p
from functools import cache
from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from hico_plugin.native import DTYPE_SUFFIXES, NativeKernel, pointer

_SHAPE_AND_WINDOWS = [c_int64] * 4 + [c_void_p, c_int64] * 2  # B, H, W, C; each window and its size
KERNEL = NativeKernel(
    "hico_ssim_cpu", Path(__file__).parent / "csrc" / "ssim_cpu.cpp", "fused CPU SSIM kernel", "pytorch-msssim",
    functions={"hico_ssim_forward_{dtype}": ([c_void_p, c_void_p, *_SHAPE_AND_WINDOWS, c_double, c_double,
                                              *[c_void_p] * 4, c_int], None),
               "hico_ssim_backward_{dtype}": ([*[c_void_p] * 6, *_SHAPE_AND_WINDOWS, c_void_p, c_int], None)})
WIN_SIZE, WIN_SIGMA = 11, 1.5
C1, C2 = 0.01**2, 0.03**2  # (K1 * data_range)^2, (K2 * data_range)^2 with data_range 1, as pytorch-msssim


def ssim_fused_available() -> bool:
    """Whether the fused CPU SSIM kernel is built (building it on the first call)."""
    return KERNEL.available()


@cache
def gaussian_window() -> Tensor:
    """pytorch-msssim's 1-D window, made as it makes it (float32, centred on tap size // 2, summing to 1),
    so that float64 results agree with it to rounding: [WIN_SIZE]. Made once: every training step asks
    for it, and the kernel only reads it."""
    offsets = torch.arange(WIN_SIZE, dtype=torch.float32) - WIN_SIZE // 2
    weights = torch.exp(-offsets**2 / (2 * WIN_SIGMA**2))
    return weights / weights.sum()


def _windows(height: int, width: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """The vertical and horizontal windows: pytorch-msssim's Gaussian (made in float32 and cast, as it
    does), or [1] along a dimension shorter than it, which pytorch-msssim leaves unsmoothed."""
    gauss = gaussian_window().to(dtype)
    windows = []
    for dim, size in ((2, height), (3, width)):
        if size < WIN_SIZE:
            warnings.warn(f"Skipping Gaussian Smoothing at dimension 2+{dim - 2} for an image of {height}x{width} "
                          f"and win size: {WIN_SIZE}")
        windows.append(gauss if size >= WIN_SIZE else torch.ones(1, dtype=dtype))
    return windows[0], windows[1]


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred: Tensor, target: Tensor) -> Tensor:
        batch, height, width, channels = pred.shape
        win_v, win_h = _windows(height, width, pred.dtype)
        partials = [pred.new_empty(batch, channels, height - win_v.numel() + 1, width - win_h.numel() + 1)
                    for _ in range(3 if ctx.needs_input_grad[0] else 0)]
        values = pred.new_empty(batch)
        KERNEL.function("hico_ssim_forward_{dtype}", pred.dtype)(
            pointer(pred), pointer(target), batch, height, width, channels, pointer(win_v), win_v.numel(),
            pointer(win_h), win_h.numel(), C1, C2, pointer(values),
            *([pointer(p) for p in partials] or [None] * 3), torch.get_num_threads())
        ctx.save_for_backward(pred, target, *partials)
        ctx.windows = win_v, win_h
        return values

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_values: Tensor) -> tuple[Tensor, None]:
        pred, target, d_mu, d_xx, d_xy = ctx.saved_tensors
        win_v, win_h = ctx.windows
        grad_values, grad_pred = grad_values.contiguous(), torch.empty_like(pred)  # held through the call
        KERNEL.function("hico_ssim_backward_{dtype}", pred.dtype)(
            pointer(pred), pointer(target), pointer(d_mu), pointer(d_xx), pointer(d_xy),
            pointer(grad_values), *pred.shape, pointer(win_v), win_v.numel(), pointer(win_h),
            win_h.numel(), pointer(grad_pred), torch.get_num_threads())
        return grad_pred, None


def ssim_fused(pred: Tensor, target: Tensor) -> Tensor:
    """SSIM of images in [0, 1], as ``metrics.image.ssim``: pred, target [H, W, C] or [B, H, W, C], float32
    or float64 CPU tensors of one shape -> [] (or [B]). Differentiable w.r.t. ``pred`` only: a ``target``
    that needs a gradient is refused (use pytorch-msssim). Call ``ssim_fused_available()`` first."""
    if (pred.shape != target.shape or pred.dim() not in (3, 4) or pred.numel() == 0
            or pred.dtype not in DTYPE_SUFFIXES or pred.device.type != "cpu"):
        raise ValueError(f"ssim_fused takes non-empty float32/float64 CPU images [H, W, C] or [B, H, W, C] of one "
                         f"shape, got {tuple(pred.shape)} {pred.dtype} and {tuple(target.shape)} {target.dtype} "
                         f"on {pred.device}")
    if target.requires_grad and torch.is_grad_enabled():
        raise ValueError("ssim_fused differentiates w.r.t. pred only; use pytorch-msssim when target needs a gradient")
    batched = pred.dim() == 4
    pred_b, target_b = (pred, target) if batched else (pred[None], target[None])
    values = _FusedSSIM.apply(pred_b.contiguous(), target_b.to(pred.dtype).contiguous())
    return values if batched else values[0]
