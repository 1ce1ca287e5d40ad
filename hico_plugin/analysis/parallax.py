"""Open sky or near surfaces: does a region that no reconstructed point explains move with parallax?

Each uncovered cell (``analysis.uncovered_cells``) is mapped into the ``PARTNERS`` nearest views by the rotation
alone (the homography at infinity, Hartley & Zisserman, Multiple View Geometry, 2nd ed., Sec. 13.4) and through
the nearby points' depth; each pair votes for the mapping whose colour, exposure gains divided out, is closer by
``MARGIN``. Near surfaces when depth wins ``NEAR_SHARE`` of the pairs and ``NEAR_ODDS`` times infinity's votes,
else open sky, as a flat colour is (thresholds: benchmarks/RESULTS.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from hico_plugin.analysis.uncovered_cells import ViewCells

PARTNERS = 4  # nearest views (by camera centre) each view's cells are mapped into,
MIN_AXIS_COS = 0.5  # among those whose optical axis is within 60 degrees of the view's
MIN_CELLS = 30  # cell pairs needed to say anything
MARGIN = 0.01  # a hypothesis matches better when its colour error is lower by this (2.5 of 255 levels)
# near surfaces: the points' depth matches better in at least this share of the cell pairs
NEAR_SHARE = 0.25
NEAR_ODDS = 2.0  # and this many times as often as infinity does


@dataclass
class Parallax:
    """What the mapping into neighbouring views found: ``cells`` pairs told apart (both mappings on
    uncovered cells, a cell or more apart), of which ``near_better`` / ``far_better`` match the colour
    better at the nearest points' depth / at infinity, and ``still`` pairs whose two mappings fall
    within a cell (the nearest points are too far to move)."""

    cells: int
    near_better: int
    far_better: int
    still: int

    @property
    def kind(self) -> str | None:
        """"open sky", "near surfaces", or None when too few cells were seen twice to tell."""
        if self.cells + self.still < MIN_CELLS:
            return None
        if self.near_better >= max(NEAR_SHARE * self.cells, NEAR_ODDS * self.far_better, 1):
            return "near surfaces"
        return "open sky"

    def description(self) -> str:
        counts = (f"in {self.near_better} of {self.cells} cell pairs in neighbouring views their colour matches better "
                  f"at the points' depth than at infinity, in {self.far_better} the reverse")
        if self.kind is None:
            return (f"too few of them are seen in two neighbouring views to measure whether they are distant "
                    f"({self.cells + self.still} cell pairs, {MIN_CELLS} needed)")
        if self.kind == "near surfaces":
            return ("near uncovered surfaces (walls or ceilings without features): these cells move with the parallax of "
                    f"the nearest reconstructed points ({counts})")
        if self.still >= self.cells:
            return (f"open sky: the reconstructed points around these cells are too far to move between views "
                    f"({self.still} of {self.cells + self.still} cell pairs within a cell), so they show a distant background")
        return f"open sky: these cells do not move with the parallax of the nearest reconstructed points ({counts})"

    def figures(self) -> dict[str, Any]:
        return {"cell_pairs": self.cells, "better_at_point_depth": self.near_better,
                "better_at_infinity": self.far_better, "cell_pairs_within_a_cell": self.still,
                "thresholds": {"colour_margin": MARGIN, "near_share": NEAR_SHARE, "near_odds": NEAR_ODDS}}


def measure_parallax(dataset: Any, cells: dict[int, "ViewCells"], log2_gains: np.ndarray) -> Parallax:
    """Map the uncovered cells of every view in ``cells`` into its neighbours (module docstring);
    ``log2_gains`` [V, 3] are the photos' measured exposure gains (NaN = unknown, taken as 0)."""
    gains = 2.0 ** np.nan_to_num(log2_gains)
    viewmats = dataset.cameras.viewmats.double().numpy()
    Ks = dataset.cameras.Ks.double().numpy()
    views = [view for view, c in cells.items() if c.uncovered.size]
    centres = {view: -viewmats[view, :3, :3].T @ viewmats[view, :3, 3] for view in views}
    errors_far, errors_near, still = [np.zeros(0)], [np.zeros(0)], 0
    for i in views:
        source = cells[i]
        rows, cols = np.nonzero(source.uncovered & np.isfinite(source.nearest_depth))
        K, R = Ks[i], viewmats[i, :3, :3]
        rays = np.stack([((cols + 0.5) * source.size - K[0, 2]) / K[0, 0],
                         ((rows + 0.5) * source.size - K[1, 2]) / K[1, 1], np.ones(len(rows))], axis=1)
        colour = source.colours[rows, cols] / gains[i]
        directions = rays @ R  # world directions (R^T d, row-vector form)
        near_points = centres[i] + (rays * source.nearest_depth[rows, cols, None]) @ R
        for j in _partners(i, views, centres, viewmats):
            target = cells[j]
            far = _cell_coords(directions, viewmats[j, :3, :3], np.zeros(3), Ks[j], target.size)
            near = _cell_coords(near_points, viewmats[j, :3, :3], viewmats[j, :3, 3], Ks[j], target.size)
            both = _on_uncovered(target, far) & _on_uncovered(target, near)
            apart = np.linalg.norm(np.nan_to_num(far - near), axis=1) >= 1.0
            still += int((both & ~apart).sum())
            keep = both & apart
            for coords, errors in ((far, errors_far), (near, errors_near)):
                errors.append(np.abs(_sample(target.colours, coords[keep]) / gains[j] - colour[keep]).mean(axis=1))
    gap = np.concatenate(errors_far) - np.concatenate(errors_near)
    return Parallax(len(gap), int((gap > MARGIN).sum()), int((gap < -MARGIN).sum()), still)


