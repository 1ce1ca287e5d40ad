"""Camera placement for the built-in scenes: look-at poses on orbits (world z up, OpenCV camera axes)."""

from __future__ import annotations

import numpy as np


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World->camera 4x4 (OpenCV: x right, y down, z forward) for cameras at ``eye`` [C, 3] looking at
    ``target`` [C, 3] with ``up`` ([3] or [C, 3], world +z by default; not along the view) towards the
    image's top. Returns [C, 4, 4]."""
    forward = target - eye
    forward /= np.linalg.norm(forward, axis=-1, keepdims=True)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward], axis=-2)  # rows: camera axes in world coords
    viewmats = np.zeros((len(eye), 4, 4))
    viewmats[:, :3, :3] = rotation
    viewmats[:, :3, 3] = -np.einsum("cij,cj->ci", rotation, eye)
    viewmats[:, 3, 3] = 1.0
    return viewmats


def intrinsics(width: int, height: int, fov_x_deg: float) -> np.ndarray:
    """Pinhole K [3, 3] with square pixels and the principal point at the image centre."""
    focal = 0.5 * width / np.tan(np.radians(fov_x_deg) / 2)
    return np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


def orbit_rings(
    num_views: int,
    radii: list[float],
    heights: list[float],
    target: np.ndarray,
    target_jitter: float,
    seed: int,
) -> np.ndarray:
    """``num_views`` cameras split evenly over rings (radius, height) around ``target`` [3]; each
    ring starts at a different azimuth and every camera aims at a jittered point near ``target``
    so views overlap without all sharing one centre. Returns viewmats [num_views, 4, 4]."""
    rng = np.random.default_rng([seed, 2])
    ring = np.arange(num_views) % len(radii)
    order = np.arange(num_views) // len(radii)
    per_ring = np.bincount(ring, minlength=len(radii))
    azimuth = 2 * np.pi * (order / per_ring[ring] + ring / (len(radii) * per_ring[ring] + 1) + 0.13 * ring)
    azimuth += rng.uniform(-0.3, 0.3, num_views) * 2 * np.pi / per_ring[ring]
    radius = np.asarray(radii)[ring] * rng.uniform(0.92, 1.08, num_views)
    height = np.asarray(heights)[ring] * rng.uniform(0.92, 1.08, num_views)
    eye = np.stack([radius * np.cos(azimuth), radius * np.sin(azimuth), height], 1) + target * [1, 1, 0]
    aim = target + rng.normal(0.0, 1.0, (num_views, 3)) * target_jitter * [1, 1, 0.3]
    return look_at(eye, aim)
