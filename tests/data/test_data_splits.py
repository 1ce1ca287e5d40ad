"""Extrapolation split and sparse views on the built-in city-block orbits and by hand."""

import numpy as np
import pytest
import torch

from hico_plugin.data.parser import DataParserConfig
from hico_plugin.data.splits import extrapolation_split, nearest_distances, sparse_views
from hico_plugin.errors import HicoError
from hico_plugin.scenes.generate import generate_scene


def test_test_views_are_farther_from_training_than_any_training_view_on_a_ring():
    angles = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    centres = np.stack([np.cos(angles), np.sin(angles), np.zeros(32)], 1)
    train, test = extrapolation_split(centres, 8)
    assert len(test) == 4 and not set(train.tolist()) & set(test.tolist())
    train_c, test_c = centres[train.numpy()], centres[test.numpy()]
    assert nearest_distances(test_c, train_c).min() > nearest_distances(train_c, train_c, exclude_self=True).max()
    assert len(train) >= 20  # only a small gap is given up
    # The interleaved split of the same ring has every test view between two training views.
    interleaved = np.arange(32) % 8 == 0
    spacing = nearest_distances(centres[~interleaved], centres[~interleaved], exclude_self=True).max()
    assert nearest_distances(centres[interleaved], centres[~interleaved]).min() <= spacing


def test_sparse_views_and_bad_values():
    assert sparse_views(torch.arange(10), 4).tolist() == [0, 4, 8]
    with pytest.raises(HicoError, match="--train-every"):
        sparse_views(torch.arange(10), 0)
    with pytest.raises(HicoError, match="extrapolation split needs >= 2"):
        extrapolation_split(np.eye(3), 1)
    with pytest.raises(HicoError, match="--split extrapolate: 2 views"):
        extrapolation_split(np.eye(3)[:2], 2)


def test_parser_options_on_a_built_in_scene(tmp_path):
    root = generate_scene("city-block", tmp_path / "city", num_views=24, width=32, height=24, pixel_samples=1,
                          sparse_points=200)
    base = DataParserConfig(data=root).parse()
    extrapolate = DataParserConfig(data=root, split="extrapolate").parse()
    sparse = DataParserConfig(data=root, train_every=4).parse()
    assert sparse.train_indices.tolist() == base.train_indices[::4].tolist()
    assert torch.equal(sparse.test_indices, base.test_indices)
    centres = extrapolate.cameras.centers.numpy()
    train, test = centres[extrapolate.train_indices.numpy()], centres[extrapolate.test_indices.numpy()]
    assert len(test) == 3
    assert nearest_distances(test, train).min() > nearest_distances(train, train, exclude_self=True).max()
    with pytest.raises(HicoError, match="--split"):
        DataParserConfig(data=root, split="random").parse()