def _partners(view: int, views: list[int], centres: dict[int, np.ndarray], viewmats: np.ndarray) -> list[int]:
    """The PARTNERS views nearest to ``view`` whose optical axes are within 60 degrees of its own."""
    axis = viewmats[view, 2, :3]
    facing = [other for other in views if other != view and viewmats[other, 2, :3] @ axis > MIN_AXIS_COS]
    return sorted(facing, key=lambda other: float(np.linalg.norm(centres[other] - centres[view])))[:PARTNERS]


def _cell_coords(points: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, size: int) -> np.ndarray:
    """World points (or, with t = 0, directions) [N, 3] -> (x, y) [N, 2] in cell units of a view
    (NaN behind the camera)."""
    cam = points @ R.T + t
    z = np.where(cam[:, 2] > 1e-9, cam[:, 2], np.nan)
    return np.stack([K[0, 0] * cam[:, 0] / z + K[0, 2], K[1, 1] * cam[:, 1] / z + K[1, 2]], axis=1) / size


def _on_uncovered(cells: "ViewCells", coords: np.ndarray) -> np.ndarray:
    rows, cols = cells.uncovered.shape
    finite = np.isfinite(coords).all(axis=1)
    x, y = np.where(finite, coords[:, 0], -1.0), np.where(finite, coords[:, 1], -1.0)
    inside = (x >= 0) & (x < cols) & (y >= 0) & (y < rows)
    return inside & cells.uncovered[np.clip(y.astype(np.int64), 0, rows - 1), np.clip(x.astype(np.int64), 0, cols - 1)]


def _sample(colours: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Bilinear colours [N, 3] (the grid's dtype) of the cell-colour grid [R, C, 3] at (x, y) [N, 2] in
    cell units: cell centres at +0.5, the edge cells' colours continuing beyond the outer centres."""
    rows, cols = colours.shape[:2]
    x = np.clip(coords[:, 0] - 0.5, 0, cols - 1)
    y = np.clip(coords[:, 1] - 0.5, 0, rows - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, cols - 1), np.minimum(y0 + 1, rows - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = (1 - fx) * colours[y0, x0] + fx * colours[y0, x1]
    bottom = (1 - fx) * colours[y1, x0] + fx * colours[y1, x1]
    return ((1 - fy) * top + fy * bottom).astype(colours.dtype)
