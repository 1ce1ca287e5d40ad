"""An example plug-in for hico_plugin, installed as its own distribution.

Importing this module (which hico_plugin does through the ``hico_plugin.components`` entry point in
``pyproject.toml``) registers a context aggregator, ``gated-mean``, and a preset, ``example-gated``,
so ``hico-train example-gated`` and ``--model.field.context.kind gated-mean`` work with no edit of
hico_plugin. Its other modules, each named by an entry point of its own, add a loss
(``opacity_loss``), an exporter (``cameras_exporter``), a dataset format (``nerf_synthetic``) and an
image-formation effect (``vignetting``).
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor, nn

from hico_plugin.field.context import CONTEXT_AGGREGATORS, ContextAggregator, ContextConfig, context_triplet
from hico_plugin.field.context_graph import ContextGraph
from hico_plugin.presets import PRESETS, register_preset


@CONTEXT_AGGREGATORS.register("gated-mean")
class GatedMeanContext(ContextAggregator):
    """f_hat = f + sigmoid(g) * Linear(mean of the parent/self/child contexts), one gate per channel.

    The linear layer is zero-initialised, so f_hat = f at initialisation, like the built-in
    aggregators."""

    def __init__(self, config: ContextConfig, feature_dim: int):
        super().__init__(config, feature_dim)
        self.mix = nn.Linear(feature_dim, feature_dim)
        self.gate = nn.Parameter(torch.zeros(feature_dim))
        nn.init.zeros_(self.mix.weight)
        nn.init.zeros_(self.mix.bias)

    def forward(self, features: Tensor, graph: ContextGraph) -> Tensor:
        triplet = context_triplet(features, graph)  # [V,3,d]
        return features + torch.sigmoid(self.gate) * self.mix(triplet.mean(1))


def _example_preset():
    """hico-gs-lite with the gated-mean aggregator."""
    base = PRESETS["hico-gs-lite"][1]
    model = base.model
    field = dataclasses.replace(model.field, context=dataclasses.replace(model.field.context, kind="gated-mean"))
    return dataclasses.replace(base, method_name="example-gated", model=dataclasses.replace(model, field=field))


register_preset("example-gated", "Example plug-in: hico-gs-lite with a gated-mean context aggregator.",
                _example_preset())
