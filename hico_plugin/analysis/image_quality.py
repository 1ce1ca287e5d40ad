"""Sensor noise and lens distortion: measured and reported, simulated by no model component (the L1 loss
averages zero-mean noise; distorted cameras are undistorted to pinhole at load).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding, sampled_views
from hico_plugin.data.undistort import PINHOLE_MODELS


# noise: Immerkær's estimate over the smoothest 10 % of cells, median over photos, in 8-bit levels.
# Clean renders measure < 1 level (quantisation); the built-in sensor noise is ~3-4 levels.
NOISE_MIN_LEVELS = 1.5
NOISE_UNCLIPPED = (2, 253)  # 8-bit levels a noise cell must stay strictly between
NOISE_MIN_FLAT_SHARE = 0.05  # fewer flat unclipped cells than this share: noise not measurable
NOISE_FLAT_GRADIENT = 2.0  # 8-bit levels per pixel of the blurred image: flat cells only

# distortion: a camera counts as distorted when undistortion moves its corner pixel by > this.
DISTORTION_MIN_PX = 0.5


_LAPLACE = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float64)


def noise_levels(image: np.ndarray, cell: int = 8) -> float | None:
    """Sensor noise std of ``image`` [H,W,3] uint8 in 8-bit levels (Immerkær 1996: the mean |L * I|
    times sqrt(pi/2)/6 is the std of white noise), over the smoothest 10 % of flat, unclipped cells;
    None when too few such cells exist (textured everywhere, or a clipped black background)."""
    gray = image.astype(np.float64).mean(axis=2)
    h, w = gray.shape
    response = np.zeros((h - 2, w - 2))
    for dy in range(3):
        for dx in range(3):
            response += _LAPLACE[dy, dx] * gray[dy : dy + h - 2, dx : dx + w - 2]
    rows, cols = (h - 2) // cell, (w - 2) // cell
    if rows == 0 or cols == 0:
        return 0.0
    blocks = np.abs(response[: rows * cell, : cols * cell]).reshape(rows, cell, cols, cell).mean(axis=(1, 3))
    # clipped cells (black background, blown highlights) lose their noise: leave them out
    level = gray[1 : 1 + rows * cell, 1 : 1 + cols * cell].reshape(rows, cell, cols, cell)
    unclipped = ((level.min(axis=(1, 3)) > NOISE_UNCLIPPED[0]) & (level.max(axis=(1, 3)) < NOISE_UNCLIPPED[1])).ravel()
    # and textured cells inflate it: keep cells that are flat once blurred past the noise
    blurred = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.5)
    grad = np.abs(np.diff(blurred, axis=1))[1 : 1 + rows * cell, 1 : 1 + cols * cell]
    flat = (grad.reshape(rows, cell, cols, cell).mean(axis=(1, 3)) < NOISE_FLAT_GRADIENT).ravel()
    blocks = blocks.ravel()[unclipped & flat]
    if blocks.size < NOISE_MIN_FLAT_SHARE * rows * cols:
        return None
    smooth = np.sort(blocks)[: max(1, blocks.size // 10)]
    # a gray pixel averages three channels with independent noise: scale back to one channel
    return float(smooth.mean() * math.sqrt(math.pi / 2) / 6.0 * math.sqrt(3.0))


def noise_finding(evidence: DatasetEvidence) -> EffectFinding:
    dataset = evidence.dataset
    views = sampled_views(dataset)
    measured = [x for v in views if (x := noise_levels(dataset.image(int(v)).numpy())) is not None]
    if not measured:
        return EffectFinding(False, "not measurable: no flat, unclipped image region (reported only, no model "
                             "component)", {"noise_std_levels": None, "threshold_levels": NOISE_MIN_LEVELS})
    levels = float(np.median(measured))
    present = levels > NOISE_MIN_LEVELS
    reason = (f"noise std {levels:.2f} of 255 levels (threshold {NOISE_MIN_LEVELS}); "
              + ("the L1 loss averages it, no model component" if present else "clean images"))
    return EffectFinding(bool(present), reason, {"noise_std_levels": round(levels, 3), "threshold_levels": NOISE_MIN_LEVELS})




def distortion_finding(evidence: DatasetEvidence) -> EffectFinding:
    dataset = evidence.dataset
    worst, models = 0.0, set()
    for source in dataset.sources.values():
        models.add(source.model)
        if source.model in PINHOLE_MODELS:
            continue
        camera = source.distorted
        corner = np.array([[0.0, 0.0], [camera.width - 1.0, camera.height - 1.0]])
        rays = camera.cam_from_img(corner)  # undistorted normalised coordinates
        ideal = np.stack([camera.focal_length_x * rays[:, 0] + camera.principal_point_x,
                          camera.focal_length_y * rays[:, 1] + camera.principal_point_y], axis=1)
        worst = max(worst, float(np.abs(ideal - corner).max()))
    present = worst > DISTORTION_MIN_PX
    reason = (f"camera model {', '.join(sorted(models))}; corner displacement {worst:.1f} px (threshold "
              f"{DISTORTION_MIN_PX} px)" + ("; undistorted to PINHOLE at load" if present else ""))
    return EffectFinding(bool(present), reason, {"models": sorted(models), "corner_displacement_px": round(worst, 3)})

