"""Cross-Level Context Aggregation (CLCA, paper Sec. 3.3): f_hat = f + MLP([c_parent; c_self; c_child]).

For the visible anchors of one view, features are pooled per (level, grid cell) into c_self; each
anchor also reads a parent context from the next coarser level and a child context from the next
finer one. The parent relation (``ContextConfig.parent_rule``) decides which anchors those are:

- ``"trilinear"`` (default): anchors sit on grid points (octree.py), so a level-l anchor with index k
  lies at k / b in level-(l-1) index units: on a level-(l-1) grid point where k is even, halfway
  between two where k is odd. Its parents are the 1, 2, 4 or 8 grid points around k / b with their
  trilinear weights (0 / 1 or 1/2 per axis for b = 2); c_parent is the weighted mean of the present
  ones, weights renormalised. A level-l anchor made from a point x (octree.voxelize) always has a
  level-(l-1) anchor made from the same x among these candidates (x is within v_l / 2 of k v_l, so it
  rounds to one of them one level up): the levels nest, and densification keeps them nested
  (``DensifyConfig.keep_ancestors``), so a parent is absent only where LOD or frustum culling hid it. Chosen over cell-centre anchors because it
  keeps the base method's grid, voxelisation, checkpoints and LOD exactly as they are.
  A context that is truly absent (coarsest level, no candidate visible, no finer anchor) is a learned
  ``missing`` vector per role (parent, child), so the MLP can tell "no context" from "same context".
- ``"paper"``: Eqs. 3-4 taken literally, parent cell ``round((p - o) / v_{l-1})`` on the (possibly
  drifted) position with torch's round-half-to-even on the .5 ties of odd indices, and the paper's
  fallback (a missing parent / child reads c_self) for every empty lookup. Kept for the ablation.

The child context uses the same relation ("child of" is the transpose of "parent of"): c_child of a
cell is the weighted mean of the finer anchors that have it as a parent candidate, with their weights.

Cost: one sort (``unique`` over the self keys and the <= 8 V candidate keys of the view) and a few
scatters: O(V log V), no Python loop over anchors or levels.
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

ParentRule = Literal["trilinear", "paper"]
PARENT_RULES = ("trilinear", "paper")
# Standard deviation of the last context layer at init: "near-zero" output (paper Sec. 3.3) that
# still lets the first layer receive gradient from the first step.
NEAR_ZERO_STD = 1e-3


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


def parent_edges(levels: Tensor, positions: Tensor, grid: OctreeGrid, rule: ParentRule
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """Candidate parents of every anchor above level 0: (anchor [E] long, parent index [E,3] long at
    level - 1, weight [E]). levels [V] long, positions [V,3]. Weights of one anchor sum to 1."""
    fine = (levels > 0).nonzero().squeeze(1)
    if rule == "paper":
        index = grid.grid_index(positions.detach()[fine], levels[fine] - 1)
        return fine, index, positions.new_ones(fine.shape[0])
    own = grid.grid_index(positions.detach()[fine], levels[fine])  # [F,3]
    base = torch.div(own, grid.fork, rounding_mode="floor")
    frac = (own - base * grid.fork).to(positions.dtype) / grid.fork  # [F,3] position of k/b in its cell
    corners = torch.tensor([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], device=levels.device)
    per_axis = torch.where(corners[None].bool(), frac[:, None, :], 1.0 - frac[:, None, :])  # [F,8,3]
    weights = per_axis.prod(-1)  # [F,8]
    keep = weights > 0
    anchor = fine[:, None].expand(-1, 8)[keep]
    return anchor, (base[:, None, :] + corners[None])[keep], weights[keep]


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


def context_lookup(features: Tensor, levels: Tensor, positions: Tensor, grid: OctreeGrid,
                   parent_rule: ParentRule = "trilinear", reduce: str = "mean") -> ContextLookup:
    """c_parent, c_self, c_child of the visible anchors of one view (paper Eqs. 2-4, see module doc).

    features [V,d]; levels [V] long; positions [V,3]; reduce "mean" (weighted mean) | "amax" (max over
    the found anchors, weights ignored).
    """
    num, dim = features.shape
    self_index = grid.grid_index(positions.detach(), levels)
    self_keys = torch.cat([levels[:, None], self_index], 1)
    anchor, parent_index, weight = parent_edges(levels, positions, grid, parent_rule)
    parent_keys = torch.cat([levels[anchor, None] - 1, parent_index], 1)
    ids, num_cells = dense_cell_ids(torch.cat([self_keys, parent_keys]))
    self_ids, edge_cells = ids[:num], ids[num:]

    counts = torch.bincount(self_ids, minlength=num_cells)
    present = counts[edge_cells] > 0  # the candidate parent cell holds a visible anchor
    anchor, edge_cells, weight = anchor[present], edge_cells[present], weight[present].to(features.dtype)
    if reduce == "mean":
        self_pool = features.new_zeros(num_cells, dim).index_add(0, self_ids, features)
        self_pool = self_pool / counts.clamp_min(1)[:, None].to(features.dtype)
    else:
        self_pool = features.new_zeros(num_cells, dim).scatter_reduce(
            0, self_ids[:, None].expand(-1, dim), features, "amax", include_self=False)
    own = self_pool.index_select(0, self_ids)

    def gather(target: Tensor, values: Tensor, size: int) -> tuple[Tensor, Tensor]:
        """Weighted mean (or max) of values [E,d] into rows target [E] of a [size,d] table."""
        total = weight.new_zeros(size).index_add(0, target, weight)
        if reduce == "mean":
            pooled = features.new_zeros(size, dim).index_add(0, target, weight[:, None] * values)
            return pooled / total.clamp_min(1e-12)[:, None], total > 0
        pooled = features.new_zeros(size, dim).scatter_reduce(
            0, target[:, None].expand(-1, dim), values, "amax", include_self=False)
        return pooled, total > 0

    parent, parent_found = gather(anchor, self_pool.index_select(0, edge_cells), num)
    child_cells, child_cell_found = gather(edge_cells, features.index_select(0, anchor), num_cells)
    child = child_cells.index_select(0, self_ids)
    child_found = child_cell_found[self_ids]
    parent_pooled = torch.zeros(num, dtype=torch.long, device=levels.device).index_add(
        0, anchor, counts[edge_cells])
    child_pooled = torch.bincount(edge_cells, minlength=num_cells)[self_ids]
    if parent_rule == "paper":  # the paper's fallback: an empty lookup reads c_self
        parent = torch.where(parent_found[:, None], parent, own)
        child = torch.where(child_found[:, None], child, own)
    return ContextLookup(parent, own, child, parent_found, child_found, parent_pooled, child_pooled)


def context_triplet(features: Tensor, levels: Tensor, positions: Tensor, grid: OctreeGrid,
                    parent_rule: ParentRule = "trilinear", reduce: str = "mean",
                    missing: Tensor | None = None) -> Tensor:
    """The MLP input [V,3,d]: (c_parent, c_self, c_child), with missing [2,d] (parent, child rows)
    where a context is absent under the trilinear rule (zeros if missing is None)."""
    found = context_lookup(features, levels, positions, grid, parent_rule, reduce)
    parent, child = found.parent, found.child
    if parent_rule != "paper" and missing is not None:
        parent = torch.where(found.parent_found[:, None], parent, missing[0])
        child = torch.where(found.child_found[:, None], child, missing[1])
    return torch.stack([parent, found.own, child], 1)


@dataclass
class ContextConfig(InstantiateConfig):
    """Cross-level context aggregation (CLCA) of the visible anchors' features."""

    kind: str = "mean"
    """Aggregator: none (f_hat = f), mean (the paper), max (max-pooled contexts), attention
    (attention over the parent/self/child triplet instead of concatenation + MLP)."""
    parent_rule: ParentRule = "trilinear"
    """Which coarser anchors are an anchor's parents: trilinear = the 1-8 grid points around k/2 with
    trilinear weights, absent contexts a learned vector (levels nest); paper = the paper's
    round((p - o)/v_{l-1}) with a copy of c_self for every empty lookup (the literal ablation)."""
    hidden_dim: int = -1
    """Hidden width of the context MLP; -1 = the feature dimension d (paper: 3d -> d -> d)."""
    bias: bool = True
    """Biases in the context MLP. With d = 32 and biases the MLP has 4,160 parameters (the paper's
    3,168 is not reachable by a 96 -> 32 -> 32 MLP; without biases it has 4,096)."""

    def setup(self, feature_dim: int = 32, **kwargs) -> "ContextAggregator":
        if self.parent_rule not in PARENT_RULES:
            raise HicoError(f"field.context.parent_rule: expected one of {', '.join(PARENT_RULES)}, "
                            f"got '{self.parent_rule}'")
        return CONTEXT_AGGREGATORS.get(self.kind)(self, feature_dim)


