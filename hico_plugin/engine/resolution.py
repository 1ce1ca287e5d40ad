"""Coarse-to-fine training images: a step's views downscaled by a factor that rises to 1.

A resolution schedule (DashGaussian, Chen et al., CVPR 2025) trains on low-resolution images while the
model can only represent coarse detail, and on full-resolution images once it can: the early steps
cost fewer pixels (rasterizing, the losses and their backward pass all scale with pixels) and the
model's result is judged at full resolution as before. Evaluation, the viewer and exports never see
the schedule; it only changes the batches the engine hands to ``train_step``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from hico_plugin.engine.protocol import TrainBatch
from hico_plugin.errors import HicoError

# Scales are rounded to this step so a run uses a handful of image sizes, not one per step.
_SCALE_QUANTUM = 1 / 16

FIXED_STEP_SHARE = 0.2
"""Share of a full-size step's time that does not shrink with the image (decoding the anchors, CLCA,
projection, the optimizer): a step at scale s costs about FIXED_STEP_SHARE + (1 - FIXED_STEP_SHARE) s^2
full-size steps (the share measured on instant-ngp's fox: benchmarks/RESULTS.md)."""


@dataclass
class ResolutionSchedule:
    """Training image resolution as a function of the step (evaluation is always at full resolution)."""

    start_scale: float = 1.0
    """Image scale (side length, fraction of full) of the first step; 1.0 turns the schedule off."""
    full_at: float = 0.5
    """Fraction of max_steps by which the scale has risen to 1."""
    ramp_power: float = 1.0
    """How the pixels per view rise to full_at: in proportion to the run's progress to the power
    ramp_power. 1 adds the same pixels every stretch of steps (DashGaussian's interpolation between its
    levels); 2 keeps the images small longer and spends the run's pixels in its last stretch."""
    min_long_side: int = 480
    """Never train on images whose long side is under this many pixels: a schedule that would go
    lower starts at the scale that gives this size instead, and photos this small or smaller train
    at full size throughout (there, the few pixels saved cost more accuracy than they save time)."""

    def validate(self) -> None:
        if not 0.0 < self.start_scale <= 1.0:
            raise HicoError(f"config.resolution.start_scale: expected in (0, 1], got {self.start_scale}")
        if not 0.0 < self.full_at <= 1.0:
            raise HicoError(f"config.resolution.full_at: expected in (0, 1], got {self.full_at}")
        if self.ramp_power <= 0.0:
            raise HicoError(f"config.resolution.ramp_power: expected > 0, got {self.ramp_power}")
        if self.min_long_side < 0:
            raise HicoError(f"config.resolution.min_long_side: expected >= 0, got {self.min_long_side}")

    def scale(self, step: int, max_steps: int, long_side: int) -> float:
        """Side-length scale of the images of ``step`` (0-based) in a run of ``max_steps`` whose
        photos have a long side of ``long_side`` pixels."""
        start = max(self.start_scale, min(1.0, self.min_long_side / max(1, long_side)))
        if start >= 1.0:
            return 1.0
        progress = min(1.0, step / max(1.0, self.full_at * max_steps))
        pixels = start**2 + (1.0 - start**2) * progress**self.ramp_power
        # Rounded down, so full resolution starts exactly at full_at (1e-9: 0.25 stays 4 quanta).
        return min(1.0, math.floor(pixels**0.5 / _SCALE_QUANTUM + 1e-9) * _SCALE_QUANTUM)

    def full_steps(self, start: int, stop: int, max_steps: int, long_side: int) -> float:
        """Steps start..stop-1 counted in full-resolution steps (each weighs the fixed share of a step
        plus the rest times its scale squared, the share of the pixels it draws), so the time left
        is this times the time of a full-resolution step."""
        return sum(FIXED_STEP_SHARE + (1.0 - FIXED_STEP_SHARE) * self.scale(step, max_steps, long_side) ** 2
                   for step in range(start, stop))


def downscale_batch(batch: TrainBatch, scale: float) -> TrainBatch:
    """``batch`` at ``scale`` times its resolution: images area-averaged (no aliasing), masks and
    ground-truth depth / normals sampled at the nearest pixel (averaging would invent depths across
    edges), cameras' intrinsics rescaled to the new size (``Camera.scaled``)."""
    if scale >= 1.0:
        return batch
    cameras = [camera.scaled(scale) for camera in batch.cameras]
    size = (cameras[0].height, cameras[0].width)
    images = _resize(batch.images, size, "area")
    gt = {key: _resize(value, size, "nearest-exact") for key, value in batch.gt.items()}
    return dataclasses.replace(batch, cameras=cameras, images=images, gt=gt)


def _resize(images: Tensor, size: tuple[int, int], mode: str) -> Tensor:
    """[B, H, W, C] (any dtype) -> [B, h, w, C] of the same dtype."""
    if mode == "area" and images.device.type == "cpu" and images.dtype == torch.float32:
        # OpenCV's INTER_AREA averages each output pixel's exact footprint (fractional weights at its
        # edges), where torch's area mode (adaptive pooling) rounds footprints out to whole pixels; and
        # it is several times faster.
        return torch.from_numpy(np.stack([
            cv2.resize(image.numpy(), (size[1], size[0]), interpolation=cv2.INTER_AREA).reshape(*size, -1)
            for image in images.contiguous()]))
    channels_first = images.permute(0, 3, 1, 2)
    resized = F.interpolate(channels_first.float(), size=size, mode=mode)
    if images.dtype == torch.bool:
        resized = resized > 0.5
    return resized.to(images.dtype).permute(0, 2, 3, 1).contiguous()
