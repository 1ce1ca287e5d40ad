"""``octree``: Octree-GS's and CityGS-X's level-aware densification, with a budget and the kept tree as options.

Statistics per anchor and per offset (summed child opacity, NDC gradient norms, views) gathered after each
backward; every ``interval`` steps in the window, offsets whose mean gradient passes the level's threshold
grow anchors (``rules.grow_anchors``), rarely opaque anchors are pruned, and the extra level eps rises
where gradients stay high (``rules.extra_level_increment``).
"""

from __future__ import annotations

import math
from typing import Any, Callable

import torch
from torch import Tensor

from hico_plugin.field.context_graph import cell_keys
from hico_plugin.strategy.base import STRATEGIES, DensifyConfig, Strategy
from hico_plugin.strategy.rules import (GrownAnchors, close_ancestors, extra_level_increment, grow_anchors,
                                        offset_gradients, prune_decision, rows_in)

# Statistics; each has a ``<name>_synced`` twin holding its value at the last sync across workers.
STAT_BUFFERS = ("opacity_accum", "anchor_denom", "offset_grad_accum", "offset_denom", "stat_views")
# The per-anchor ones, whose rows follow the field's anchors.
ROW_BUFFERS = tuple(name + suffix for suffix in ("", "_synced") for name in STAT_BUFFERS if name != "stat_views")
BUFFERS = (*STAT_BUFFERS, *(f"{name}_synced" for name in STAT_BUFFERS), "last_adjust_step")
"""Every buffer of the strategy (checkpoints from before it was one held them in the field)."""


