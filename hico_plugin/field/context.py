"""Cross-Level Context Aggregation (CLCA, paper Sec. 3.3): f_hat = f + MLP([c_parent; c_self; c_child]).

For the visible anchors of one view, features are pooled per (level, grid cell); each anchor reads
the pooled context of its own cell (c_self), of the cell containing it one level coarser (c_parent),
and of the finer anchors lying in its own cell (c_child). Missing parent / child (coarsest or finest
active level, or an empty cell among the visible anchors) fall back to c_self, the paper's rule for
the coarsest / finest level applied to every empty lookup.

Cost: one sort (``unique`` over the 2V self + parent keys of the view) and a few scatters:
O(V log V), no Python loop over anchors or levels.

Reading of the grid coordinate (``ContextConfig.parent_rule``): anchors sit on grid points
(octree.py), so the paper's ``round((p - o) / v_l)`` is exactly the anchor's own index k. One level
coarser, ``round(k / 2)`` is an exact .5 tie for every odd component of k.
- ``"floor"`` (default): parent cell = floor(k / b) on the integer self index, the octree containment
  (children 2k', 2k'+1 of cell k'); symmetric, deterministic, and robust to trained drift of p.
- ``"round"``: the paper's formula taken literally, ``round((p - o) / v_{l-1})`` on the (possibly
  drifted) position, with torch's round-half-to-even on ties.
The child context uses the same rule so that "child of" and "parent of" are one relation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor, nn

from hico_plugin.config import InstantiateConfig
from hico_plugin.errors import HicoError
from hico_plugin.field.octree import OctreeGrid
from hico_plugin.registry import Registry

CONTEXT_AGGREGATORS: Registry[type["ContextAggregator"]] = Registry("context aggregator")

ParentRule = Literal["floor", "round"]


def dense_cell_ids(keys: Tensor) -> tuple[Tensor, int]:
    """Dense ids of integer keys: keys [N,4] long -> (ids [N] long in [0, U), U), equal keys <-> equal
    ids. Keys are packed into one int64 by mixed radix over their range when that fits (one 1-D sort),
    else ``unique(dim=0)`` (a lexicographic sort)."""
    if keys.shape[0] == 0:
        return keys.new_zeros(0), 0
    low = keys.min(0).values
    spans = (keys.max(0).values - low + 1).tolist()
    if math.prod(spans) < (1 << 62):
        shifted = keys - low
        packed = shifted[:, 0]
        for axis in range(1, keys.shape[1]):
            packed = packed * spans[axis] + shifted[:, axis]
        unique, ids = torch.unique(packed, return_inverse=True)
    else:
        unique, ids = torch.unique(keys, dim=0, return_inverse=True)
    return ids, unique.shape[0]


def _pool(features: Tensor, ids: Tensor, num_cells: int, reduce: str) -> tuple[Tensor, Tensor]:
    """Per-cell mean or max of features [n,d] grouped by ids [n] -> (pooled [U,d], counts [U])."""
    counts = torch.bincount(ids, minlength=num_cells)
    pooled = features.new_zeros(num_cells, features.shape[1])
    if reduce == "mean":
        pooled = pooled.index_add(0, ids, features) / counts.clamp_min(1)[:, None].to(features.dtype)
    else:
        pooled = pooled.scatter_reduce(0, ids[:, None].expand_as(features), features, "amax",
                                       include_self=False)
    return pooled, counts


def context_triplet(features: Tensor, levels: Tensor, positions: Tensor, grid: OctreeGrid,
                    parent_rule: ParentRule = "floor", reduce: str = "mean") -> Tensor:
    """The contexts (c_parent, c_self, c_child) of the visible anchors of one view: [V,3,d].

    features [V,d] raw anchor features f; levels [V] long; positions [V,3]; reduce "mean" | "amax".
    """
    num = features.shape[0]
    self_index = grid.grid_index(positions.detach(), levels)
    if parent_rule == "floor":
        parent_index = torch.div(self_index, grid.fork, rounding_mode="floor")
    else:
        parent_index = grid.grid_index(positions.detach(), levels - 1)
    self_keys = torch.cat([levels[:, None], self_index], 1)
    parent_keys = torch.cat([levels[:, None] - 1, parent_index], 1)
    ids, num_cells = dense_cell_ids(torch.cat([self_keys, parent_keys]))
    self_ids, parent_ids = ids[:num], ids[num:]

    # Level-0 anchors have no coarser cell: they pool into a spare row, dropped below.
    has_coarser = levels > 0
    self_pool, self_counts = _pool(features, self_ids, num_cells, reduce)
    child_pool, child_counts = _pool(features, torch.where(has_coarser, parent_ids, num_cells),
                                     num_cells + 1, reduce)
    # Rows of [self_pool; child_pool] to read, with the fallbacks resolved on integer ids, so the
    # whole triplet is one index_select (cheap forward and backward).
    parent_rows = torch.where(has_coarser & (self_counts[parent_ids] > 0), parent_ids, self_ids)
    child_rows = torch.where(child_counts[self_ids] > 0, num_cells + self_ids, self_ids)
    table = torch.cat([self_pool, child_pool[:num_cells]])
    rows = torch.stack([parent_rows, self_ids, child_rows], 1).reshape(-1)
    return table.index_select(0, rows).view(num, 3, features.shape[1])


@dataclass
class ContextConfig(InstantiateConfig):
    """Cross-level context aggregation (CLCA) of the visible anchors' features."""

    kind: str = "mean"
    """Aggregator: none (f_hat = f), mean (the paper), max (max-pooled contexts), attention
    (attention over the parent/self/child triplet instead of concatenation + MLP)."""
    parent_rule: ParentRule = "floor"
    """Parent cell of an anchor with grid index k: floor = floor(k/2) on the index (octree
    containment); round = the paper's round((p - o)/v_{l-1}) on the position (ties half to even)."""
    hidden_dim: int = -1
    """Hidden width of the context MLP; -1 = the feature dimension d (paper: 3d -> d -> d)."""
    bias: bool = True
    """Biases in the context MLP. With d = 32 and biases the MLP has 4,160 parameters (the paper's
    3,168 is not reachable by a 96 -> 32 -> 32 MLP; without biases it has 4,096)."""

    def setup(self, feature_dim: int = 32, **kwargs) -> "ContextAggregator":
        if self.parent_rule not in ("floor", "round"):
            raise HicoError(f"field.context.parent_rule: expected floor or round, got '{self.parent_rule}'")
        return CONTEXT_AGGREGATORS.get(self.kind)(self, feature_dim)


