"""The share of each photo that no reconstructed point explains, where it lies, and what it is.

Anchors seed at the sparse points and densify next to existing Gaussians, so photo regions far from every point
show whatever the model composites behind them. A cell (``CELLS_PER_SIDE`` to the shorter side) is *uncovered*
when no sparse point projects into it, it is smooth and bright, and it connects through such cells to the image
edge facing the scene's up vector (no visibility needed: an occluded point still lands on a surface pixel).
Whether it is open sky or a featureless near surface is ``analysis.parallax``'s question.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding, project_points, sampled_views
from hico_plugin.analysis.parallax import measure_parallax
from hico_plugin.analysis.photo_gains import photo_gains
from hico_plugin.data.transform import scene_up
from hico_plugin.nearest import knn

# image cells of 1/CELLS_PER_SIDE of the shorter image side (>= 4 px), so a thin band of sky still
# fills whole cells at low resolution; an uncovered cell has no sparse point in it,
CELLS_PER_SIDE = 30
# it is connected through such cells to the image edge facing the scene's up vector (edge cells whose
# centre ray lies above the view's median elevation) — not "elevation > 0": a finite ground lets sky
# show below the true horizon (city-block's top rows look 8 degrees down at sky),
# its mean absolute colour gradient, after a sigma-1.5 px blur that removes sensor noise, is below
# this (sky and plain walls are smooth; textured surfaces are not),
MAX_GRADIENT = 0.03
# and its mean luminance is above this: a dark void is what the learned constant background models.
MIN_LUMINANCE = 0.2
# the capture needs a background model when more than this share of all cells is uncovered.
MIN_FRACTION = 0.02


@dataclass
class ViewCells:
    """One view's cells: which are uncovered [R, C] bool, their mean colours [R, C, 3] (0..1), the mean
    depth of the sparse points in the nearest cell that has any [R, C] (NaN when the view has none),
    and the cell size in pixels."""

    uncovered: np.ndarray
    colours: np.ndarray
    nearest_depth: np.ndarray
    size: int


def up_vector(dataset: Any) -> np.ndarray:
    """The scene's up direction [3] (data.transform.scene_up) in the dataset's (normalised, so z-up when oriented) frame."""
    return scene_up(dataset.cameras.viewmats).numpy()


def nearest_occupied(values: np.ndarray, occupied: np.ndarray) -> np.ndarray:
    """Each cell's value taken from the nearest occupied cell (Euclidean, in cells; of equidistant ones,
    the one the k-d tree finds first): values [R, C], occupied [R, C] bool, not all False -> [R, C]."""
    # An exact search: OpenCV's distanceTransformWithLabels propagates a 3x3 / 5x5 mask's approximate
    # distance and takes a farther cell for some cells.
    _, nearest = knn(np.argwhere(occupied), 1, np.argwhere(np.ones_like(occupied)))  # [R*C, 1]
    return values[occupied][nearest[:, 0]].reshape(values.shape)


def view_cells(dataset: Any, view: int, points: np.ndarray, up: np.ndarray) -> ViewCells:
    """The cells of ``view`` (see the module docstring) and what ``analysis.parallax`` reads of them."""
    image = dataset.image(view).numpy().astype(np.float32) / 255.0
    height, width = image.shape[:2]
    size = max(4, min(height, width) // CELLS_PER_SIDE)
    rows, cols = height // size, width // size
    if rows == 0 or cols == 0:
        return ViewCells(np.zeros((0, 0), bool), np.zeros((0, 0, 3)), np.zeros((0, 0)), size)
    image = image[: rows * size, : cols * size]
    pixels, depth, inside = project_points(dataset, view, points)
    cell_rows = np.clip((pixels[inside, 1] // size).astype(np.int64), 0, rows - 1)
    cell_cols = np.clip((pixels[inside, 0] // size).astype(np.int64), 0, cols - 1)
    count = np.zeros((rows, cols))
    depth_sum = np.zeros((rows, cols))
    np.add.at(count, (cell_rows, cell_cols), 1.0)
    np.add.at(depth_sum, (cell_rows, cell_cols), depth[inside])
    occupied = count > 0
    nearest_depth = np.full((rows, cols), np.nan)
    if occupied.any():
        nearest_depth = nearest_occupied(depth_sum / np.maximum(count, 1.0), occupied)
    blurred = cv2.GaussianBlur(image, (0, 0), 1.5)
    gradient = np.zeros(image.shape[:2], np.float32)
    gradient[:, :-1] += np.abs(np.diff(blurred, axis=1)).mean(axis=2)
    gradient[:-1, :] += np.abs(np.diff(blurred, axis=0)).mean(axis=2)
    cell = lambda a: a.reshape(rows, size, cols, size, *a.shape[2:]).mean(axis=(1, 3))  # noqa: E731
    colours = cell(image)
    candidate = ~occupied & (cell(gradient) < MAX_GRADIENT) & (colours.mean(axis=2) > MIN_LUMINANCE)
    # centre ray of each cell, world frame
    K = dataset.cameras.Ks[view].double().numpy()
    R = dataset.cameras.viewmats[view, :3, :3].double().numpy()
    uu, vv = np.meshgrid((np.arange(cols) + 0.5) * size, (np.arange(rows) + 0.5) * size)
    dirs = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], axis=-1) @ R
    elevation = (dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)) @ up
    edge = np.zeros_like(candidate)
    edge[[0, -1], :] = True
    edge[:, [0, -1]] = True
    upper_edge = edge & (elevation > np.median(elevation)) & candidate
    _, labels = cv2.connectedComponents(candidate.astype(np.uint8), connectivity=4)
    keep = np.unique(labels[upper_edge])
    return ViewCells(candidate & np.isin(labels, keep[keep > 0]), colours, nearest_depth, size)


def environment_finding(evidence: DatasetEvidence) -> EffectFinding:
    """Whether the photos have a share of uncovered cells a background model must fill, and whether it
    is open sky or near uncovered surfaces (``analysis.parallax``)."""
    dataset = evidence.dataset
    points = dataset.points.double().numpy()
    up = up_vector(dataset)
    views = [int(view) for view in sampled_views(dataset)]
    cells = {view: view_cells(dataset, view, points, up) for view in views}
    uncovered = sum(int(c.uncovered.sum()) for c in cells.values())
    total = sum(c.uncovered.size for c in cells.values())
    views_with = sum(int(c.uncovered.size > 0 and c.uncovered.mean() > MIN_FRACTION) for c in cells.values())
    fraction = uncovered / max(total, 1)
    present = fraction > MIN_FRACTION
    share = (f"{100 * fraction:.1f} % of image cells are not explained by any reconstructed point (point-free, "
             f"smooth, bright, reaching the upward image edge; {views_with}/{len(views)} views; threshold "
             f"{100 * MIN_FRACTION:.0f} %)")
    figures: dict[str, Any] = {"unexplained_fraction": round(fraction, 4), "views_analysed": len(views),
                               "views_with_unexplained": views_with, "threshold_fraction": MIN_FRACTION,
                               "up": [round(float(x), 4) for x in up]}
    if uncovered:  # what a constant behind the Gaussians should start at (HiCoModelConfig.background_start)
        colours = np.concatenate([c.colours[c.uncovered] for c in cells.values()])
        figures["unexplained_colour"] = [round(float(x), 4) for x in np.median(colours, axis=0)]
    if not present:
        return EffectFinding(False, share, figures)
    parallax = measure_parallax(dataset, cells, photo_gains(evidence)[0])
    figures.update(kind=parallax.kind, parallax=parallax.figures())
    return EffectFinding(True, f"{share}: {parallax.description()}", figures)

