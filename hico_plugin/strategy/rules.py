"""Level-aware anchor growing and pruning (Octree-GS's densification), as pure tensor functions.

The strategy (octree.py) owns the statistics and applies the results to the field; these functions only
decide which offsets spawn which new anchors and which anchors are pruned.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hico_plugin.field.context_graph import ParentRule, cell_keys, dense_cell_ids, parent_edges
from hico_plugin.field.octree import OctreeGrid, visibility_fraction
from hico_plugin.strategy.base import DensifyConfig


def offset_gradients(grad_accum: Tensor, denom: Tensor, min_observations: float) -> tuple[Tensor, Tensor]:
    """Mean gradient per offset, zeroed where seen too rarely: [N,K] each -> (grads [N,K], eligible)."""
    eligible = denom > min_observations
    grads = torch.where(eligible, grad_accum / denom.clamp_min(1), torch.zeros_like(grad_accum))
    return grads, eligible


@dataclass
class GrownAnchors:
    """New anchors: positions [G,3] (on grid points), levels [G] long, features [G,d]."""

    positions: Tensor
    levels: Tensor
    features: Tensor


def level_thresholds(levels: Tensor, grid: OctreeGrid, config: DensifyConfig) -> Tensor:
    """tau_l = tau x u^l per anchor: levels [N] -> [N], u = b^update_ratio."""
    growth = float(grid.fork) ** config.update_ratio
    return config.grad_threshold * growth ** levels.to(torch.float32)


def grow_anchors(positions: Tensor, levels: Tensor, features: Tensor, offsets: Tensor, log_scaling: Tensor,
                 grads: Tensor, grid: OctreeGrid, config: DensifyConfig, camera_centers: Tensor,
                 visible_threshold: float, allow_next_level: bool, blocks: Tensor | None = None,
                 limit: int | None = None) -> GrownAnchors:
    """Anchors spawned by high-gradient offsets, all levels at once.

    positions [N,3], levels [N], features [N,d], offsets [N,K,3], log_scaling [N,6], grads [N,K]
    (offset_gradients), camera_centers [C,3] (weed-out); blocks [N] bool: anchors whose cells count as held;
    limit: at most this many new cells, largest gradient first (default: all). A level-l anchor's offset with
    tau_l <= g < tau_l x u proposes its Gaussian centre's level-l cell, with g >= tau_l x u (l < L-1, growth
    allowed) its level-(l+1) cell; held cells dropped, the rest de-duplicated and weeded out by visibility. A new
    cell's feature is the channel-wise max of its same-level sources, else zero.
    """
    growth = float(grid.fork) ** config.update_ratio
    tau = level_thresholds(levels, grid, config).to(grads)[:, None]
    same_level = (grads >= tau) & (grads < tau * growth)
    next_level = (grads >= tau * growth) & (levels < grid.num_levels - 1)[:, None] & allow_next_level
    rows, children = (same_level | next_level).nonzero(as_tuple=True)
    to_finer = next_level[rows, children]
    target_levels = levels[rows] + to_finer.long()
    centres = positions[rows] + offsets[rows, children] * torch.exp(log_scaling[rows, :3])
    cand_keys = cell_keys(centres, target_levels, grid)
    anchor_keys = cell_keys(positions, levels, grid)

    ids, num_cells = dense_cell_ids(torch.cat([anchor_keys, cand_keys]))
    occupied = torch.zeros(num_cells, dtype=torch.bool, device=positions.device)
    held = ids[: positions.shape[0]]
    occupied[held if blocks is None else held[blocks]] = True
    cand_ids = ids[positions.shape[0]:]
    free = ~occupied[cand_ids]
    new_cells, slot = torch.unique(cand_ids[free], return_inverse=True)
    num_new = new_cells.shape[0]
    free_keys = cand_keys[free]
    # Every candidate of a slot has the same key, so any one of them names the cell.
    new_keys = free_keys.new_empty(num_new, 4).index_copy_(0, slot, free_keys)
    same_sources = ~to_finer[free]
    new_features = features.new_zeros(num_new, features.shape[1]).scatter_reduce(
        0, slot[same_sources, None].expand(-1, features.shape[1]),
        features[rows[free][same_sources]].detach(), "amax", include_self=False)

    new_levels = new_keys[:, 0]
    new_positions = grid.grid_position(new_keys[:, 1:], new_levels, positions.dtype)
    keep = visibility_fraction(new_positions, new_levels, camera_centers, grid) > visible_threshold
    if limit is not None and int(keep.sum()) > limit:
        score = grads.new_zeros(num_new).scatter_reduce(0, slot, grads[rows, children][free], "amax",
                                                        include_self=False)
        score = torch.where(keep, score, torch.full_like(score, -1.0))
        keep = torch.zeros_like(keep).index_fill_(0, torch.topk(score, max(limit, 0)).indices, True)
    return GrownAnchors(new_positions[keep], new_levels[keep], new_features[keep])


def extra_level_increment(grads: Tensor, eligible: Tensor, levels: Tensor, grid: OctreeGrid,
                          config: DensifyConfig) -> Tensor:
    """Increment of eps_i: extra_up where the anchor's mean eligible gradient >= tau_l x extra_ratio.

    grads, eligible [N,K]; levels [N] -> [N]. Applied once per adjustment with each anchor's own
    level threshold (the base code applies it inside its per-level loop to all anchors, so eps can
    rise by up to L x extra_up per adjustment; we take the level-aware reading).
    """
    mean_grad = grads.sum(1) / (eligible.sum(1) + 1e-6)
    tau_extra = level_thresholds(levels, grid, config).to(grads) * config.extra_ratio
    return config.extra_up * (mean_grad >= tau_extra).to(grads)


def prune_decision(opacity_accum: Tensor, anchor_denom: Tensor, min_opacity: float, min_views: float
                   ) -> tuple[Tensor, Tensor]:
    """(prune [N] bool, judged [N] bool): judged anchors were seen in > min_views views; they are
    pruned when their accumulated opacity < min_opacity x views."""
    judged = anchor_denom > min_views
    return judged & (opacity_accum < min_opacity * anchor_denom), judged


def rows_in(queries: Tensor, table: Tensor) -> Tensor:
    """[Q] bool: which rows of queries [Q,4] long occur among the rows of table [T,4] long."""
    ids, num_cells = dense_cell_ids(torch.cat([table, queries]))
    held = torch.zeros(num_cells, dtype=torch.bool, device=queries.device)
    held[ids[: table.shape[0]]] = True
    return held[ids[table.shape[0]:]]


def orphan_edges(levels: Tensor, positions: Tensor, grid: OctreeGrid, occupied: Tensor | None = None
                 ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Anchors above level 0 none of whose trilinear candidate parents holds an anchor.

    levels [N] long, positions [N,3]; occupied [T,4] long: the cells that hold an anchor (default:
    the anchors' own cells) -> (orphan [N] bool, and the orphans' candidate edges: anchor [E] long,
    parent key [E,4] long (level, index), weight [E]).
    """
    anchor, parent_index, weight = parent_edges(levels, positions, grid, ParentRule.trilinear)
    parent_keys = torch.cat([levels[anchor, None] - 1, parent_index], 1)
    table = cell_keys(positions, levels, grid) if occupied is None else occupied
    has_parent = torch.zeros(levels.shape[0], dtype=torch.bool, device=levels.device)
    has_parent[anchor[rows_in(parent_keys, table)]] = True
    orphan = (levels > 0) & ~has_parent
    on_orphan = orphan[anchor]
    return orphan, anchor[on_orphan], parent_keys[on_orphan], weight[on_orphan]


