"""Seed points for formats that carry none (transforms.json without a PLY, Mega-NeRF).

One decision for every such format: triangulate from the known poses (``data/triangulate.py``) or,
when that is switched off or too few points triangulate, draw random points in the box around the
cameras with a warning.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hico_plugin.data.camera_model import Camera, camera_centres
from hico_plugin.data.triangulate import MIN_POINTS, triangulate_known_poses


def no_points() -> tuple[np.ndarray, np.ndarray]:
    """Empty [0, 3] float64 points and [0, 3] uint8 colours."""
    return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)


def random_points(viewmats: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """[count, 3] float64 points uniform in the box around the camera centres (3DGS's fallback) and
    their grey [count, 3] uint8 colours; seeded, so a dataset always loads to the same points."""
    centres = camera_centres(viewmats)
    low, high = centres.min(axis=0), centres.max(axis=0)
    middle, half = (low + high) / 2, np.maximum((high - low) / 2, 1e-3)
    rng = np.random.default_rng(0)
    points = middle + rng.uniform(-1.0, 1.0, size=(count, 3)) * half
    return points, np.full((count, 3), 128, dtype=np.uint8)


def random_seed_points(viewmats: np.ndarray, count: int, source: str, reason: str,
                       notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """``random_points`` with the warning (naming ``source`` and why) appended to ``notes``."""
    # Training then has to grow the geometry from scratch, which costs quality on real captures.
    notes.append(f"warning: {source} has no seed points and {reason}; seeding with {count} random "
                 "points (run hico-process for a COLMAP model with points)")
    return random_points(viewmats, count)


def seed_points(data_dir: Path, names: list[str], camera_ids: list[int], cameras: dict[int, Camera],
                viewmats: np.ndarray, source: str, triangulate: bool, random_count: int,
                notes: list[str], long_side: int) -> tuple[np.ndarray, np.ndarray]:
    """Seed points of a posed image set without a point cloud: triangulated from the known poses
    (``names`` are image paths relative to ``data_dir``) with the photos read at ``long_side`` pixels,
    the size they are trained at, else ``random_count`` random points; the warning for the fallback is
    appended to ``notes``. ``source`` names the dataset file in it."""
    reason = "triangulation is off (--no-triangulate)"
    if triangulate:
        points, colors = triangulate_known_poses(data_dir, names, camera_ids, cameras, viewmats, long_side)
        if len(points) >= MIN_POINTS:
            notes.append(f"{source}: no seed points in the dataset; triangulated {len(points)} from the known poses")
            return points, colors
        reason = f"only {len(points)} points triangulated from the known poses (expected {MIN_POINTS}+)"
    return random_seed_points(viewmats, random_count, source, reason, notes)
