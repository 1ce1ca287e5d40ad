"""Cameras for tests: random COLMAP cameras of the models the loaders evaluate."""

from __future__ import annotations

import numpy as np

from hico_plugin.data.camera_model import Camera


def random_camera(rng: np.random.Generator, model: str, camera_id: int = 7) -> Camera:
    """A camera of ``model`` with a random size, focal lengths, principal point near the centre and
    distortion up to +-0.3 (k) and +-0.01 (p)."""
    width, height = (int(v) for v in rng.integers(64, 2500, 2))
    f = rng.uniform(0.4, 1.5) * max(width, height)
    cx, cy = width / 2 + rng.normal(0, 0.03 * width), height / 2 + rng.normal(0, 0.03 * height)
    k1, k2 = rng.uniform(-0.3, 0.3, 2)
    p1, p2 = rng.uniform(-0.01, 0.01, 2)
    params = {"SIMPLE_PINHOLE": [f, cx, cy], "PINHOLE": [f, f * rng.uniform(0.9, 1.1), cx, cy],
              "SIMPLE_RADIAL": [f, cx, cy, k1], "RADIAL": [f, cx, cy, k1, k2],
              "OPENCV": [f, f * rng.uniform(0.9, 1.1), cx, cy, k1, k2, p1, p2]}[model]
    return Camera(camera_id=camera_id, model=model, width=width, height=height, params=params)
