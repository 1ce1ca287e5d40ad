"""The toy model's own checks (the toy itself is tests/helpers_toy_model.py)."""

from __future__ import annotations

import numpy as np
import torch

from hico_plugin.engine.optimizers import Optimizers
from hico_plugin.engine.protocol import TrainableModel, TrainDataset
from helpers_toy_model import ToyDataConfig, ToyModelConfig


def test_toy_satisfies_protocols():
    dataset = ToyDataConfig().setup()
    model = ToyModelConfig().setup(dataset)
    assert isinstance(model, TrainableModel)
    assert isinstance(dataset, TrainDataset)
    assert dataset.image(0).dtype == np.uint8 and dataset.image(0).shape == (8, 8, 3)


def test_toy_densify_resizes_through_optimizers():
    dataset = ToyDataConfig().setup()
    model = ToyModelConfig(densify_every=1).setup(dataset)
    optimizers = Optimizers(model.param_groups(), model.lr_schedules(10))
    model.grad_accum.copy_(torch.tensor([3.0, 0.5, 9.0, 1.0, 2.0, 4.0]))
    before = model.features.detach().clone()
    model.after_optimizer_step(0, optimizers)
    assert model.features.shape == (7, 3)
    assert torch.equal(model.features[:5], before[[0, 1, 3, 4, 5]])
    assert torch.equal(model.features[5], before[2] / 2) and torch.equal(model.features[6], before[2] / 2)
    assert optimizers.params("blobs")[0] is model.features
