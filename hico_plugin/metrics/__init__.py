"""Image and geometry metrics: PSNR, SSIM, LPIPS, depth / normal error, surface F1."""

from hico_plugin.metrics.geometry import (
    NormalError,
    SurfaceMetrics,
    depth_abs_rel,
    gt_spacing_threshold,
    normal_angular_error,
    surface_metrics,
)
from hico_plugin.metrics.image import image_metrics, psnr, ssim
from hico_plugin.metrics.lpips_net import LPIPS, load_lpips, lpips

__all__ = [
    "LPIPS", "NormalError", "SurfaceMetrics", "depth_abs_rel", "gt_spacing_threshold", "image_metrics",
    "load_lpips", "lpips", "normal_angular_error", "psnr", "ssim", "surface_metrics",
]
