"""Cross-Level Context Aggregation (CLCA, paper Sec. 3.3): f_hat = f + MLP([c_parent; c_self; c_child]).

For one view's visible anchors, features are pooled per (level, grid cell) into c_self; each anchor also reads a
parent context from the next coarser level and a child context (the transposed relation) from the next finer one,
by ``ContextConfig.parent_rule`` (``context_graph.ParentRule``). Under "trilinear" a truly absent context is a
learned ``missing`` vector per role, so the MLP can tell "no context" from "same context". Pooling along
context_graph.py's relation is O(V + E) a view: context_fused.py's kernel on CPU, else sparse products.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from hico_plugin.config import InstantiateConfig
from hico_plugin.errors import HicoError
from hico_plugin.field.context_fused import fused_context, pooled_triplet, view_graph
from hico_plugin.field.context_graph import PARENT_RULES, ContextGraph, ContextIndex, ParentRule
from hico_plugin.field.octree import OctreeGrid
from hico_plugin.registry import Registry

CONTEXT_AGGREGATORS: Registry[type["ContextAggregator"]] = Registry("context aggregator")

# Standard deviation of the last context layer at init: "near-zero" output (paper Sec. 3.3) that
# still lets the first layer receive gradient from the first step.
NEAR_ZERO_STD = 1e-3


@dataclass
class ContextLookup:
    """The contexts of the visible anchors of one view and how they were found.

    parent, own, child [V,d]: pooled contexts; where a parent / child was not found they are zero,
    except under the paper rule, where they are c_self (its fallback).
    parent_found, child_found [V] bool; parent_pooled, child_pooled [V] long: anchors pooled into it.
    """

    parent: Tensor
    own: Tensor
    child: Tensor
    parent_found: Tensor
    child_found: Tensor
    parent_pooled: Tensor
    child_pooled: Tensor


def context_lookup(features: Tensor, graph: ContextGraph, reduce: str = "mean") -> ContextLookup:
    """c_parent, c_self, c_child of the visible anchors of one view (paper Eqs. 2-4, see module doc).

    features [V,d] in the graph's anchor order; reduce "mean" (weighted mean) | "amax" (max over the
    found anchors, weights ignored).
    """
    num, dim = features.shape
    parent_found = graph.parent_weight > 0
    child_found = graph.child_weight[graph.cell] > 0
    if reduce == "mean":
        of_cell = graph.of_cell()
        pooled = graph.cell_mean()(features)  # [K,d]
        own = of_cell(pooled)
        parent = graph.parent_mean()(pooled)
        child = of_cell(graph.child_mean()(features))
    else:
        def amax(target: Tensor, values: Tensor, size: int) -> Tensor:
            return features.new_zeros(size, dim).scatter_reduce(
                0, target[:, None].expand(-1, dim), values, "amax", include_self=False)
        pooled = amax(graph.cell, features, graph.num_cells)
        parent = amax(graph.anchor, pooled.index_select(0, graph.edge_cell), num)
        child = amax(graph.edge_cell, features.index_select(0, graph.anchor), graph.num_cells
                     ).index_select(0, graph.cell)
        own = pooled.index_select(0, graph.cell)
    parent_pooled = torch.zeros(num, dtype=torch.long, device=features.device).index_add(
        0, graph.anchor, graph.count[graph.edge_cell])
    child_pooled = torch.bincount(graph.edge_cell, minlength=graph.num_cells)[graph.cell]
    if not graph.rule.nests:  # the paper's fallback: an empty lookup reads c_self
        parent = parent + (~parent_found)[:, None] * own
        child = child + (~child_found)[:, None] * own
    return ContextLookup(parent, own, child, parent_found, child_found, parent_pooled, child_pooled)


def context_triplet(features: Tensor, graph: ContextGraph, reduce: str = "mean",
                    missing: Tensor | None = None) -> Tensor:
    """The MLP input [V,3,d]: (c_parent, c_self, c_child), with missing [2,d] (parent, child rows)
    where a context is absent under the trilinear rule (zeros if missing is None)."""
    if reduce == "mean" and fused_context(features.device):
        return pooled_triplet(features, graph, missing)
    found = context_lookup(features, graph, reduce)
    parent, child = found.parent, found.child
    if graph.rule.nests and missing is not None:
        # parent / child are exactly 0 where absent: adding is where() without its two-branch backward.
        parent = parent + (~found.parent_found)[:, None] * missing[0]
        child = child + (~found.child_found)[:, None] * missing[1]
    return torch.stack([parent, found.own, child], 1)


@dataclass
class ContextConfig(InstantiateConfig):
    """Cross-level context aggregation (CLCA) of the visible anchors' features."""

    kind: str = "mean"
    """Aggregator: none (f_hat = f), mean (the paper), max (max-pooled contexts), attention
    (attention over the parent/self/child triplet instead of concatenation + MLP)."""
    parent_rule: ParentRule = ParentRule.trilinear
    """Which coarser anchors are an anchor's parents: trilinear = the 1-8 grid points around k/2 with
    trilinear weights, absent contexts a learned vector (levels nest); paper = the paper's
    round((p - o)/v_{l-1}) with a copy of c_self for every empty lookup (the literal ablation)."""
    hidden_dim: int = -1
    """Hidden width of the context MLP; -1 = the feature dimension d (paper: 3d -> d -> d)."""
    bias: bool = True
    """Biases in the context MLP. With d = 32 and biases the MLP has 4,160 parameters (the paper's
    3,168 is not reachable by a 96 -> 32 -> 32 MLP; without biases it has 4,096)."""

    def __post_init__(self) -> None:
        # config.yml files and Python callers give the rule as its name
        if self.parent_rule not in PARENT_RULES:
            raise HicoError(f"field.context.parent_rule: expected one of {', '.join(PARENT_RULES)}, "
                            f"got '{self.parent_rule}'")
        self.parent_rule = ParentRule(self.parent_rule)

    def setup(self, feature_dim: int = 32, **kwargs) -> "ContextAggregator":
        return CONTEXT_AGGREGATORS.get(self.kind)(self, feature_dim)


