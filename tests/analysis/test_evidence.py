"""The analyses' shared helpers against slow, obvious references."""

from __future__ import annotations

import numpy as np
import pytest

from hico_plugin.analysis.evidence import group_median


def _median_per_group(groups: np.ndarray, values: np.ndarray, num_groups: int) -> np.ndarray:
    """np.median of each group's rows, one group at a time (0 for an empty group)."""
    out = np.zeros((num_groups, values.shape[1]))
    for g in range(num_groups):
        rows = values[groups == g]
        if len(rows):
            out[g] = np.median(rows, axis=0)
    return out


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_group_median_equals_the_median_of_each_group(dtype):
    rng = np.random.default_rng(0)
    num_groups = 300
    groups = rng.integers(0, num_groups - 20, size=5000)  # the last 20 groups are empty
    values = rng.normal(size=(5000, 3)).astype(dtype)
    values[::7] = values[1::7][: len(values[::7])]  # ties
    values[rng.integers(0, 5000, 30), 0] = -np.inf  # log of a black pixel
    values[rng.integers(0, 5000, 5), 1] = np.inf
    values[rng.integers(0, 5000, 3), 2] = np.nan
    groups[:2] = num_groups - 21  # a group of its own size, odd and even counts around it
    with np.errstate(invalid="ignore"):
        expected = _median_per_group(groups, values, num_groups)
    got = group_median(groups, values, num_groups)
    np.testing.assert_array_equal(got, expected)  # bit for bit, NaN where a group holds one
    assert np.isnan(got[:, 2]).any() and (got[-20:] == 0).all()


def test_group_median_of_an_odd_group_is_its_middle_value_even_near_overflow():
    groups = np.array([0, 1, 1, 1, 3])
    values = np.array([[1e308], [1e308], [1.5e308], [-1e308], [-2.5]])
    got = group_median(groups, values, 4)
    np.testing.assert_array_equal(got, _median_per_group(groups, values, 4))
    np.testing.assert_array_equal(got[:, 0], [1e308, 1e308, 0.0, -2.5])