def close_ancestors(positions: Tensor, levels: Tensor, features: Tensor, keep: Tensor, grown: GrownAnchors,
                    grid: OctreeGrid) -> tuple[Tensor, GrownAnchors]:
    """Give every kept or grown anchor a parent (see ``DensifyConfig.keep_ancestors``).

    positions [N,3], levels [N], features [N,d]: the current anchors; keep [N] bool: survives pruning; grown: the
    new anchors. Returns (keep [N] with pruned parents revived, grown with new parents appended). A pruned anchor
    in a candidate parent cell is revived (keeping its training), else an orphan gets a new anchor at its
    highest-weight candidate; only the anchors a round revived or created are checked in the next: at most
    num_levels - 1 rounds.
    """
    keep = keep.clone()
    own_keys = cell_keys(positions, levels, grid)  # [N,4]
    extra_positions, extra_levels, extra_features = [grown.positions], [grown.levels], [grown.features]
    check_positions = torch.cat([positions[keep], grown.positions])
    check_levels = torch.cat([levels[keep], grown.levels])
    check_features = torch.cat([features[keep], grown.features])
    occupied = torch.cat([own_keys[keep], cell_keys(grown.positions, grown.levels, grid)])
    for _ in range(grid.num_levels - 1):
        orphan, anchor, parent_keys, weight = orphan_edges(check_levels, check_positions, grid, occupied)
        if not orphan.any():
            break
        # revive pruned anchors sitting in a candidate parent cell of an orphan
        dead = (~keep).nonzero().squeeze(1)
        revived = dead[rows_in(own_keys[dead], parent_keys)]
        keep[revived] = True
        served = torch.zeros_like(orphan)
        served[anchor[rows_in(parent_keys, own_keys[revived])]] = True
        # the rest: a new anchor at each remaining orphan's highest-weight candidate (first on ties)
        pending = orphan & ~served
        on_pending = pending[anchor]
        edge_anchor, edge_keys, edge_weight = anchor[on_pending], parent_keys[on_pending], weight[on_pending]
        num = orphan.shape[0]
        top = edge_weight.new_zeros(num).scatter_reduce(0, edge_anchor, edge_weight, "amax", include_self=False)
        is_top = edge_weight == top[edge_anchor]
        edge_ids = torch.arange(edge_anchor.shape[0], device=levels.device)
        first_top = torch.full((num,), edge_anchor.shape[0], dtype=torch.long, device=levels.device)
        first_top = first_top.scatter_reduce(0, edge_anchor[is_top], edge_ids[is_top], "amin")
        new_keys, slot = torch.unique(edge_keys[first_top[pending]], dim=0, return_inverse=True)
        new_features = features.new_zeros(new_keys.shape[0], features.shape[1]).scatter_reduce(
            0, slot[:, None].expand(-1, features.shape[1]), check_features[pending], "amax", include_self=False)
        new_positions = grid.grid_position(new_keys[:, 1:], new_keys[:, 0], positions.dtype)
        extra_positions.append(new_positions)
        extra_levels.append(new_keys[:, 0])
        extra_features.append(new_features)
        # next round: only what this round added
        check_positions = torch.cat([positions[revived], new_positions])
        check_levels = torch.cat([levels[revived], new_keys[:, 0]])
        check_features = torch.cat([features[revived], new_features])
        occupied = torch.cat([occupied, own_keys[revived], new_keys])
    return keep, GrownAnchors(torch.cat(extra_positions), torch.cat(extra_levels), torch.cat(extra_features))

