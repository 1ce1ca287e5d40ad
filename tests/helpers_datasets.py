"""Datasets for tests that are large on disk but cheap to make."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import torch


def ring_pose(angle: float, radius: float = 4.0, height: float = 1.5) -> np.ndarray:
    """[3, 4] cam_from_world of a camera on a ring around the origin looking at it (OpenCV axes, z up)."""
    centre = np.array([radius * np.cos(angle), radius * np.sin(angle), height])
    forward = -centre / np.linalg.norm(centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    rotation = np.stack([right, np.cross(forward, right), forward])
    return np.concatenate([rotation, -rotation @ centre[:, None]], axis=1)


def write_large_colmap_dataset(root: Path, num_images: int = 300, size: tuple[int, int] = (1600, 1200),
                               num_points: int = 2_000, seed: int = 0) -> Path:
    """A COLMAP dataset in ``root`` of ``num_images`` photos of ``size`` px, as costly to decode and
    analyse as real ones: one noise JPEG, hard-linked under every name (seconds to make, one file's
    worth of disk), cameras on a ring, random points near the origin. Returns ``root``."""
    rng = np.random.default_rng(seed)
    width, height = size
    camera = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 0.8 * width, width, height)
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(camera)
    (root / "images").mkdir(parents=True)
    photo = root / "photo.jpg"
    cv2.imwrite(str(photo), rng.integers(0, 256, (height, width, 3), dtype=np.uint8))
    for i in range(num_images):
        name = f"view_{i:04d}.jpg"
        os.link(photo, root / "images" / name)
        reconstruction.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=i + 1),
                                                    pycolmap.Rigid3d(ring_pose(2 * np.pi * i / num_images)))
    for xyz in rng.uniform(-1, 1, (num_points, 3)):
        reconstruction.add_point3D(xyz, pycolmap.Track(), rng.integers(0, 256, 3, dtype=np.uint8))
    (root / "sparse" / "0").mkdir(parents=True)
    reconstruction.write_binary(str(root / "sparse" / "0"))
    return root


# Mega-NeRF's converter: world axes (right, down, forward) of the source frame -> (down, right, back)
RDF_TO_DRB = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
ORIGIN_DRB = np.array([0.3, -1.2, 2.0])
SCALE = 7.5


def write_meganerf(scene: Path, out: Path, val_every: int = 4) -> dict[str, str]:
    """A Mega-NeRF folder of the COLMAP scene, following the steps of Mega-NeRF's converter (camera
    frame permuted to DRB, columns reordered to OpenGL axes, shifted and scaled). Returns
    {Mega-NeRF image name: COLMAP image name}."""
    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    out.mkdir()
    torch.save({"origin_drb": torch.tensor(ORIGIN_DRB), "pose_scale_factor": SCALE}, out / "coordinates.pt")
    names = {}
    for i, image in enumerate(sorted(model.images.values(), key=lambda im: im.name)):
        split = "val" if i % val_every == 0 else "train"
        for folder in ("rgbs", "metadata"):
            (out / split / folder).mkdir(parents=True, exist_ok=True)
        c2w = image.cam_from_world().inverse().matrix()  # [3, 4], OpenCV axes
        in_drb = np.concatenate([RDF_TO_DRB @ c2w[:, :3] @ RDF_TO_DRB.T, RDF_TO_DRB @ c2w[:, 3:]], axis=1)
        in_drb[:, 3] = (in_drb[:, 3] - ORIGIN_DRB) / SCALE
        stored = np.concatenate([in_drb[:, 1:2], -in_drb[:, :1], in_drb[:, 2:4]], axis=1)
        camera = model.cameras[image.camera_id]
        fx, fy, cx, cy = camera.params
        torch.save({"H": camera.height, "W": camera.width, "c2w": torch.tensor(stored, dtype=torch.float32),
                    "intrinsics": torch.tensor([fx, fy, cx, cy], dtype=torch.float32),
                    "distortion": torch.zeros(4)}, out / split / "metadata" / f"{i:06d}.pt")
        shutil.copy(scene / "images" / image.name, out / split / "rgbs" / f"{i:06d}.png")
        names[f"{split}/rgbs/{i:06d}.png"] = image.name
    return names


def write_without_tracks(source: Path, out: Path) -> Path:
    """A copy of the COLMAP dataset ``source`` whose points carry no tracks and whose images list no
    2D points, as many tools export a model (text format); returns ``out``."""
    import pycolmap

    shutil.copytree(source, out, ignore=shutil.ignore_patterns("sparse"))
    model = out / "sparse" / "0"
    model.mkdir(parents=True)
    pycolmap.Reconstruction(str(source / "sparse" / "0")).write_text(str(model))
    points = (model / "points3D.txt").read_text().splitlines()  # ID X Y Z R G B ERROR, then the track
    (model / "points3D.txt").write_text("\n".join(line if line.startswith("#") else " ".join(line.split()[:8])
                                                  for line in points) + "\n")
    lines = (model / "images.txt").read_text().splitlines()  # per image: a pose line, then its 2D points
    comments, body = [x for x in lines if x.startswith("#")], [x for x in lines if not x.startswith("#")]
    (model / "images.txt").write_text("\n".join(comments + [x for pose in body[::2] for x in (pose, "")]) + "\n")
    return out


SMALL_DISTRICT = dict(blocks=3, num_views=30, sparse_points=300, surface_spacing=1.0)
"""A district small enough for a test whose views still have neighbours: 3 x 3 blocks, 30 views."""