class ContextAggregator(nn.Module):
    """Maps the visible anchors' raw features to enhanced ones: features [V,d] -> [V,d]."""

    def __init__(self, config: ContextConfig, feature_dim: int):
        super().__init__()
        self.config = config
        self.feature_dim = feature_dim

    def forward(self, features: Tensor, levels: Tensor, positions: Tensor, grid: OctreeGrid) -> Tensor:
        raise NotImplementedError


@CONTEXT_AGGREGATORS.register("none")
class NoContext(ContextAggregator):
    """The ablation without CLCA: f_hat = f (no parameters)."""

    def forward(self, features, levels, positions, grid):
        return features


@CONTEXT_AGGREGATORS.register("mean")
class MeanContext(ContextAggregator):
    """The paper's CLCA: mean-pooled triplet -> Linear(3d, h) -> ReLU -> Linear(h, d), residual.

    The last layer is zero-initialised, so f_hat = f exactly at initialisation (the paper's "near-zero
    output at init"; PyTorch's default init would not give that).
    """

    reduce = "mean"

    def __init__(self, config: ContextConfig, feature_dim: int):
        super().__init__(config, feature_dim)
        hidden = config.hidden_dim if config.hidden_dim > 0 else feature_dim
        self.mlp = nn.Sequential(nn.Linear(3 * feature_dim, hidden, bias=config.bias), nn.ReLU(),
                                 nn.Linear(hidden, feature_dim, bias=config.bias))
        nn.init.zeros_(self.mlp[2].weight)
        if config.bias:
            nn.init.zeros_(self.mlp[2].bias)

    def forward(self, features, levels, positions, grid):
        triplet = context_triplet(features, levels, positions, grid, self.config.parent_rule, self.reduce)
        return features + self.mlp(triplet.flatten(1))


@CONTEXT_AGGREGATORS.register("max")
class MaxContext(MeanContext):
    """Ablation: the same MLP on max-pooled (per channel) instead of mean-pooled contexts."""

    reduce = "amax"


@CONTEXT_AGGREGATORS.register("attention")
class AttentionContext(ContextAggregator):
    """Ablation: single-head attention of the anchor over its (parent, self, child) contexts.

    query = W_q f, keys = W_k (c_t + r_t), values = W_v (c_t + r_t) for the three mean-pooled contexts
    c_t with a learned role embedding r_t (so the three stay distinguishable when fallbacks make them
    equal); f_hat = f + W_o softmax(q.k / sqrt(h)) v. W_o is zero-initialised so f_hat = f at init.
    """

    def __init__(self, config: ContextConfig, feature_dim: int):
        super().__init__(config, feature_dim)
        hidden = config.hidden_dim if config.hidden_dim > 0 else feature_dim
        self.query = nn.Linear(feature_dim, hidden, bias=config.bias)
        self.key = nn.Linear(feature_dim, hidden, bias=config.bias)
        self.value = nn.Linear(feature_dim, hidden, bias=config.bias)
        self.out = nn.Linear(hidden, feature_dim, bias=config.bias)
        self.roles = nn.Parameter(0.02 * torch.randn(3, feature_dim))
        nn.init.zeros_(self.out.weight)
        if config.bias:
            # Zero biases too: anchor features start at zero, so the values would otherwise be the
            # value bias (|b| ~ 0.18 per channel), the same for every anchor, and Adam's first steps
            # on W_o would shift every f_hat alike by ~0.04 per channel per step -- enough to drive
            # every opacity below zero within ten steps (all Gaussians gone, anchors pruned).
            for layer in (self.query, self.key, self.value, self.out):
                nn.init.zeros_(layer.bias)

    def forward(self, features, levels, positions, grid):
        triplet = context_triplet(features, levels, positions, grid, self.config.parent_rule) + self.roles
        q = self.query(features)  # [V,h]
        k, v = self.key(triplet), self.value(triplet)  # [V,3,h]
        weights = torch.softmax((k @ q[:, :, None]).squeeze(-1) / math.sqrt(q.shape[1]), dim=1)  # [V,3]
        return features + self.out((weights[:, :, None] * v).sum(1))
