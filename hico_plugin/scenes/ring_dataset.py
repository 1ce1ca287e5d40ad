"""A small synthetic COLMAP dataset: random images seen from a ring of cameras, random points. For
trying the loaders and what they refuse (the test suite, benchmarks/bad_input_table.py); the
built-in scenes (``generate_scene``) are the ones with content and ground truth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap

WIDTH, HEIGHT = 40, 30


def look_at(centre: np.ndarray, target: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """[3, 4] cam_from_world of a camera at ``centre`` looking at ``target`` (OpenCV axes, z up)."""
    forward = np.asarray(target) - centre
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    return np.concatenate([rotation, -rotation @ centre[:, None]], axis=1)


def write_ring_dataset(
    root: Path,
    *,
    model: str = "PINHOLE",
    params: list[float] | None = None,
    num_images: int = 6,
    size: tuple[int, int] = (WIDTH, HEIGHT),
    text: bool = False,
    num_points: int = 40,
    write_images: bool = True,
    seed: int = 0,
    edit=None,
) -> dict:
    """A small COLMAP dataset in ``root``: one shared camera, cameras on a ring looking at the origin,
    random points near the origin, random PNGs; ``edit(reconstruction)`` may spoil the model before it
    is written. Returns what was written (COLMAP frame)."""
    rng = np.random.default_rng(seed)
    width, height = size
    camera = pycolmap.Camera.create_from_model_name(1, model, 0.8 * width, width, height)
    if params is not None:
        camera.params = params
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(camera)
    names, poses = [], []
    for i in range(num_images):
        angle = 2 * np.pi * i / num_images
        pose = look_at(
            np.array([4 * np.cos(angle) + 1.0, 4 * np.sin(angle) - 2.0, 1.5]), np.array([1.0, -2.0, 0.0])
        )
        name = f"view_{i:03d}.png"
        reconstruction.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=1, image_id=i + 1), pycolmap.Rigid3d(pose)
        )
        names.append(name)
        poses.append(pose)
    points = rng.uniform(-1, 1, (num_points, 3)) + np.array([1.0, -2.0, 0.0])
    colors = rng.integers(0, 256, (num_points, 3), dtype=np.uint8)
    for xyz, color in zip(points, colors):
        reconstruction.add_point3D(xyz, pycolmap.Track(), color)
    if edit is not None:
        edit(reconstruction)
    model_dir = root / "sparse" / "0"
    model_dir.mkdir(parents=True)
    (reconstruction.write_text if text else reconstruction.write_binary)(str(model_dir))
    (root / "images").mkdir()
    images = {}
    if write_images:
        for name in names:
            images[name] = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
            cv2.imwrite(str(root / "images" / name), images[name][..., ::-1])
    return {
        "names": names,
        "poses": np.array(poses).reshape(-1, 3, 4),
        "points": points,
        "colors": colors,
        "images": images,
        "camera": camera,
    }
