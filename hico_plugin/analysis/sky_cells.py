"""Open sky: image cells (``SKY_CELLS_PER_SIDE`` to the shorter side) with no sparse point projected into
them, above the horizon of the scene's up vector, smooth and bright: open sky or an unbounded background
the Gaussians cannot represent. A point occluded in a view still projects onto a surface pixel, never
onto sky, so this test needs no visibility.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding, project_points, sampled_views
from hico_plugin.data.transform import scene_up

# sky: image cells of 1/SKY_CELLS_PER_SIDE of the shorter image side (>= 4 px), so a thin band of sky
# still fills whole cells at low resolution; a cell is sky-like when no sparse point falls in it,
SKY_CELLS_PER_SIDE = 30
# it is connected through such cells to the image edge facing the scene's up vector (edge
# cells whose centre ray lies above the view's median elevation) — not "elevation > 0": a finite
# ground lets sky show below the true horizon (city-block's top rows look 8 degrees down at sky),
# its mean absolute colour gradient, after a sigma-1.5 px blur that removes sensor noise, is below
# this (sky is smooth; textured surfaces are not),
SKY_MAX_GRADIENT = 0.03
# and its mean luminance is above this: a black fill is the model's constant background already.
SKY_MIN_LUMINANCE = 0.2
# a capture has sky when more than this share of all cells is sky-like (city-block: ~25 %).
SKY_MIN_FRACTION = 0.02


def up_vector(dataset: Any) -> np.ndarray:
    """The scene's up direction [3] (data.transform.scene_up) in the dataset's (normalised, so z-up when oriented) frame."""
    return scene_up(dataset.cameras.viewmats).numpy()


def sky_cells(dataset: Any, view: int, points: np.ndarray, up: np.ndarray) -> np.ndarray:
    """bool [H/cell, W/cell]: the sky-like cells of ``view`` (see the module docstring)."""
    image = dataset.image(view).numpy().astype(np.float32) / 255.0
    height, width = image.shape[:2]
    size = max(4, min(height, width) // SKY_CELLS_PER_SIDE)
    rows, cols = height // size, width // size
    if rows == 0 or cols == 0:
        return np.zeros((0, 0), bool)
    image = image[: rows * size, : cols * size]
    pixels, _, inside = project_points(dataset, view, points)
    occupied = np.zeros((rows, cols), bool)
    occupied[np.clip((pixels[inside, 1] // size).astype(np.int64), 0, rows - 1),
             np.clip((pixels[inside, 0] // size).astype(np.int64), 0, cols - 1)] = True
    blurred = cv2.GaussianBlur(image, (0, 0), 1.5)
    gradient = np.zeros(image.shape[:2], np.float32)
    gradient[:, :-1] += np.abs(np.diff(blurred, axis=1)).mean(axis=2)
    gradient[:-1, :] += np.abs(np.diff(blurred, axis=0)).mean(axis=2)
    cell = lambda a: a.reshape(rows, size, cols, size).mean(axis=(1, 3))  # noqa: E731
    smooth = cell(gradient) < SKY_MAX_GRADIENT
    bright = cell(image.mean(axis=2)) > SKY_MIN_LUMINANCE
    # centre ray of each cell, world frame
    K = dataset.cameras.Ks[view].double().numpy()
    R = dataset.cameras.viewmats[view, :3, :3].double().numpy()
    u = (np.arange(cols) + 0.5) * size
    v = (np.arange(rows) + 0.5) * size
    uu, vv = np.meshgrid(u, v)
    dirs = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], axis=-1) @ R
    elevation = (dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)) @ up
    candidate = ~occupied & smooth & bright
    edge = np.zeros_like(candidate)
    edge[[0, -1], :] = True
    edge[:, [0, -1]] = True
    upper_edge = edge & (elevation > np.median(elevation)) & candidate
    _, labels = cv2.connectedComponents(candidate.astype(np.uint8), connectivity=4)
    keep = np.unique(labels[upper_edge])
    return candidate & np.isin(labels, keep[keep > 0])


def sky_finding(evidence: DatasetEvidence) -> EffectFinding:
    dataset = evidence.dataset
    points = dataset.points.double().numpy()
    up = up_vector(dataset)
    views = sampled_views(dataset)
    sky, total, views_with_sky = 0, 0, 0
    for view in views:
        cells = sky_cells(dataset, int(view), points, up)
        sky += int(cells.sum())
        total += cells.size
        views_with_sky += int(cells.mean() > SKY_MIN_FRACTION) if cells.size else 0
    fraction = sky / max(total, 1)
    present = fraction > SKY_MIN_FRACTION
    figures = {"sky_fraction": round(fraction, 4), "views_analysed": len(views), "views_with_sky": views_with_sky,
               "threshold_fraction": SKY_MIN_FRACTION, "up": [round(float(x), 4) for x in up]}
    if present:
        reason = (f"{100 * fraction:.1f} % of image cells are point-free, smooth, bright and reach the "
                  f"upward image edge ({views_with_sky}/{len(views)} views; threshold {100 * SKY_MIN_FRACTION:.0f} %)")
    else:
        reason = (f"no open sky found ({100 * fraction:.1f} % of image cells sky-like; threshold "
                  f"{100 * SKY_MIN_FRACTION:.0f} %)")
    return EffectFinding(bool(present), reason, figures)

