"""Adam without ``torch.optim``.

Every ``torch.optim`` optimizer imports ``torch._dynamo`` on its first call (``Optimizer.step`` goes
through ``_use_grad_for_differentiable``, ``zero_grad`` and ``state_dict`` through
``torch._disable_dynamo``), which with the sympy and FX modules it pulls in holds about 70 MiB of
resident memory for the rest of a CPU run that never compiles anything (torch 2.13). This class does
what ``torch.optim.Adam`` does with the options the engine uses (one parameter group, no weight decay,
no AMSGrad), with the arithmetic of torch's single-tensor implementation (the CPU default) operation
for operation, so the parameters it produces are bit for bit the same, and ``state_dict`` /
``load_state_dict`` use torch's layout, so checkpoints move either way.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch
from torch import Tensor

# The group entries torch.optim.Adam writes into a state_dict besides lr, betas and eps.
_TORCH_GROUP_DEFAULTS = {"weight_decay": 0, "amsgrad": False, "maximize": False, "foreach": None,
                         "capturable": False, "differentiable": False, "fused": None,
                         "decoupled_weight_decay": False}


class Adam:
    """``torch.optim.Adam(params, lr, betas, eps)`` for one group: ``param_groups[0]["lr"]`` may be
    changed between steps; ``state[param]`` holds ``step`` (a float32 scalar tensor),
    ``exp_avg`` and ``exp_avg_sq``, created at a parameter's first step with a gradient."""

    def __init__(self, params: Iterable[Tensor], lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8):
        self.param_groups = [{"params": list(params), "lr": lr, "betas": betas, "eps": eps}]
        self.state: dict[Tensor, dict[str, Tensor]] = {}

    @torch.no_grad()
    def step(self) -> None:
        group = self.param_groups[0]
        lr, eps = group["lr"], group["eps"]
        beta1, beta2 = group["betas"]
        for param in group["params"]:
            grad = param.grad
            if grad is None:
                continue
            state = self.state.get(param)
            if not state:
                state = self.state[param] = {
                    "step": torch.tensor(0.0, dtype=torch.float32),
                    "exp_avg": torch.zeros_like(param, memory_format=torch.preserve_format),
                    "exp_avg_sq": torch.zeros_like(param, memory_format=torch.preserve_format)}
            exp_avg, exp_avg_sq = state["exp_avg"], state["exp_avg_sq"]
            state["step"] += 1
            step = state["step"].item()
            exp_avg.lerp_(grad, 1 - beta1)
            exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            step_size = lr / (1 - beta1**step)
            denom = (exp_avg_sq.sqrt() / (1 - beta2**step) ** 0.5).add_(eps)
            param.addcdiv_(exp_avg, denom, value=-step_size)

    def zero_grad(self) -> None:
        """Drop the gradients (torch's default, ``set_to_none=True``): the next backward allocates them."""
        for param in self.param_groups[0]["params"]:
            param.grad = None

    def state_dict(self) -> dict[str, Any]:
        """torch.optim's layout: state by the parameter's position, the group with positions."""
        group = self.param_groups[0]
        params = group["params"]
        state = {i: self.state[p] for i, p in enumerate(params) if p in self.state}
        packed = {**_TORCH_GROUP_DEFAULTS, **{k: v for k, v in group.items() if k != "params"}}
        return {"state": state, "param_groups": [{**packed, "params": list(range(len(params)))}]}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Load a state_dict of this class or of ``torch.optim.Adam`` (moments cast to each parameter's
        dtype and device, as torch does)."""
        groups = state_dict["param_groups"]
        params = self.param_groups[0]["params"]
        if len(groups) != 1 or len(groups[0]["params"]) != len(params):
            raise ValueError("loaded state dict has a different number of parameter groups or parameters")
        position = {index: param for index, param in zip(groups[0]["params"], params)}
        self.state = {}
        for index, saved in state_dict["state"].items():
            param = position[index]
            self.state[param] = {key: value if key == "step" else value.to(dtype=param.dtype, device=param.device)
                                 for key, value in saved.items()}
        self.param_groups[0].update({k: groups[0][k] for k in ("lr", "betas", "eps") if k in groups[0]})
