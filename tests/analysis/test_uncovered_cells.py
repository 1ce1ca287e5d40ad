"""The share of the photos no reconstructed point explains: where it lies, and open sky or near surfaces."""

from __future__ import annotations

import numpy as np
import pytest

from hico_plugin.analysis.evidence import DatasetEvidence, project_points
from hico_plugin.analysis.uncovered_cells import environment_finding, nearest_occupied, up_vector, view_cells
from hico_plugin.data import DataParserConfig
from hico_plugin.model.effects import EffectChoice
from hico_plugin.scenes.generate import generate_scene

TWIN = dict(num_views=24, width=128, height=96, pixel_samples=1)


def _finding(name, **overrides):
    dataset = DataParserConfig(data=generate_scene(name, **{**TWIN, **overrides})).setup(announce=False)
    return dataset, environment_finding(DatasetEvidence(dataset))


def test_the_room_has_uncovered_walls_and_ceiling_not_sky():
    """Indoors the paper between the flowers and the ceiling have no points: the background is needed
    (on), and the finding says near surfaces — never sky."""
    dataset, finding = _finding("room")
    assert finding.present and finding.figures["kind"] == "near surfaces", finding.reason
    assert finding.figures["unexplained_fraction"] > 0.1
    parallax = finding.figures["parallax"]
    assert parallax["better_at_point_depth"] > 2 * parallax["better_at_infinity"]
    line = EffectChoice("environment", finding.present, finding.reason).line()
    assert line.startswith("environment: on — ") and "near uncovered surfaces" in line
    assert "sky" not in line.lower()


def test_outdoor_twins_have_open_sky():
    for name in ("pagoda", "city-block"):
        _, finding = _finding(name)
        assert finding.present and finding.figures["kind"] == "open sky", (name, finding.reason)
        assert "open sky" in finding.reason


def test_uncovered_cells_have_no_point_and_reach_the_upward_edge():
    dataset = DataParserConfig(data=generate_scene("pagoda", **TWIN)).setup(announce=False)
    points = dataset.points.double().numpy()
    cells = view_cells(dataset, 0, points, up_vector(dataset))
    rows, cols = cells.uncovered.shape
    assert cells.size == 4 and (rows, cols) == (96 // 4, 128 // 4) and cells.uncovered.any()
    pixels, _, inside = project_points(dataset, 0, points)
    hit = np.zeros_like(cells.uncovered)
    hit[(pixels[inside, 1] // 4).astype(int), (pixels[inside, 0] // 4).astype(int)] = True
    assert not (hit & cells.uncovered).any()
    assert cells.uncovered[0].any()  # the drone looks down at the tower: sky at the top of the frame
    assert np.isfinite(cells.nearest_depth).all() and cells.colours.shape == (rows, cols, 3)


def test_nearest_occupied_cell_matches_scipy_distance_transform():
    """The exact Euclidean nearest occupied cell: scipy's distance, and scipy's cell wherever no other
    occupied cell is as near (equidistant ones may resolve differently)."""
    ndimage = pytest.importorskip("scipy.ndimage")
    rng = np.random.default_rng(0)
    grid = np.argwhere(np.ones((24, 32), bool))
    for share in (0.002, 0.02, 0.1, 0.5):
        occupied = rng.random((24, 32)) < share
        occupied[rng.integers(24), rng.integers(32)] = True
        taken = nearest_occupied(np.arange(occupied.size).reshape(occupied.shape), occupied).reshape(-1)
        distance, (rows, cols) = ndimage.distance_transform_edt(~occupied, return_indices=True)
        assert occupied.reshape(-1)[taken].all()
        np.testing.assert_allclose(np.linalg.norm(grid[taken] - grid, axis=1), distance.reshape(-1), atol=1e-12)
        squared = ((grid[:, None] - np.argwhere(occupied)[None]) ** 2).sum(-1)
        alone = (squared == squared.min(1, keepdims=True)).sum(1) == 1
        np.testing.assert_array_equal(taken[alone], (rows * 32 + cols).reshape(-1)[alone])
