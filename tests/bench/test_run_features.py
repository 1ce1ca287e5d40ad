"""Cross-level feature analysis on hand-built fields: known features -> known distances."""

import math

import pytest
import torch

from hico_plugin.bench.run_features import (
    adjacent_distances,
    analyze_features,
    cross_level_distance,
    pair_pca,
    stratified_sample,
)


def test_known_features_give_known_distances():
    e1, e2 = torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0])
    features = torch.stack([e1, 3 * e1, e2, 2 * e2, e1 + e2, 2 * (e1 + e2)])
    levels = torch.tensor([0, 0, 1, 1, 2, 2])
    distance = cross_level_distance(features, levels)
    expected = torch.tensor([[0.0, 1.0, 1 - 1 / math.sqrt(2)],
                             [1.0, 0.0, 1 - 1 / math.sqrt(2)],
                             [1 - 1 / math.sqrt(2), 1 - 1 / math.sqrt(2), 0.0]])
    torch.testing.assert_close(distance, expected, atol=1e-6, rtol=0)
    torch.testing.assert_close(adjacent_distances(distance), torch.tensor([1.0, 1 - 1 / math.sqrt(2)]))


def test_opposite_features_within_a_level_average_out():
    # Level 0 holds f and -f: its mean cosine with anything is 0, so every distance to it is 1.
    features = torch.tensor([[1.0, 2.0], [-1.0, -2.0], [1.0, 2.0]])
    distance = cross_level_distance(features, torch.tensor([0, 0, 1]))
    torch.testing.assert_close(distance, torch.tensor([[1.0, 1.0], [1.0, 0.0]]))


def test_matches_the_double_sum_of_the_definition_and_marks_empty_levels():
    generator = torch.Generator().manual_seed(0)
    features = torch.randn(40, 8, generator=generator)
    levels = torch.randint(0, 3, (40,), generator=generator)
    levels[levels == 1] = 3  # level 1 empty
    distance = cross_level_distance(features, levels, num_levels=4)
    cos = torch.nn.functional.cosine_similarity(features[:, None], features[None], dim=2)
    for a in (0, 2, 3):
        for b in (0, 2, 3):
            reference = 1 - cos[levels == a][:, levels == b].mean()
            assert distance[a, b] == pytest.approx(float(reference), abs=1e-5)
    assert distance[1].isnan().all() and distance[:, 1].isnan().all()


def test_stratified_sample_caps_every_level():
    levels = torch.tensor([0] * 50 + [1] * 3 + [2] * 20)
    ids = stratified_sample(levels, 10, torch.Generator().manual_seed(1))
    assert torch.bincount(levels[ids]).tolist() == [10, 3, 10]
    assert len(set(ids.tolist())) == len(ids)


def test_pair_pca_separated_levels():
    generator = torch.Generator().manual_seed(2)
    noise = 0.01 * torch.randn(200, 4, generator=generator)
    centres = torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
    levels = torch.tensor([0] * 100 + [1] * 100)
    result = pair_pca(centres[levels] + noise, levels, 0, per_level=60, generator=generator)
    assert result["projection"].shape == (120, 2)
    assert result["explained"][0] > 0.99  # the level split is the principal axis
    assert abs(result["cos_sim"]) < 0.05  # orthogonal level means
    first = result["projection"][result["levels"] == 0, 0]
    second = result["projection"][result["levels"] == 1, 0]
    assert first.max() < second.min() or second.max() < first.min()
    assert pair_pca(centres[levels], levels, 1) is None  # level 2 has no anchors


def test_clca_reduction_is_relative_drop_of_adjacent_distance():
    features = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    f_hat = torch.tensor([[1.0, 0.0], [1.0, 1.0]])
    numbers = analyze_features(features, torch.tensor([0, 1]), 2, f_hat, per_level=10)
    assert numbers["f"]["adjacent"] == pytest.approx([1.0])
    assert numbers["f_hat"]["adjacent"] == pytest.approx([1 - 1 / math.sqrt(2)])
    assert numbers["adjacent_reduction"] == pytest.approx([1 / math.sqrt(2)])
    assert numbers["anchors_per_level"] == [1, 1]
