"""One Adam per named parameter group with its own LR schedule (nerfstudio style), resizable rows."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from hico_plugin.engine.adam import Adam
from hico_plugin.engine.schedule import LRSchedule
from hico_plugin.errors import HicoError

ADAM_EPS = 1e-15


@dataclass
class ParamGroupOptimizerConfig:
    """Adam learning-rate schedule of one parameter group (an entry of a model's ``optimizers``)."""

    lr_init: float = 1e-3
    """Learning rate at the start (after the warm-up); 0 freezes the group."""
    lr_final: float | None = None
    """Learning rate reached at the end of training by log-linear decay; None keeps lr_init."""
    warmup_steps: int = 0
    """Steps of linear warm-up from 0 to lr_init."""
    scale_by_extent: bool = False
    """Multiply both learning rates by the scene extent (for parameters in world units)."""

    def schedule(self, max_steps: int, extent: float = 1.0) -> LRSchedule:
        scale = extent if self.scale_by_extent else 1.0
        lr_final = None if self.lr_final is None else self.lr_final * scale
        return LRSchedule(self.lr_init * scale, lr_final, max_steps, self.warmup_steps)


class Optimizers:
    """Adam optimisers keyed by parameter-group name.

    The LR of every group is a pure function of the step (``LRSchedule.lr``), so the schedules carry
    no state of their own: a checkpoint's step restores them exactly.
    """

    def __init__(self, param_groups: dict[str, list[nn.Parameter]], schedules: dict[str, LRSchedule]):
        missing = sorted(set(param_groups) - set(schedules))
        if missing:
            raise HicoError(f"model.lr_schedules: no schedule for parameter group(s) {', '.join(missing)}")
        self.schedules = {name: schedules[name] for name in param_groups}
        self.optimizers: dict[str, Adam] = {
            name: Adam(list(params), lr=self.schedules[name].lr(0), eps=ADAM_EPS)
            for name, params in param_groups.items()
        }

    def __contains__(self, name: str) -> bool:
        return name in self.optimizers

    def params(self, name: str) -> list[nn.Parameter]:
        return self.optimizers[name].param_groups[0]["params"]

    def all_params(self) -> list[nn.Parameter]:
        """Every optimised parameter, in a fixed order (group insertion order)."""
        return [p for name in self.optimizers for p in self.params(name)]

    def set_lrs(self, step: int) -> dict[str, float]:
        """Apply every group's schedule for ``step``; returns ``name -> lr``."""
        lrs = {}
        for name, optimizer in self.optimizers.items():
            lrs[name] = self.schedules[name].lr(step)
            optimizer.param_groups[0]["lr"] = lrs[name]
        return lrs

    def step(self, step: int) -> dict[str, float]:
        """Set the LRs for ``step`` and take one Adam step in every group."""
        lrs = self.set_lrs(step)
        for optimizer in self.optimizers.values():
            optimizer.step()
        return lrs

    def zero_grad(self) -> None:
        for optimizer in self.optimizers.values():
            optimizer.zero_grad()

    def release_state(self) -> None:
        """Drop every group's Adam moments (twice the parameters' memory). Only for a run that will
        take no further step: a later step would restart the moments from zero."""
        for optimizer in self.optimizers.values():
            optimizer.state.clear()

    def resize_group(
        self, name: str, new_params: list[nn.Parameter], kept_rows: Tensor, num_new: int
    ) -> None:
        """Swap the parameters of group ``name`` for resized ones and carry their Adam state.

        new_params: the group's new parameters, in the order of ``params(name)``; each has
                    ``len(kept_rows) + num_new`` rows: ``old[kept_rows]`` followed by ``num_new`` new ones
        kept_rows:  [R] long, rows of the old parameters that survive (any order, repeats allowed)
        Adam's ``exp_avg`` / ``exp_avg_sq`` follow the rows (kept rows carried, new rows zero); the
        step count is kept.
        """
        optimizer = self.optimizers[name]
        group = optimizer.param_groups[0]
        old_params = group["params"]
        if len(new_params) != len(old_params):
            raise ValueError(f"resize_group('{name}'): {len(new_params)} new params for {len(old_params)}")
        kept_rows = kept_rows.to(dtype=torch.long)
        for i, (old, new) in enumerate(zip(old_params, new_params)):
            expected = (kept_rows.numel() + num_new, *old.shape[1:])
            if tuple(new.shape) != expected:
                raise ValueError(
                    f"resize_group('{name}') param {i}: shape {tuple(new.shape)}, expected {expected}"
                )
            state = optimizer.state.pop(old, None)
            if state:
                for key in ("exp_avg", "exp_avg_sq"):
                    moment = state[key]
                    kept = moment[kept_rows.to(moment.device)]
                    state[key] = torch.cat([kept, kept.new_zeros((num_new, *kept.shape[1:]))])
                optimizer.state[new] = state
        group["params"] = list(new_params)

    def state_dict(self) -> dict[str, Any]:
        return {name: optimizer.state_dict() for name, optimizer in self.optimizers.items()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if set(state) != set(self.optimizers):
            raise HicoError(
                f"checkpoint optimizers hold groups {sorted(state)}, the model has {sorted(self.optimizers)}"
            )
        for name, optimizer in self.optimizers.items():
            optimizer.load_state_dict(state[name])
