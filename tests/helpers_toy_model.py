"""A toy model + dataset that exercise the engine's protocol (the engine's tests train it; the toy's
own checks are in engine/test_engine_toy_model.py).

The toy "renders" N coloured 2-D blobs, shifted by the camera's x/y translation, through a small
colour MLP. It has what the real model has that matters to the engine: two parameter groups, one of
which changes its row count when the model "densifies" (split the most
useful one in two halves), optionally row-sparse gradients of the blobs a view draws, densification statistics from per-view gradients reduced over workers, buffers in
the state dict, optional global-RNG use, and an optional NaN loss at chosen steps.
"""

from __future__ import annotations

import time
from pathlib import Path
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor, nn

from hico_plugin.cameras import Camera, Cameras
from hico_plugin.config import InstantiateConfig
from hico_plugin.engine import TrainerConfig
from hico_plugin.engine.distributed import all_reduce_sum_
from hico_plugin.engine.optimizers import Optimizers
from hico_plugin.engine.protocol import StepOutput, TrainBatch
from hico_plugin.engine.schedule import LRSchedule
from hico_plugin.field.gather import take_rows


def pixel_grid(height: int, width: int) -> Tensor:
    """[H, W, 2] pixel centres (x, y)."""
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    return torch.stack([xs, ys], dim=-1)


def render_blobs(features: Tensor, centers: Tensor, mlp: nn.Linear, camera: Camera, sigma: float) -> Tensor:
    """features [N, 3], centers [N, 2] -> image [H, W, 3] in (0, 1)."""
    shift = camera.viewmat[:2, 3] * camera.K[0, 0]
    grid = pixel_grid(camera.height, camera.width).to(centers)
    offsets = grid[:, :, None, :] - (centers + shift)[None, None]  # [H, W, N, 2]
    weights = torch.exp(-(offsets**2).sum(-1) / (2 * sigma**2))  # [H, W, N]
    return torch.sigmoid(mlp(weights @ features))


class ToyModel(nn.Module):
    def __init__(self, num_blobs: int, size: int, seed: int, densify_every: int, densify_until: int,
                 noise: float = 0.0, sigma: float = 2.0, sparse_rows: bool = False):
        super().__init__()
        generator = torch.Generator().manual_seed(seed)
        self.features = nn.Parameter(torch.randn(num_blobs, 3, generator=generator))
        self.centers = nn.Parameter(torch.rand(num_blobs, 2, generator=generator) * size)
        self.mlp = nn.Linear(3, 3)
        with torch.no_grad():
            self.mlp.weight.copy_(torch.eye(3) + 0.1 * torch.randn(3, 3, generator=generator))
            self.mlp.bias.zero_()
        self.register_buffer("grad_accum", torch.zeros(num_blobs))
        self.register_buffer("num_densified", torch.zeros((), dtype=torch.long))
        self.densify_every = densify_every
        self.densify_until = densify_until
        self.noise = noise
        self.sigma = sigma
        self.sparse_rows = sparse_rows
        self.nan_steps: set[int] = set()

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"blobs": [self.features, self.centers], "mlp": list(self.mlp.parameters())}

    def lr_schedules(self, max_steps: int) -> dict[str, LRSchedule]:
        return {
            "blobs": LRSchedule(0.2, 0.02, max_steps=max_steps),
            "mlp": LRSchedule(0.05, 0.005, max_steps=max_steps, warmup_steps=3),
        }

    def train_step(self, batch: TrainBatch, step: int) -> StepOutput:
        # One zero offset per view, like the rasterizer's means2d: its grad is a per-view statistic.
        view_offsets = [torch.zeros_like(self.centers, requires_grad=True) for _ in batch.cameras]
        preds = torch.stack([self._render(camera, offset, step) for camera, offset in zip(batch.cameras, view_offsets)])
        if self.noise:
            preds = preds + self.noise * torch.randn_like(preds)
        mse = ((preds - batch.images) ** 2).mean()
        loss = mse * float("nan") if step in self.nan_steps else mse
        psnr = -10 * torch.log10(mse.detach())
        return StepOutput(loss=loss, metrics={"psnr": psnr, "loss/mse": mse.detach()},
                          extras={"view_offsets": view_offsets, "batch_size": len(batch)})

    def _render(self, camera: Camera, offset: Tensor, step: int) -> Tensor:
        if not self.sparse_rows:
            return render_blobs(self.features, self.centers + offset, self.mlp, camera, self.sigma)
        # Each view draws every other blob (which half depends on the view and the step), through
        # gathers with row-sparse gradients, as the anchor field's rows are.
        rows = torch.arange((step + int(camera.viewmat[0, 3] > 0)) % 2, self.features.shape[0], 2)
        centers = take_rows(self.centers, rows, sparse_grad=True) + take_rows(offset, rows)
        return render_blobs(take_rows(self.features, rows, sparse_grad=True), centers, self.mlp, camera, self.sigma)

    def after_backward(self, step: int, output: StepOutput) -> None:
        # x batch size undoes the mean over the batch, so the statistic does not depend on how
        # the global batch is split over workers.
        per_view = torch.stack([o.grad.norm(dim=-1) for o in output.extras["view_offsets"]])
        increment = per_view.sum(0) * output.extras["batch_size"]
        self.grad_accum += all_reduce_sum_(increment)

    def after_optimizer_step(self, step: int, optimizers: Optimizers) -> None:
        if (step + 1) % self.densify_every or step >= self.densify_until:
            return
        # Split the blob with the largest statistic into two halves either side of it.
        best = int(self.grad_accum.argmax())
        kept = torch.cat([torch.arange(best), torch.arange(best + 1, self.features.shape[0])])
        with torch.no_grad():
            new_features = torch.cat([self.features[kept], 0.5 * self.features[best].expand(2, 3)])
            nudge = torch.tensor([[0.5, 0.0], [-0.5, 0.0]])
            new_centers = torch.cat([self.centers[kept], self.centers[best] + nudge])
        self.features = nn.Parameter(new_features)
        self.centers = nn.Parameter(new_centers)
        optimizers.resize_group("blobs", [self.features, self.centers], kept, 2)
        self.grad_accum = torch.zeros(new_features.shape[0])
        self.num_densified += 1

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        # Densification changes shapes: take the checkpoint's before loading values.
        num_blobs = state_dict["features"].shape[0]
        if num_blobs != self.features.shape[0]:
            self.features = nn.Parameter(torch.empty(num_blobs, 3))
            self.centers = nn.Parameter(torch.empty(num_blobs, 2))
            self.grad_accum = torch.empty(num_blobs)
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    @torch.no_grad()
    def eval_view(self, camera: Camera, image: Tensor, gt: dict[str, Tensor]) -> dict:
        start = time.perf_counter()
        pred = render_blobs(self.features, self.centers, self.mlp, camera, self.sigma)
        render_seconds = time.perf_counter() - start
        mse = ((pred - image) ** 2).mean()
        results = {"psnr": float(-10 * torch.log10(mse)), "render_seconds": render_seconds,
                   "lpips": None, "rgb": pred}
        if "depth" in gt:
            results["depth_abs_rel"] = float(((1.0 - gt["depth"]).abs() / gt["depth"]).mean())
        return results

    def stats(self) -> dict[str, float]:
        return {"num_anchors": float(self.features.shape[0]), "num_gaussians": float(2 * self.features.shape[0])}