class ContextAggregator(nn.Module):
    """Maps the visible anchors' raw features to enhanced ones: features [V,d], graph -> [V,d].

    ``graph`` (context_graph.ContextGraph) says which visible anchors each one's contexts read; the
    field gets it from ``graph()``, which keeps the relation over all anchors between steps.
    """

    reduce = "mean"
    reads_context = True
    """False for an aggregator that ignores the graph (the field then does not build it)."""

    def __init__(self, config: ContextConfig, feature_dim: int):
        super().__init__()
        self.config = config
        self.feature_dim = feature_dim
        self._index: ContextIndex | None = None

    def graph(self, levels: Tensor, positions: Tensor, visible: Tensor, grid: OctreeGrid) -> ContextGraph:
        """levels [N], positions [N,3] of all anchors, visible [V] ascending -> the view's graph."""
        if fused_context(positions.device):
            return view_graph(levels, positions, visible, grid, self.config.parent_rule)
        if self._index is None or self._index.grid is not grid:
            self._index = ContextIndex(grid, self.config.parent_rule)
        return self._index.view(levels, positions, visible)

    def lookup(self, features: Tensor, graph: ContextGraph) -> ContextLookup:
        """The contexts this aggregator reads (for statistics; ``none`` reports its would-be lookup)."""
        return context_lookup(features, graph, self.reduce)

    def forward(self, features: Tensor, graph: ContextGraph) -> Tensor:
        raise NotImplementedError


@CONTEXT_AGGREGATORS.register("none")
class NoContext(ContextAggregator):
    """The ablation without CLCA: f_hat = f (no parameters)."""

    reads_context = False

    def forward(self, features, graph):
        return features


