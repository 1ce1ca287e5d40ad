"""Learning-rate schedules: each parameter group's LR as a pure function of the optimizer step."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LRSchedule:
    """Learning rate of one parameter group as a pure function of the optimizer step.

    Linear warmup from ``lr_pre_warmup`` to ``lr_init`` over ``warmup_steps``, then log-linear
    (exponential) interpolation from ``lr_init`` to ``lr_final`` over the following
    ``max_steps - warmup_steps`` steps, then held at ``lr_final``. ``lr_final=None`` keeps ``lr_init``.
    ``lr_init=0`` freezes the group (e.g. anchor positions in Octree-GS).
    """

    lr_init: float
    lr_final: float | None = None
    max_steps: int = 30_000
    warmup_steps: int = 0
    lr_pre_warmup: float = 0.0

    def lr(self, step: int) -> float:
        if self.warmup_steps > 0 and step < self.warmup_steps:
            return self.lr_pre_warmup + (self.lr_init - self.lr_pre_warmup) * step / self.warmup_steps
        if self.lr_final is None or self.lr_init == 0.0 or self.lr_final == self.lr_init:
            return self.lr_init
        if self.lr_final <= 0.0:
            raise ValueError(f"lr_final must be > 0 for log-linear decay, got {self.lr_final}")
        decay_steps = max(1, self.max_steps - self.warmup_steps)
        progress = min(max((step - self.warmup_steps) / decay_steps, 0.0), 1.0)
        return self.lr_init ** (1.0 - progress) * self.lr_final**progress
