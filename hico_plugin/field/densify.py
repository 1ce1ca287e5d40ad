"""Level-aware anchor growing and pruning (Octree-GS's densification), as pure tensor functions.

The field (field.py) owns the statistics buffers and applies the results; these functions only decide
which offsets spawn which new anchors and which anchors are pruned.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from hico_plugin.config import InstantiateConfig
from hico_plugin.field.context_graph import ParentRule, cell_keys, dense_cell_ids, parent_edges
from hico_plugin.field.octree import OctreeGrid, visibility_fraction


@dataclass
class DensifyConfig(InstantiateConfig):
    """Anchor growing / pruning schedule and thresholds. Step values are optimizer steps for a run of
    ``FieldConfig.reference_steps`` steps and scale with the run's length."""

    enabled: bool = True
    """Grow and prune anchors during training."""
    start_step: int = 500
    """First step at which anchors are adjusted (CityGS-X: 500)."""
    interval: int = 100
    """Steps between adjustments (CityGS-X: 100)."""
    stop_step: int = 25_000
    """Last step of statistics and adjustments. CityGS-X keeps a fixed 50k-image horizon (so a 30k run
    densifies to its end); Octree-GS stops at 25k of 40k; we stop at 25k of the 30k reference run so the
    last anchors get trained."""
    grad_threshold: float = 2e-4
    """tau: mean NDC-space gradient norm above which an offset spawns an anchor (level 0)."""
    success_threshold: float = 0.8
    """An offset's gradient counts once it was seen in > interval x views/step x this x 0.5 views;
    an anchor is judged for pruning once seen in > interval x views/step x this views."""
    update_ratio: float = 0.2
    """Level l's threshold is tau x u^l with u = b^update_ratio; g >= tau_l x u grows one level finer."""
    extra_ratio: float = 0.25
    """eps_i is raised when the anchor's mean gradient >= tau_l x extra_ratio."""
    extra_up: float = 0.01
    """Increment of the extra level eps_i."""
    min_opacity: float = 0.005
    """Prune anchors whose mean summed child opacity per view is below this."""
    max_log_scale: float = 0.05
    """On every prune, the anchors' log scale factors s[3:6] are clamped to at most this."""
    keep_ancestors: bool = True
    """Keep the octree a tree for CLCA's trilinear lookup: after growing and pruning, an anchor none of
    whose candidate parents holds an anchor gets one back (a pruned one is kept, else a new anchor at
    its nearest parent grid point, with its feature), so no anchor loses its parent context. Used only
    when CLCA is on with the trilinear rule, unless keep_ancestors_without_context is set."""
    draw_ancestors: bool = False
    """Draw the ancestors the kept tree adds (revived and new parents) like any anchor. Off, they only
    lend their features to CLCA's lookup; drawn, they add coarse Gaussians off the surface, trading
    mesh quality for PSNR (benchmarks/RESULTS.md). An ancestor is drawn once growth asks for its cell."""
    max_anchors: int = 0
    """Budget of drawn anchors (0: none). Once growth would pass it, an adjustment adds only the new
    cells with the largest offset gradients, as many as fit after its pruning; pruning frees room. A
    fixed budget filled by score is Taming 3DGS's and gsplat's MCMC ``cap_max``: the step's cost stops
    rising with the anchors where the budget is reached."""
    max_anchors_per_seed: float = 0.0
    """The same budget as a multiple of the anchors the octree starts with (0: none; Taming 3DGS's
    "multiplier" mode): it follows the capture's size. With max_anchors too, the smaller counts."""
    keep_ancestors_without_context: bool = False
    """Keep the tree also where no trilinear CLCA lookup reads it (context kind none, or the paper's
    lookup): the anchors the tree adds, without the context; the control that tells the two apart in
    CLCA's ablation."""

    def budget(self, initial_anchors: int) -> int | None:
        """The drawn-anchor budget of a field that started with ``initial_anchors``; None: unbounded."""
        limits = [self.max_anchors] if self.max_anchors > 0 else []
        if self.max_anchors_per_seed > 0:
            limits.append(int(self.max_anchors_per_seed * initial_anchors))
        return min(limits) if limits else None

    def keeps_tree(self, context: Any) -> bool:
        """Whether densification keeps the octree a tree for the field whose context config is
        ``context``: where a nesting CLCA lookup reads it (``keep_ancestors``), or everywhere with
        ``keep_ancestors_without_context``."""
        read = context.kind != "none" and context.parent_rule.nests
        return self.keep_ancestors and (self.keep_ancestors_without_context or read)


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