def _near_zero_(layer: nn.Linear) -> None:
    """Small random weights, zero bias: f_hat ~ f at init, and the layers before still get gradient."""
    nn.init.normal_(layer.weight, std=NEAR_ZERO_STD)
    if layer.bias is not None:
        nn.init.zeros_(layer.bias)


class _TripletAggregator(ContextAggregator):
    """Shared by the aggregators that read a triplet: the learned "missing" vectors (parent, child)."""

    def __init__(self, config: ContextConfig, feature_dim: int):
        super().__init__(config, feature_dim)
        self.missing = nn.Parameter(0.02 * torch.randn(2, feature_dim))

    def triplet(self, features: Tensor, graph: ContextGraph) -> Tensor:
        return context_triplet(features, graph, self.reduce, self.missing)


@CONTEXT_AGGREGATORS.register("mean")
class MeanContext(_TripletAggregator):
    """The paper's CLCA: mean-pooled triplet -> Linear(3d, h) -> ReLU -> Linear(h, d), residual.

    The last layer starts near zero (std 1e-3, zero bias), the paper's "near-zero output at init".
    """

    def __init__(self, config: ContextConfig, feature_dim: int):
        super().__init__(config, feature_dim)
        hidden = config.hidden_dim if config.hidden_dim > 0 else feature_dim
        self.mlp = nn.Sequential(nn.Linear(3 * feature_dim, hidden, bias=config.bias), nn.ReLU(),
                                 nn.Linear(hidden, feature_dim, bias=config.bias))
        _near_zero_(self.mlp[2])

    def forward(self, features, graph):
        return features + self.mlp(self.triplet(features, graph).flatten(1))


@CONTEXT_AGGREGATORS.register("max")
class MaxContext(MeanContext):
    """Ablation: the same MLP on max-pooled (per channel) instead of mean-pooled contexts."""

    reduce = "amax"


@CONTEXT_AGGREGATORS.register("attention")
class AttentionContext(_TripletAggregator):
    """Ablation: single-head attention of the anchor over its (parent, self, child) contexts.

    query = W_q f, keys = W_k (c_t + r_t), values = W_v (c_t + r_t) for the three mean-pooled contexts
    c_t with a learned role embedding r_t (so the three stay distinguishable when fallbacks make them
    equal); f_hat = f + W_o softmax(q.k / sqrt(h)) v. W_o starts near zero so f_hat ~ f at init.
    """

    def __init__(self, config: ContextConfig, feature_dim: int):
        super().__init__(config, feature_dim)
        hidden = config.hidden_dim if config.hidden_dim > 0 else feature_dim
        self.query = nn.Linear(feature_dim, hidden, bias=config.bias)
        self.key = nn.Linear(feature_dim, hidden, bias=config.bias)
        self.value = nn.Linear(feature_dim, hidden, bias=config.bias)
        self.out = nn.Linear(hidden, feature_dim, bias=config.bias)
        self.roles = nn.Parameter(0.02 * torch.randn(3, feature_dim))
        _near_zero_(self.out)
        if config.bias:
            # Zero biases too: anchor features start at zero, so the values would otherwise be the
            # value bias (|b| ~ 0.18 per channel), the same for every anchor, and Adam's first steps
            # on W_o would shift every f_hat alike by ~0.04 per channel per step -- enough to drive
            # every opacity below zero within ten steps (all Gaussians gone, anchors pruned).
            for layer in (self.query, self.key, self.value):
                nn.init.zeros_(layer.bias)

    def forward(self, features, graph):
        triplet = self.triplet(features, graph) + self.roles
        q = self.query(features)  # [V,h]
        k, v = self.key(triplet), self.value(triplet)  # [V,3,h]
        weights = torch.softmax((k @ q[:, :, None]).squeeze(-1) / math.sqrt(q.shape[1]), dim=1)  # [V,3]
        return features + self.out((weights[:, :, None] * v).sum(1))