class ContextAggregator(nn.Module):
    """Maps the visible anchors' raw features to enhanced ones: features [V,d] -> [V,d]."""

    reduce = "mean"

    def __init__(self, config: ContextConfig, feature_dim: int):
        super().__init__()
        self.config = config
        self.feature_dim = feature_dim

    def lookup(self, features: Tensor, levels: Tensor, positions: Tensor, grid: OctreeGrid) -> ContextLookup:
        """The contexts this aggregator reads (for statistics; ``none`` reports its would-be lookup)."""
        return context_lookup(features, levels, positions, grid, self.config.parent_rule, self.reduce)

    def forward(self, features: Tensor, levels: Tensor, positions: Tensor, grid: OctreeGrid) -> Tensor:
        raise NotImplementedError


@CONTEXT_AGGREGATORS.register("none")
class NoContext(ContextAggregator):
    """The ablation without CLCA: f_hat = f (no parameters)."""

    def forward(self, features, levels, positions, grid):
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

    def triplet(self, features, levels, positions, grid) -> Tensor:
        return context_triplet(features, levels, positions, grid, self.config.parent_rule, self.reduce,
                               self.missing)


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

    def forward(self, features, levels, positions, grid):
        return features + self.mlp(self.triplet(features, levels, positions, grid).flatten(1))


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

    def forward(self, features, levels, positions, grid):
        triplet = self.triplet(features, levels, positions, grid) + self.roles
        q = self.query(features)  # [V,h]
        k, v = self.key(triplet), self.value(triplet)  # [V,3,h]
        weights = torch.softmax((k @ q[:, :, None]).squeeze(-1) / math.sqrt(q.shape[1]), dim=1)  # [V,3]
        return features + self.out((weights[:, :, None] * v).sum(1))