class ToyDataset:
    """Views of a hidden toy model: every 4th view is a test view."""

    def __init__(self, num_views: int, size: int, seed: int, with_depth: bool = False):
        generator = torch.Generator().manual_seed(seed + 1)
        viewmats = torch.eye(4).repeat(num_views, 1, 1)
        viewmats[:, :2, 3] = (torch.rand(num_views, 2, generator=generator) - 0.5) * 0.2
        Ks = torch.tensor([[10.0, 0, size / 2], [0, 10.0, size / 2], [0, 0, 1]]).repeat(num_views, 1, 1)
        sizes = torch.full((num_views,), size, dtype=torch.long)
        self.cameras = Cameras(viewmats, Ks, sizes, sizes)
        self.train_indices = [i for i in range(num_views) if i % 4 != 3]
        self.test_indices = [i for i in range(num_views) if i % 4 == 3]
        truth = ToyModel(num_blobs=5, size=size, seed=seed + 2, densify_every=10**9, densify_until=0)
        with torch.no_grad():
            self._images = [
                (render_blobs(truth.features, truth.centers, truth.mlp, self.cameras[i], truth.sigma) * 255)
                .round().to(torch.uint8).numpy()
                for i in range(num_views)
            ]
        self.with_depth = with_depth

    def image(self, i: int) -> np.ndarray:
        return self._images[i]

    def gt_depth(self, i: int) -> Tensor | None:
        return torch.full((self.cameras[i].height, self.cameras[i].width, 1), 1.25) if self.with_depth else None


@dataclass
class ToyDataConfig(InstantiateConfig):
    num_views: int = 12
    size: int = 8
    seed: int = 0
    with_depth: bool = True

    def setup(self, **kwargs) -> ToyDataset:
        return ToyDataset(self.num_views, self.size, self.seed, self.with_depth)


@dataclass
class ToyModelConfig(InstantiateConfig):
    num_blobs: int = 6
    seed: int = 3
    densify_every: int = 5
    densify_until: int = 20
    noise: float = 0.0
    nan_steps: tuple[int, ...] = field(default_factory=tuple)
    sparse_rows: bool = False

    def setup(self, dataset: ToyDataset, **kwargs) -> ToyModel:
        model = ToyModel(self.num_blobs, dataset.cameras[0].width, self.seed, self.densify_every,
                         self.densify_until, self.noise, sparse_rows=self.sparse_rows)
        model.nan_steps = set(self.nan_steps)
        return model


def toy_config(tmp_path: Path, **overrides) -> TrainerConfig:
    values = dict(
        method_name="toy", experiment_name="toy-scene", output_dir=tmp_path / "run",
        data=ToyDataConfig(), model=ToyModelConfig(), max_steps=24, batch_size=2, seed=7,
        device="cpu", save_every=10, keep_checkpoints=2, log_every=1, progress="none", vis="none",
    )
    values.update(overrides)
    return TrainerConfig(**values)
