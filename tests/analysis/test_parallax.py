"""Open sky or near surfaces, from cells whose colours follow the view direction or a nearby plane."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from hico_plugin.analysis.parallax import MIN_CELLS, Parallax, _sample, measure_parallax
from hico_plugin.analysis.uncovered_cells import ViewCells
from hico_plugin.scenes.orbits import look_at

SIZE, ROWS, COLS = 4, 12, 16  # cells of 4 px: 64 x 48 px views
K = np.array([[40.0, 0.0, 32.0], [0.0, 40.0, 24.0], [0.0, 0.0, 1.0]])
PLANE_X = 3.0  # the near wall every camera faces


def _cameras() -> np.ndarray:
    """Six cameras a metre apart in y and 0.6 m in z, all looking along +x at the wall x = PLANE_X."""
    eye = np.array([[0.0, y, z] for y in (0.0, 0.8, 1.6) for z in (0.0, 0.6)])
    return look_at(eye, eye + [1.0, 0.0, 0.0])


def _cells(viewmats: np.ndarray, colour_of) -> dict[int, ViewCells]:
    """Every cell uncovered, coloured by ``colour_of(centre [N,3], direction [N,3])`` of its centre ray."""
    rows, cols = np.mgrid[0:ROWS, 0:COLS]
    rays = np.stack([((cols + 0.5) * SIZE - K[0, 2]) / K[0, 0], ((rows + 0.5) * SIZE - K[1, 2]) / K[1, 1],
                     np.ones(rows.shape)], axis=-1).reshape(-1, 3)
    out = {}
    for view, viewmat in enumerate(viewmats):
        R = viewmat[:3, :3]
        centre = -R.T @ viewmat[:3, 3]
        directions = rays @ R
        colour = colour_of(centre, directions / np.linalg.norm(directions, axis=1, keepdims=True))
        depth = np.full((ROWS, COLS), PLANE_X - centre[0])  # camera z of the wall (the axis is +x)
        out[view] = ViewCells(np.ones((ROWS, COLS), bool), colour.reshape(ROWS, COLS, 3), depth, SIZE)
    return out


def _measure(colour_of) -> Parallax:
    viewmats = _cameras()
    dataset = SimpleNamespace(cameras=SimpleNamespace(viewmats=torch.from_numpy(viewmats),
                                                      Ks=torch.from_numpy(np.stack([K] * len(viewmats)))))
    return measure_parallax(dataset, _cells(viewmats, colour_of), np.zeros((len(viewmats), 3)))


def test_colours_that_follow_the_direction_are_open_sky():
    # a gradient sky: brighter upwards and to the left, whatever the camera's position
    parallax = _measure(lambda centre, d: np.stack([0.5 + 0.4 * d[:, 2], 0.5 + 0.4 * d[:, 1], 0.6 + 0 * d[:, 0]], 1))
    assert parallax.cells >= MIN_CELLS and parallax.kind == "open sky"
    assert parallax.far_better > 10 * max(parallax.near_better, 1)
    assert parallax.description().startswith("open sky: these cells do not move with the parallax")


def test_colours_painted_on_a_near_wall_are_near_surfaces():
    def paper(centre, d):  # the colour of the wall point the ray meets
        point = centre + d * ((PLANE_X - centre[0]) / d[:, 0])[:, None]
        return np.stack([0.5 + 0.3 * np.sin(2.0 * point[:, 1]), 0.5 + 0.3 * np.cos(2.5 * point[:, 2]),
                         0.6 + 0 * point[:, 0]], 1)

    parallax = _measure(paper)
    assert parallax.cells >= MIN_CELLS and parallax.kind == "near surfaces"
    assert "sky" not in parallax.description()


def test_flat_colour_and_few_cells():
    flat = _measure(lambda centre, d: np.full((len(d), 3), 0.7))  # no parallax to see: counts as distant
    assert flat.near_better == flat.far_better == 0 and flat.kind == "open sky"
    assert Parallax(cells=10, near_better=10, far_better=0, still=5).kind is None
    assert "sky" not in Parallax(cells=10, near_better=10, far_better=0, still=5).description()
    assert Parallax(cells=10, near_better=0, far_better=0, still=40).description().startswith(
        "open sky: the reconstructed points around these cells are too far to move")


def test_bilinear_sampling_matches_scipy_map_coordinates():
    """Order-1 interpolation with the edge cells continued outwards (scipy's mode "nearest")."""
    ndimage = pytest.importorskip("scipy.ndimage")
    rng = np.random.default_rng(0)
    for rows, cols in ((ROWS, COLS), (1, 5), (4, 1), (1, 1)):
        colours = rng.random((rows, cols, 3)).astype(np.float32)
        coords = rng.uniform(-1.5, 1.5, (400, 2)) + rng.uniform(0, 1, (400, 2)) * [cols, rows]
        coords[:4] = [[0.5, 0.5], [cols - 0.5, rows - 0.5], [cols, rows], [0.0, 0.0]]  # centres and edges
        at = [coords[:, 1] - 0.5, coords[:, 0] - 0.5]
        expected = np.stack([ndimage.map_coordinates(colours[..., c], at, order=1, mode="nearest")
                             for c in range(3)], axis=1)
        got = _sample(colours, coords)
        assert got.dtype == expected.dtype
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)
