"""Coarse-to-fine training images: the schedule, the downscaled batch and the trainer's use of it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from hico_plugin.cameras import Camera
from hico_plugin.engine.protocol import TrainBatch
from hico_plugin.engine.resolution import ResolutionSchedule, downscale_batch
from hico_plugin.errors import HicoError

from helpers_toy_model import ToyModel, ToyModelConfig, toy_config


def _camera(width: int = 64, height: int = 48) -> Camera:
    K = torch.tensor([[50.0, 0.0, width / 2], [0.0, 55.0, height / 2], [0.0, 0.0, 1.0]])
    viewmat = torch.eye(4)
    viewmat[:3, 3] = torch.tensor([0.1, -0.2, 2.0])
    return Camera(viewmat, K, width, height, index=3)


def _project(camera: Camera, point: torch.Tensor) -> torch.Tensor:
    cam = camera.viewmat[:3, :3] @ point + camera.viewmat[:3, 3]
    uvw = camera.K @ cam
    return uvw[:2] / uvw[2]


def test_schedule_rises_to_full_resolution_by_full_at_and_off_is_one():
    schedule = ResolutionSchedule(start_scale=0.25, full_at=0.5)
    scales = [schedule.scale(step, 1000, 4000) for step in range(0, 1001, 10)]
    assert scales[0] == 0.25
    assert all(b >= a for a, b in zip(scales, scales[1:]))
    assert schedule.scale(499, 1000, 4000) < 1.0 and schedule.scale(500, 1000, 4000) == 1.0 and scales[-1] == 1.0
    # Linear in pixels: half way to full_at holds about half the pixels the schedule adds.
    half = schedule.scale(250, 1000, 4000)
    assert abs(half**2 - (0.25**2 + 1.0) / 2) < 2 * (1 / 16)  # within the rounding to 1/16 of a side
    assert len(set(scales)) <= 16  # quantised: a handful of image sizes per run
    assert all(ResolutionSchedule().scale(step, 1000, 4000) == 1.0 for step in (0, 500, 999))


def test_ramp_power_spends_the_pixels_late_and_still_ends_at_full_size():
    linear, late = ResolutionSchedule(start_scale=0.25, full_at=1.0), ResolutionSchedule(
        start_scale=0.25, full_at=1.0, ramp_power=2.0)
    # Half way, the squared ramp has added a quarter of the pixels (side rounded down to 1/16).
    pixels = 0.25**2 + (1 - 0.25**2) * 0.5**2
    assert late.scale(500, 1000, 4000) == math.floor(pixels**0.5 * 16) / 16 == 0.5
    assert all(late.scale(step, 1000, 4000) <= linear.scale(step, 1000, 4000) for step in range(1001))
    assert late.scale(0, 1000, 4000) == 0.25 and late.scale(1000, 1000, 4000) == 1.0
    assert late.full_steps(0, 1000, 1000, 4000) < 0.85 * linear.full_steps(0, 1000, 1000, 4000)


def test_schedule_never_trains_below_min_long_side():
    schedule = ResolutionSchedule(start_scale=0.25, full_at=0.5, min_long_side=480)
    assert schedule.scale(0, 1000, 960) == 0.5  # starts at 480 px, not 240
    assert all(schedule.scale(step, 1000, 320) == 1.0 for step in (0, 100, 999))  # small photos: off
    assert schedule.scale(0, 1000, 1920) == 0.25


@pytest.mark.parametrize("field, value", [("start_scale", 0.0), ("start_scale", 1.5), ("full_at", 0.0), ("ramp_power", 0.0),
                                          ("min_long_side", -1)])
def test_schedule_out_of_range_names_the_field(field, value):
    with pytest.raises(HicoError, match=f"config.resolution.{field}"):
        ResolutionSchedule(**{field: value}).validate()
    with pytest.raises(HicoError, match=f"config.resolution.{field}"):
        toy_config(Path("/nonexistent"), resolution=ResolutionSchedule(**{field: value})).validate()


def test_downscaled_batch_averages_pixels_and_keeps_projection():
    generator = torch.Generator().manual_seed(0)
    images = torch.rand(2, 48, 64, 3, generator=generator)
    depth = torch.rand(2, 48, 64, 1, generator=generator) + 1.0
    mask = torch.rand(2, 48, 64, 1, generator=generator) > 0.3
    cameras = [_camera(), _camera()]
    batch = TrainBatch(cameras=cameras, images=images, indices=torch.tensor([3, 5]),
                       gt={"depth": depth, "mask": mask})
    half = downscale_batch(batch, 0.5)
    assert half.images.shape == (2, 24, 32, 3) and half.images.dtype == images.dtype
    # Area averaging: each output pixel is the mean of its 2x2 block (no aliasing).
    blocks = images.reshape(2, 24, 2, 32, 2, 3).mean(dim=(2, 4))
    torch.testing.assert_close(half.images, blocks)
    # Ground truth is sampled, not averaged: every value is one of the full-resolution values.
    assert half.gt["mask"].dtype == torch.bool and half.gt["mask"].shape == (2, 24, 32, 1)
    assert torch.isin(half.gt["depth"], depth).all()
    # The rescaled camera sees a point where the full one does, in its own pixels (x 0.5).
    point = torch.tensor([0.3, 0.2, 1.0])
    torch.testing.assert_close(_project(half.cameras[0], point), 0.5 * _project(cameras[0], point))
    assert (half.cameras[0].width, half.cameras[0].height, half.cameras[0].index) == (32, 24, 3)
    assert torch.equal(half.indices, batch.indices)
    assert downscale_batch(batch, 1.0) is batch


def test_a_fractional_downscale_averages_each_pixels_exact_footprint():
    """At 3/4 a 4x4 block of photo pixels becomes 3x3: the corner pixel's footprint covers one photo pixel
    whole and a third of three neighbours (weights 9, 3, 3, 1 over 16/9 of a pixel)."""
    images = torch.rand(1, 8, 8, 3, generator=torch.Generator().manual_seed(1))
    cameras = [_camera(8, 8)]
    small = downscale_batch(TrainBatch(cameras=cameras, images=images, indices=torch.tensor([0]), gt={}), 0.75)
    assert small.images.shape == (1, 6, 6, 3) and small.images.dtype == torch.float32
    corner = (9 * images[0, 0, 0] + 3 * images[0, 0, 1] + 3 * images[0, 1, 0] + images[0, 1, 1]) / 16
    torch.testing.assert_close(small.images[0, 0, 0], corner)
    torch.testing.assert_close(small.images.mean(), images.mean(), atol=1e-6, rtol=0)  # no light lost or added


class _SizeRecorder(ToyModel):
    def train_step(self, batch, step):
        self.sizes.append((step, tuple(batch.images.shape[1:3]), batch.cameras[0].width))
        return super().train_step(batch, step)


class _RecorderConfig(ToyModelConfig):
    def setup(self, dataset, **kwargs):
        model = super().setup(dataset, **kwargs)
        model.__class__ = _SizeRecorder
        model.sizes = []
        return model


def test_trainer_trains_coarse_first_and_evaluates_at_full_resolution(tmp_path):
    config = toy_config(tmp_path, model=_RecorderConfig(), max_steps=12, save_every=0,
                        resolution=ResolutionSchedule(start_scale=0.5, full_at=0.5, min_long_side=0))
    trainer = config.setup()
    result = trainer.train()
    sizes = trainer.model.sizes
    full = trainer.dataset.cameras[0].width
    assert sizes[0][2] == full // 2 and sizes[0][1][1] == full // 2  # images and cameras agree
    assert all(width == full for step, _, width in sizes if step >= 6)
    assert [width for _, _, width in sizes] == sorted(width for _, _, width in sizes)
    assert result.eval_results is not None and result.eval_results["psnr"] > 0
    logged = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    scales = {row["step"]: row.get("resolution_scale", 1.0) for row in logged if "loss" in row}
    assert scales[0] == 0.5 and scales[max(scales)] == 1.0
