"""One optimizer step on this worker: the model's forward pass over its views, one all-reduce of the
step's scalars, backward, gradient averaging over workers, the optimizer step and the model's hooks."""

from __future__ import annotations

import torch

from hico_plugin.engine import distributed as dist_utils
from hico_plugin.engine.optimizers import Optimizers
from hico_plugin.engine.protocol import StepOutput, TrainableModel, TrainBatch


def reduce_step_scalars(output: StepOutput, device: torch.device, world_size: int) -> tuple[dict[str, float], bool]:
    """One all-reduce for the loss, the metrics (means over ranks; the metric names must be the same
    on every rank) and whether any rank's loss is non-finite.

    Returns (metrics, loss finite on every rank).
    """
    metric_names = sorted(output.metrics)
    values = [output.loss.detach().float().reshape(())]
    values += [torch.as_tensor(output.metrics[k], dtype=torch.float32).detach().reshape(-1).mean() for k in metric_names]
    nonfinite = (~torch.isfinite(output.loss.detach())).any().float().reshape(())
    vector = torch.stack([v.to(device) for v in values] + [nonfinite.to(device)])
    dist_utils.all_reduce_sum_(vector)
    vector = vector.cpu()
    means = (vector[:-1] / world_size).tolist()
    return dict(zip(["loss", *metric_names], means)), bool(vector[-1] == 0)


def optimizer_step(model: TrainableModel, optimizers: Optimizers, batch: TrainBatch, step: int,
                   device: torch.device, world_size: int) -> tuple[dict[str, float], bool]:
    """Train ``model`` on ``batch`` for step ``step`` (0-based). A loss that is non-finite on any
    rank skips the update everywhere. Returns (metrics with ``lr/<group>``, whether the step was taken)."""
    optimizers.zero_grad()
    output = model.train_step(batch, step)
    metrics, finite = reduce_step_scalars(output, device, world_size)
    if not finite:
        optimizers.zero_grad()
        return metrics, False
    output.loss.backward()
    model.after_backward(step, output)
    dist_utils.average_gradients_(optimizers.all_params())
    lrs = optimizers.step(step)
    model.after_optimizer_step(step, optimizers)
    metrics.update({f"lr/{name}": lr for name, lr in lrs.items()})
    return metrics, True
