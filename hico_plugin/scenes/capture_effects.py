"""Image-formation effects a scene may declare. The generator runs exactly the enabled ones.

``multi_distance`` changes where cameras are placed and lives in each scene's camera layout; the
other effects act on rendered images here.
"""

from __future__ import annotations

import numpy as np

# Strengths, fixed so a scene's parameters hash means the same images across versions.
EXPOSURE_STOPS_STD = 0.35  # per-image exposure, std of log2 gain
WHITE_BALANCE_STD = 0.06  # per-image, per-channel std of log gain
NOISE_READ_STD = 0.008  # additive read noise (linear units)
NOISE_SHOT_SCALE = 0.015  # shot noise std = scale * sqrt(signal)

SKY_HORIZON = np.array([0.82, 0.87, 0.92])
SKY_ZENITH = np.array([0.32, 0.5, 0.78])


def exposure_gains(num_images: int, seed: int) -> np.ndarray:
    """Per-image RGB gains [C, 3]: a log-normal exposure times a small white-balance shift."""
    rng = np.random.default_rng([seed, 1])
    exposure = 2.0 ** rng.normal(0.0, EXPOSURE_STOPS_STD, (num_images, 1))
    balance = np.exp(rng.normal(0.0, WHITE_BALANCE_STD, (num_images, 3)))
    return exposure * balance


def apply_exposure(rgb: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """rgb [H, W, 3] linear, gain [3] -> rgb * gain."""
    return rgb * gain


def apply_sky(rgb: np.ndarray, hit: np.ndarray, dirs_world: np.ndarray) -> np.ndarray:
    """Fill pixels without a surface with a vertical gradient sky: rgb [H, W, 3], hit [H, W] bool,
    dirs_world [H, W, 3] unit ray directions (world z up)."""
    elevation = np.clip(dirs_world[..., 2], 0.0, 1.0) ** 0.6
    sky = SKY_HORIZON + (SKY_ZENITH - SKY_HORIZON) * elevation[..., None]
    return np.where(hit[..., None], rgb, sky)


def apply_sensor_noise(rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Shot + read noise on linear rgb [H, W, 3]."""
    std = NOISE_READ_STD + NOISE_SHOT_SCALE * np.sqrt(np.clip(rgb, 0.0, None))
    return rgb + rng.normal(0.0, 1.0, rgb.shape) * std
