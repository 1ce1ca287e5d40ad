"""What the engine asks of a model (``TrainableModel``) and a dataset (``TrainDataset``): structural protocols.

One step (``step`` counts optimizer steps from 0): ``output = model.train_step(batch, step)`` on B views (one
global batch drawn on every rank, then split; loss = MEAN over its images), ``output.loss.backward()``,
``model.after_backward(step, output)``, gradients averaged over ranks, ``optimizers.step(step)``,
``model.after_optimizer_step(step, optimizers)`` (may resize parameters); so P workers x batch b update as 1
worker x batch P*b.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from torch import Tensor, nn

from hico_plugin.cameras import Camera, Cameras
from hico_plugin.engine.schedule import LRSchedule

if TYPE_CHECKING:
    from hico_plugin.engine.optimizers import Optimizers


@dataclass
class TrainBatch:
    """The views one rank trains on in one step.

    cameras: B cameras (``camera.index`` is the dataset index)
    images:  [B, H, W, 3] float32 in [0, 1]
    indices: [B] long, dataset indices of the views
    gt:      optional per-view ground truth stacked over the batch where every view has it,
             e.g. ``{"depth": [B, H, W, 1], "normal": [B, H, W, 3], "mask": [B, H, W, 1]}``
    """

    cameras: list[Camera]
    images: Tensor
    indices: Tensor
    gt: dict[str, Tensor] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.cameras)


@dataclass
class StepOutput:
    """What ``train_step`` returns.

    loss:    scalar tensor with grad, the MEAN over the batch's images
    metrics: scalars to log / show (``"psnr"``, ``"loss/rgb"``, ...); tensors are detached + averaged
    images:  optional images for the logs, ``name -> [H, W, C]``
    extras:  anything ``after_backward`` needs (e.g. the rasterizer's means2d with its grad)
    """

    loss: Tensor
    metrics: dict[str, float | Tensor] = field(default_factory=dict)
    images: dict[str, Tensor] = field(default_factory=dict)
    extras: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class TrainableModel(Protocol):
    """A model the Trainer can drive (an ``nn.Module`` with these methods).

    ``state_dict`` / ``load_state_dict`` carry everything to resume exactly, densification accumulators and the
    current parameter shapes included (loading resizes a fresh model's parameters); the engine rebuilds the
    optimizers from ``param_groups()`` afterwards. Optional ``train_gt``: the keys of ``TrainBatch.gt`` that
    ``train_step`` reads (e.g. ``("mask",)``), the only ones decoded for training batches (default: every kind).
    """

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        """Trainable parameters by group name; each group gets its own Adam and LR schedule."""
        ...

    def lr_schedules(self, max_steps: int) -> dict[str, LRSchedule]:
        """One schedule per group of ``param_groups()`` for a run of ``max_steps`` optimizer steps."""
        ...

    def train_step(self, batch: TrainBatch, step: int) -> StepOutput:
        ...

    def after_backward(self, step: int, output: StepOutput) -> None:
        """Called after ``loss.backward()`` (before gradient averaging). Statistics that must agree
        across workers are reduced here with ``engine.distributed.all_reduce_sum_`` / ``_mean_``.
        Gradients of per-view tensors (e.g. means2d) carry the 1/len(batch) of the batch mean: scale
        them by ``len(batch)`` so a view's statistic does not depend on how the batch is split."""
        ...

    def after_optimizer_step(self, step: int, optimizers: "Optimizers") -> None:
        """Called after the update; may grow / prune through ``optimizers.resize_group``. It runs on
        every rank with identical inputs, so decisions are identical without communication."""
        ...

    def eval_view(self, camera: Camera, image: Tensor, gt: dict[str, Tensor]) -> dict[str, Any]:
        """Metrics of one test view: ``image`` [H, W, 3] float in [0, 1], ``gt`` as in TrainBatch
        (unbatched). Scalar values (float / 0-d tensor / None = unavailable) are averaged over views;
        ``"render_seconds"`` (the render alone) gives fps; other values (images) are ignored.
        Runs on rank 0 only: must not use collectives."""
        ...

    def stats(self) -> dict[str, float]:
        """Counters for the progress bar and logs, e.g. ``num_anchors``, ``num_gaussians``."""
        ...


@runtime_checkable
class TrainDataset(Protocol):
    """The dataset the engine reads (``hico_plugin.data.Dataset`` satisfies it).

    Optional methods, used when present: ``gt_depth(i) -> [H, W, 1] | None``,
    ``gt_normal(i) -> [H, W, 3] | None``, ``mask(i) -> [H, W, 1] | None``.
    """

    cameras: Cameras
    train_indices: list[int] | Tensor
    test_indices: list[int] | Tensor

    def image(self, i: int) -> Any:
        """uint8 [H, W, 3] (numpy array or tensor) of dataset view ``i``."""
        ...
