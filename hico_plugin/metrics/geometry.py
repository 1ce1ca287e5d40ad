"""Geometry metrics against exact ground truth: depth abs-rel, normal angle, surface P / R / F1, chamfer.

Pixel metrics use only the pixels both sides cover (finite, positive depth / non-zero normal, and the
optional mask). The surface metrics follow the MatrixCity protocol of CityGaussianV2 (no crop, no ICP:
our built-in scenes share the prediction's frame): tau = 1.5 x the mean nearest-neighbour spacing of the
ground-truth points, precision = share of predicted points within tau of the ground truth, recall = share
of ground-truth points within tau of the prediction, F1 = 2PR / (P + R).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.nearest import knn


def _pixel_mask(mask: Tensor | None, shape: torch.Size, name: str) -> Tensor:
    if mask is None:
        return torch.ones(shape, dtype=torch.bool)
    mask = mask.reshape(mask.shape[:2]) if mask.dim() == 3 else mask
    if mask.shape != shape:
        raise HicoError(f"{name}: mask {tuple(mask.shape)} does not match the maps {tuple(shape)}")
    return mask.bool().cpu()


def depth_abs_rel(pred_depth: Tensor, gt_depth: Tensor, mask: Tensor | None = None) -> float:
    """Mean of |pred - gt| / gt over pixels where both depths are finite and > 0 (and ``mask``).

    pred_depth, gt_depth: [H, W] or [H, W, 1]; mask: optional [H, W] bool.
    """
    pred = pred_depth.detach().cpu().double().reshape(pred_depth.shape[:2])
    gt = gt_depth.detach().cpu().double().reshape(gt_depth.shape[:2])
    if pred.shape != gt.shape:
        raise HicoError(f"depth_abs_rel: prediction {tuple(pred.shape)} and ground truth {tuple(gt.shape)} differ in size")
    valid = _pixel_mask(mask, pred.shape, "depth_abs_rel") & torch.isfinite(pred) & torch.isfinite(gt) & (pred > 0) & (gt > 0)
    if not bool(valid.any()):
        raise HicoError("depth_abs_rel: no pixel has a valid (finite, > 0) depth in both prediction and ground truth")
    return float(((pred[valid] - gt[valid]).abs() / gt[valid]).mean())


@dataclass
class NormalError:
    mean_deg: float
    median_deg: float
    pixels: int
    """Number of pixels both normal maps cover."""


def normal_angular_error(pred_normal: Tensor, gt_normal: Tensor, mask: Tensor | None = None) -> NormalError:
    """Angle in degrees between the normal maps, mean and median over pixels where both are non-zero.

    pred_normal, gt_normal: [H, W, 3] (any length; zero = not covered); mask: optional [H, W] bool.
    """
    if pred_normal.shape != gt_normal.shape or pred_normal.dim() != 3 or pred_normal.shape[-1] != 3:
        raise HicoError(f"normal_angular_error: expected two [H, W, 3] maps, got {tuple(pred_normal.shape)} and {tuple(gt_normal.shape)}")
    pred = pred_normal.detach().cpu().double()
    gt = gt_normal.detach().cpu().double()
    valid = _pixel_mask(mask, pred.shape[:2], "normal_angular_error")
    valid &= torch.isfinite(pred).all(-1) & torch.isfinite(gt).all(-1)
    valid &= (pred.norm(dim=-1) > 1e-8) & (gt.norm(dim=-1) > 1e-8)
    if not bool(valid.any()):
        raise HicoError("normal_angular_error: no pixel has a non-zero normal in both prediction and ground truth")
    pred, gt = pred[valid], gt[valid]
    # atan2(|a x b|, a . b) stays accurate near 0 and 180 degrees, where acos of the cosine does not.
    angles = torch.rad2deg(torch.atan2(torch.linalg.cross(pred, gt).norm(dim=-1), (pred * gt).sum(-1)))
    return NormalError(float(angles.mean()), float(angles.median()), int(valid.sum()))


def _points(points: Tensor | np.ndarray, name: str) -> np.ndarray:
    array = points.detach().cpu().numpy() if isinstance(points, Tensor) else np.asarray(points)
    if array.ndim != 2 or array.shape[1] != 3:
        raise HicoError(f"surface metrics: {name} must be [N, 3] points, got shape {tuple(array.shape)}")
    if array.shape[0] == 0:
        raise HicoError(f"surface metrics: {name} is empty (0 points)")
    if not np.isfinite(array).all():
        raise HicoError(f"surface metrics: {name} contains NaN or inf coordinates")
    return array.astype(np.float64)


def gt_spacing_threshold(gt_points: Tensor | np.ndarray, factor: float = 1.5) -> float:
    """tau = factor x mean distance from each ground-truth point to its nearest other point. gt_points: [M, 3]."""
    gt = _points(gt_points, "ground truth")
    if gt.shape[0] < 2:
        raise HicoError("surface metrics: ground truth needs at least 2 points to define its spacing")
    return factor * float(knn(gt, 1)[0].mean())


@dataclass
class SurfaceMetrics:
    precision: float
    recall: float
    f1: float
    accuracy: float
    """Mean distance from predicted points to the ground truth."""
    completeness: float
    """Mean distance from ground-truth points to the prediction."""
    chamfer: float
    """(accuracy + completeness) / 2."""
    threshold: float
    """tau used for precision / recall."""


def surface_metrics(
    pred_points: Tensor | np.ndarray, gt_points: Tensor | np.ndarray, threshold: float | None = None
) -> SurfaceMetrics:
    """Precision / recall / F1 at ``threshold`` and chamfer distance between two point sets.

    pred_points: [N, 3]; gt_points: [M, 3]; threshold: tau in scene units, default
    ``gt_spacing_threshold(gt_points)`` (1.5 x mean GT nearest-neighbour spacing).
    """
    pred = _points(pred_points, "prediction")
    gt = _points(gt_points, "ground truth")
    tau = gt_spacing_threshold(gt) if threshold is None else float(threshold)
    if not (tau > 0 and math.isfinite(tau)):
        raise HicoError(f"surface metrics: threshold must be a positive finite distance, got {tau}")
    pred_to_gt = knn(gt, 1, pred)[0][:, 0]
    gt_to_pred = knn(pred, 1, gt)[0][:, 0]
    precision = float((pred_to_gt < tau).mean())
    recall = float((gt_to_pred < tau).mean())
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    accuracy, completeness = float(pred_to_gt.mean()), float(gt_to_pred.mean())
    return SurfaceMetrics(precision, recall, f1, accuracy, completeness, 0.5 * (accuracy + completeness), tau)
