"""Exact k-nearest-neighbour search (OpenCV's FLANN k-d tree) against SciPy's cKDTree."""

from __future__ import annotations

import numpy as np
import pytest

from hico_plugin.nearest import knn

spatial = pytest.importorskip("scipy.spatial")


def _uniform(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((n, 3))


def _clustered(n: int, seed: int = 0) -> np.ndarray:
    """50 blobs of very different widths (1e-4 .. 1e-1) in the unit cube: a badly balanced tree."""
    rng = np.random.default_rng(seed)
    centres, widths = rng.random((50, 3)), 10.0 ** rng.uniform(-4, -1, 50)
    blob = rng.integers(0, 50, n)
    return centres[blob] + rng.normal(size=(n, 3)) * widths[blob, None]


def _check_own(points: np.ndarray, k: int, atol: float = 1e-9) -> None:
    """knn of the points themselves against cKDTree's k + 1 nearest minus the first (the point itself)."""
    distances, indices = knn(points, k)
    expected = spatial.cKDTree(points).query(points, k=k + 1)[0][:, 1:]
    assert distances.dtype == np.float64 and indices.dtype == np.int64
    assert distances.shape == indices.shape == (len(points), k)
    np.testing.assert_allclose(distances, expected, rtol=0, atol=atol)
    assert (indices != np.arange(len(points))[:, None]).all()  # never the query itself
    np.testing.assert_allclose(distances, np.linalg.norm(points[indices] - points[:, None], axis=2), rtol=1e-15)
    assert (np.diff(distances, axis=1) >= 0).all()


@pytest.mark.parametrize("points", [_uniform(20_000), _clustered(20_000)], ids=["uniform", "clustered"])
def test_own_neighbours_match_ckdtree(points):
    _check_own(points, 3)


@pytest.mark.parametrize("points", [_uniform(20_000), _clustered(20_000)], ids=["uniform", "clustered"])
@pytest.mark.parametrize("k", [1, 4])
def test_queries_match_ckdtree(points, k):
    queries = _clustered(5_000, seed=1) * 1.2 - 0.1  # some outside the points' box
    distances, indices = knn(points, k, queries)
    expected = spatial.cKDTree(points).query(queries, k=k)[0].reshape(len(queries), k)
    np.testing.assert_allclose(distances, expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(distances, np.linalg.norm(points[indices] - queries[:, None], axis=2), rtol=1e-15)


def test_duplicates_are_other_points_at_distance_zero():
    base = _uniform(300)
    points = np.concatenate([base, base[:100], base[:10], np.zeros((40, 3))])  # pairs, triples, 41 at 0
    _check_own(points, 4)
    distances, _ = knn(points, 1)
    assert (distances[:100, 0] == 0).all() and (distances[-40:, 0] == 0).all()


def test_huge_coordinates_keep_their_precision():
    """A 1e6 offset: float32 alone would round the coordinates to 0.06; centring keeps them."""
    points = _clustered(5_000)
    expected = spatial.cKDTree(points).query(points, k=4)[0][:, 1:]
    distances, _ = knn(points + [1e6, -2e6, 5e5], 3)
    np.testing.assert_allclose(distances, expected, rtol=0, atol=1e-6)


def test_tiny_and_empty_sets_return_fewer_columns():
    assert knn(np.zeros((0, 3)), 3)[0].shape == (0, 0)
    assert knn(np.zeros((0, 3)), 2, np.ones((4, 3)))[0].shape == (4, 0)
    assert knn(np.ones((5, 3)), 2, np.zeros((0, 3)))[0].shape == (0, 2)
    assert knn(np.ones((1, 3)), 3)[0].shape == (1, 0)
    distances, indices = knn(np.array([[0.0, 0, 0], [3, 4, 0]]), 3)
    np.testing.assert_array_equal(distances, [[5.0], [5.0]])
    np.testing.assert_array_equal(indices, [[1], [0]])
    distances, indices = knn(np.array([[0.0, 0, 0], [0, 0, 2], [0, 1, 0]]), 5, np.array([[0.0, 0, 1.5]]))
    np.testing.assert_allclose(distances, [[0.5, 1.5, np.sqrt(1 + 2.25)]])
    np.testing.assert_array_equal(indices, [[1, 0, 2]])


def test_any_layout_and_dtype_gives_the_same_answer():
    points = _clustered(3_000)
    reference = knn(points, 3)
    for variant in (np.asfortranarray(points), np.repeat(points, 2, axis=0)[::2], points.T.copy().T):
        for got, want in zip(knn(variant, 3), reference):
            np.testing.assert_array_equal(got, want)
    grid = np.argwhere(np.ones((20, 30), bool))  # int64 cells, 2-D
    distances, _ = knn(grid[::7], 1, grid)
    np.testing.assert_allclose(distances[:, 0], spatial.cKDTree(grid[::7]).query(grid)[0], rtol=0, atol=1e-12)


def test_same_input_same_output():
    points = np.concatenate([_clustered(10_000), _clustered(1_000)])  # with ties at distance 0
    first, second = knn(points, 3), knn(points.copy(), 3)
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a, b)


def test_rejects_bad_arrays():
    with pytest.raises(ValueError, match=r"\[N, D\]"):
        knn(np.zeros(3), 1)
    with pytest.raises(ValueError, match="NaN"):
        knn(np.array([[0.0, 0, np.nan]]), 1)
    with pytest.raises(ValueError, match="2-D but points are 3-D"):
        knn(np.zeros((4, 3)), 1, np.zeros((2, 2)))
