"""Densification as a strategy (gsplat's ``Strategy``): how the anchors grow and shrink while training.

A strategy is an ``nn.Module`` beside the field (its statistics are buffers, so checkpoints carry them) that
the model calls at two points of a step: ``step_post_backward`` (gather statistics from the view's
gradients) and ``step_post_update`` (after the optimizer: grow and prune, editing the field through
``AnchorField.resize``). A strategy is one file registering its class in ``STRATEGIES``; the config
names it (``--model.field.densify.strategy``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from torch import Tensor, nn

from hico_plugin.config import InstantiateConfig
from hico_plugin.registry import Registry

STRATEGIES: Registry[type["Strategy"]] = Registry("densification strategy")
"""Strategy classes by name; ``DensifyConfig.setup`` builds the one its ``strategy`` names."""


@dataclass
class DensifyConfig(InstantiateConfig):
    """Anchor growing / pruning schedule and thresholds. Step values are optimizer steps for a run of
    ``FieldConfig.reference_steps`` steps and scale with the run's length."""

    enabled: bool = True
    """Grow and prune anchors during training."""
    strategy: str = "octree"
    """The densification strategy, by registered name (``STRATEGIES``; octree: Octree-GS's and
    CityGS-X's level-aware rule, with the budget and the kept tree below as its options)."""
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

    def setup(self, field: Any = None, schedule_scale: float = 1.0, **kwargs: Any) -> "Strategy":
        """The strategy named ``strategy`` for ``field``, its step schedule scaled by ``schedule_scale``."""
        return STRATEGIES.get(self.strategy)(self, field, schedule_scale)

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


class Strategy(nn.Module):
    """What every strategy provides; the step schedule (start, interval, stop) is the config's, in steps
    of the reference run, scaled by ``set_schedule_scale``."""

    def __init__(self, config: DensifyConfig, field: Any, schedule_scale: float = 1.0):
        super().__init__()
        self.config = config
        self.set_schedule_scale(schedule_scale)

    def set_schedule_scale(self, scale: float) -> None:
        """Scale the step schedule by ``scale`` (a run's length / ``FieldConfig.reference_steps``)."""
        self.start = int(round(self.config.start_step * scale))
        self.interval = max(1, int(round(self.config.interval * scale)))
        self.stop = int(round(self.config.stop_step * scale))

    def is_adjust_step(self, step: int) -> bool:
        """Whether ``step_post_update`` of ``step`` may change the anchors (every worker agrees)."""
        return self.config.enabled and self.start < step <= self.stop and step % self.interval == 0

    def step_post_backward(self, field: Any, gaussians: Any, means2d_grad: Tensor, radii: Tensor, camera: Any,
                           step: int) -> None:
        """One view's contribution to the statistics, after the backward pass."""
        raise NotImplementedError

    def sync(self, all_reduce_sum: Callable[[Tensor], Any]) -> None:
        """Sum the statistics over the workers of a multi-process run (before an adjustment)."""
        raise NotImplementedError

    def step_post_update(self, field: Any, step: int) -> dict[str, tuple[Tensor, int]]:
        """After the optimizer step: grow and prune; {group: (kept_rows [R] long, num_new)} per resized
        parameter group (``Optimizers.resize_group``'s contract), or {} when no shape changed."""
        raise NotImplementedError

    def keep(self, rows: Tensor) -> None:
        """The field kept only its anchors ``rows`` [R] long: keep the same rows of the statistics."""
        raise NotImplementedError

    def bytes_per_anchor(self) -> int:
        """Bytes of strategy state each anchor holds."""
        return 0