@STRATEGIES.register("octree")
class OctreeStrategy(Strategy):
    """Buffers: opacity_accum [N], anchor_denom [N], offset_grad_accum [N,K], offset_denom [N,K], stat_views,
    last_adjust_step, and their ``_synced`` twins; ``initial_anchors``, the base of a relative budget."""

    def __init__(self, config: DensifyConfig, field: Any, schedule_scale: float = 1.0):
        super().__init__(config, field, schedule_scale)
        num, k = field.num_anchors, field.offsets.shape[1]
        self.register_buffer("opacity_accum", torch.zeros(num))
        self.register_buffer("anchor_denom", torch.zeros(num))
        self.register_buffer("offset_grad_accum", torch.zeros(num, k))
        self.register_buffer("offset_denom", torch.zeros(num, k))
        self.register_buffer("stat_views", torch.zeros((), dtype=torch.long))
        self.register_buffer("last_adjust_step", torch.zeros((), dtype=torch.long))
        for name in STAT_BUFFERS:
            self.register_buffer(f"{name}_synced", getattr(self, name).clone())
        self.keeps_ancestors = config.keeps_tree(field.config.context)
        self.last_adjustment: dict[str, int] = {}
        # The octree's own anchors, the base of a relative anchor budget. A resumed run rebuilds the
        # same octree from the same data before loading its checkpoint, so this stays the run's.
        self.initial_anchors = num

    @torch.no_grad()
    def step_post_backward(self, field: Any, gaussians: Any, means2d_grad: Tensor, radii: Tensor, camera: Any,
                           step: int) -> None:
        """Add one view (until stop_step). means2d_grad [M,2]: dL/dmeans2d in pixels of this view's loss
        (a batch mean's times the batch size), converted to NDC units, the scale of grad_threshold;
        radii [M] (or [M,2]): Gaussians of radius 0 were not drawn."""
        if not self.config.enabled or step > self.stop:
            return
        ids = gaussians.visible_ids
        opacity_sums = gaussians.raw_opacities.clamp_min(0).sum(1).to(self.opacity_accum)
        self.opacity_accum.index_add_(0, ids, opacity_sums)
        self.anchor_denom.index_add_(0, ids, torch.ones_like(ids, dtype=self.anchor_denom.dtype))
        drawn = radii > 0 if radii.dim() == 1 else (radii > 0).any(-1)  # a view may decode nothing
        ndc = means2d_grad.detach() * means2d_grad.new_tensor([camera.width / 2, camera.height / 2])
        grad_norm = ndc.norm(dim=-1)[drawn].to(self.offset_grad_accum)
        offset_rows = (gaussians.anchor_ids * self.offset_grad_accum.shape[1] + gaussians.child_ids)[drawn]
        self.offset_grad_accum.view(-1).index_add_(0, offset_rows, grad_norm)
        self.offset_denom.view(-1).index_add_(0, offset_rows, torch.ones_like(grad_norm))
        self.stat_views += 1

    @torch.no_grad()
    def sync(self, all_reduce_sum: Callable[[Tensor], Any]) -> None:
        """Only the increments since the last sync are reduced: reducing the whole accumulators would
        count the part carried over from earlier intervals (identical on every worker) once per worker."""
        for name in STAT_BUFFERS:
            total, synced = getattr(self, name), getattr(self, f"{name}_synced")
            increment = total - synced
            all_reduce_sum(increment)
            total.copy_(synced + increment)
            synced.copy_(total)

    @torch.no_grad()
    def step_post_update(self, field: Any, step: int) -> dict[str, tuple[Tensor, int]]:
        if not self.is_adjust_step(step):
            return {}
        cfg = self.config
        steps_elapsed = max(1, step - int(self.last_adjust_step))
        check_views = self.interval * float(self.stat_views) / steps_elapsed * cfg.success_threshold
        grads, eligible = offset_gradients(self.offset_grad_accum, self.offset_denom, 0.5 * check_views)
        allow_finer = field.progressive_done(step)
        if allow_finer:
            field.extra_level += extra_level_increment(grads, eligible, field.levels, field.grid, cfg)
        threshold = field.config.octree.visible_threshold
        hides = self.keeps_ancestors and not cfg.draw_ancestors
        prune, judged = prune_decision(self.opacity_accum, self.anchor_denom, cfg.min_opacity, check_views)
        budget = cfg.budget(self.initial_anchors)
        room = None if budget is None else budget - int((field.drawn & ~prune).sum())
        grown = grow_anchors(field.anchors.detach(), field.levels, field.anchor_features.detach(),
                             field.offsets.detach(), field.log_scaling.detach(), grads, field.grid, cfg,
                             field.train_camera_centers, max(threshold, 0.0), allow_finer,
                             blocks=field.drawn if hides else None, limit=room)
        if hides:
            grown = draw_hidden_ancestors(field, grown)
        self.offset_grad_accum[eligible] = 0
        self.offset_denom[eligible] = 0
        new_drawn = torch.ones(grown.positions.shape[0], dtype=torch.bool, device=field.drawn.device)
        if self.keeps_ancestors:
            # an ancestor no kept anchor needs goes; close_ancestors revives the needed ones
            before = ~prune & field.drawn if hides else ~prune
            keep, grown = close_ancestors(field.anchors.detach(), field.levels, field.anchor_features.detach(),
                                          before, grown, field.grid)
            prune = ~keep
            added = grown.positions.shape[0] - len(new_drawn)  # the new parents, appended to grown
            new_drawn = torch.cat([new_drawn, new_drawn.new_full((added,), not hides)])
            if hides:
                field.drawn &= before  # the revived anchors: context only
        self.opacity_accum[judged] = 0
        self.anchor_denom[judged] = 0
        self.stat_views.zero_()
        self.last_adjust_step.fill_(step)

        num_new = grown.positions.shape[0]
        self.last_adjustment = {"grown": num_new, "pruned": int(prune.sum())}
        for level in range(field.grid.num_levels):
            self.last_adjustment[f"grown_level_{level}"] = int((grown.levels == level).sum())
        if num_new == 0 and not prune.any():
            self._mark_synced()
            return {}
        kept_rows = (~prune).nonzero().squeeze(1)
        resized = field.resize(kept_rows, grown.positions, grown.levels, grown.features, new_drawn)
        self._resize(kept_rows, num_new)
        self._mark_synced()
        if prune.any():
            field.log_scaling[:, 3:].clamp_(max=cfg.max_log_scale)
        return resized

    @torch.no_grad()
    def keep(self, rows: Tensor) -> None:
        self._resize(rows, 0)
        self._mark_synced()

    def _resize(self, kept_rows: Tensor, num_new: int) -> None:
        """Every per-anchor statistic becomes ``cat([old[kept_rows], num_new zero rows])``."""
        for name in ROW_BUFFERS:
            old = getattr(self, name)
            setattr(self, name, torch.cat([old[kept_rows], old.new_zeros(num_new, *old.shape[1:])]))

    def _mark_synced(self) -> None:
        """After an adjustment every worker holds the same statistics: the next sync starts here."""
        for name in STAT_BUFFERS:
            getattr(self, f"{name}_synced").copy_(getattr(self, name))

    def bytes_per_anchor(self) -> int:
        return sum(math.prod(getattr(self, name).shape[1:]) * getattr(self, name).element_size()
                   for name in ROW_BUFFERS)

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys,
                              unexpected_keys, error_msgs):
        # A checkpoint holds statistics for as many anchors as its field (densification): take its shapes.
        for name, tensor in self._buffers.items():
            saved = state_dict.get(prefix + name)
            if tensor is not None and saved is not None and saved.shape != tensor.shape:
                setattr(self, name, tensor.new_empty(saved.shape))
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys,
                                      unexpected_keys, error_msgs)


def draw_hidden_ancestors(field: Any, grown: GrownAnchors) -> GrownAnchors:
    """Growth asks for an anchor where an ancestor kept for context sits: draw that ancestor (it keeps its
    training) instead of adding a second anchor to its cell; returns the rest of ``grown``."""
    hidden = (~field.drawn).nonzero().squeeze(1)
    if len(hidden) == 0 or grown.positions.shape[0] == 0:
        return grown
    hidden_keys = cell_keys(field.anchors.detach()[hidden], field.levels[hidden], field.grid)
    grown_keys = cell_keys(grown.positions, grown.levels, field.grid)
    field.drawn[hidden[rows_in(hidden_keys, grown_keys)]] = True
    fresh = ~rows_in(grown_keys, hidden_keys)
    return GrownAnchors(grown.positions[fresh], grown.levels[fresh], grown.features[fresh])
