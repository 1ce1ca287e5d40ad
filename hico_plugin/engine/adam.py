"""Adam without ``torch.optim``: bit for bit ``torch.optim.Adam(fused=True)`` for the engine's options.

Every ``torch.optim`` optimizer imports ``torch._dynamo`` on its first call, which with the sympy and FX modules
it pulls in stays resident for the rest of a CPU run that never compiles. This covers one group, no weight decay,
no AMSGrad, through ``torch._fused_adam_`` (CPU and CUDA): one pass over the group without the parameter-sized
``denom`` of torch's single-tensor CPU default (equal to it up to float32 rounding). ``state_dict`` uses torch's
layout, so checkpoints move either way (memory and timings: benchmarks/RESULTS.md, "Figures behind the defaults").
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch
from torch import Tensor

from hico_plugin.row_sparse import sparse_rows

# The group entries torch.optim.Adam writes into a state_dict besides lr, betas and eps.
_TORCH_GROUP_DEFAULTS = {"weight_decay": 0, "amsgrad": False, "maximize": False, "foreach": None,
                         "capturable": False, "differentiable": False, "fused": True,
                         "decoupled_weight_decay": False}


class Adam:
    """``torch.optim.Adam(params, lr, betas, eps, fused=True)`` for one group: ``param_groups[0]["lr"]``
    may be changed between steps; ``state[param]`` holds ``step`` (a float32 scalar tensor on the
    parameter's device, where the fused kernel reads it), ``exp_avg`` and ``exp_avg_sq``, created at a
    parameter's first step with a gradient. A sparse COO gradient (rows of a dense parameter, e.g. from
    ``take_rows(sparse_grad=True)``) updates only its rows."""

    def __init__(self, params: Iterable[Tensor], lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8):
        self.param_groups = [{"params": list(params), "lr": lr, "betas": betas, "eps": eps}]
        self.state: dict[Tensor, dict[str, Tensor]] = {}

    @torch.no_grad()
    def step(self) -> None:
        group = self.param_groups[0]
        params = [param for param in group["params"] if param.grad is not None]
        if not params:
            return
        states = []
        for param in params:
            state = self.state.get(param)
            if not state:
                state = self.state[param] = {
                    "step": torch.tensor(0.0, dtype=torch.float32, device=param.device),
                    "exp_avg": torch.zeros_like(param, memory_format=torch.preserve_format),
                    "exp_avg_sq": torch.zeros_like(param, memory_format=torch.preserve_format)}
            states.append(state)
        steps = [state["step"] for state in states]
        torch._foreach_add_(steps, 1)
        dense = [i for i, param in enumerate(params) if not param.grad.is_sparse]
        if dense:
            self._fused([params[i] for i in dense], [params[i].grad for i in dense],
                        [states[i] for i in dense], [steps[i] for i in dense])
        for param, state, step in zip(params, states, steps):
            if param.grad.is_sparse:
                self._rows_step(param, state, step)

    def _fused(self, params: list[Tensor], grads: list[Tensor], states: list[dict[str, Tensor]],
               steps: list[Tensor]) -> None:
        group = self.param_groups[0]
        beta1, beta2 = group["betas"]
        torch._fused_adam_(params, grads, [state["exp_avg"] for state in states],
                           [state["exp_avg_sq"] for state in states], [], steps, lr=group["lr"], beta1=beta1,
                           beta2=beta2, weight_decay=0.0, eps=group["eps"], amsgrad=False, maximize=False)

    def _rows_step(self, param: Tensor, state: dict[str, Tensor], step: Tensor) -> None:
        """Adam on the rows a row-sparse gradient names only (Taming 3DGS's sparse Adam, gsplat's
        ``sparse_grad``): those rows and their moments get exactly the dense update, with the bias
        correction of the global step; every other row and its moments stay as they are."""
        rows, values = sparse_rows(param.grad)
        taken = [param.index_select(0, rows), state["exp_avg"].index_select(0, rows),
                 state["exp_avg_sq"].index_select(0, rows)]
        self._fused([taken[0]], [values.contiguous()], [{"exp_avg": taken[1], "exp_avg_sq": taken[2]}], [step])
        for target, updated in zip((param, state["exp_avg"], state["exp_avg_sq"]), taken):
            target.index_copy_(0, rows, updated)

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
        """Load a state_dict of this class or of ``torch.optim.Adam``, fused or not (moments cast to each
        parameter's dtype and device, as torch does; ``step`` to float32 on that device, as its fused
        Adam keeps it)."""
        groups = state_dict["param_groups"]
        params = self.param_groups[0]["params"]
        if len(groups) != 1 or len(groups[0]["params"]) != len(params):
            raise ValueError("loaded state dict has a different number of parameter groups or parameters")
        position = {index: param for index, param in zip(groups[0]["params"], params)}
        self.state = {}
        for index, saved in state_dict["state"].items():
            param = position[index]
            self.state[param] = {key: value.to(dtype=torch.float32 if key == "step" else param.dtype,
                                               device=param.device)
                                 for key, value in saved.items()}
        self.param_groups[0].update({k: groups[0][k] for k in ("lr", "betas", "eps") if k in groups[0]})
