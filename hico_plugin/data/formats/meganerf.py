"""The Mega-NeRF layout (Mill19, UrbanScene3D), read into the source SfM's frame and units, OpenCV camera axes.

``coordinates.pt`` {"origin_drb": [3], "pose_scale_factor"}; ``{train,val}/rgbs/<stem>.jpg|png`` (undistorted; val
is our test split); ``{train,val}/metadata/<stem>.pt`` {"H", "W", "c2w": [3, 4] camera->world, OpenGL camera axes,
"intrinsics": fx, fy, cx, cy in pixels, "distortion": ignored, as by Mega-NeRF's loader}. Its COLMAP converter's
``x_drb = (P @ x_source - origin_drb) / pose_scale_factor``, ``P = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]``, is
undone. ``.pt`` files load with ``weights_only=True``: a crafted pickle cannot run code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hico_plugin.data.camera_model import Camera
from hico_plugin.data.checks import check_intrinsics
from hico_plugin.data.formats import DATA_FORMATS, DataFormat, SceneRecord
from hico_plugin.data.paths import resolve_inside
from hico_plugin.data.seed_points import no_points, seed_points
from hico_plugin.errors import HicoError

DRB_FROM_SOURCE = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # P above; P @ P = I
GL_TO_CV = np.diag([1.0, -1.0, -1.0])  # right-multiplying a camera->world rotation flips its y, z axes
SPLITS = ("train", "val")  # val/ is Mega-NeRF's held-out set: our test split
IMAGE_SUFFIXES = (".jpg", ".JPG", ".jpeg", ".png", ".PNG")


@DATA_FORMATS.register("meganerf")
@dataclass
class MegaNerfFormat(DataFormat):
    """Mega-NeRF (Mill19, UrbanScene3D): DIR/coordinates.pt and DIR/{train,val}/{rgbs,metadata}/; val/
    is the test split."""

    triangulate: bool = True
    """The layout has no point cloud: triangulate seed points from the known poses (SIFT + matching on
    the CPU, cached in the user cache directory) instead of drawing random ones."""
    random_points: int = 20_000
    """Seed points drawn at random (with a warning) when triangulation is off or finds too few points."""

    def detect(self, data_dir: Path) -> bool:
        return (data_dir / "train" / "metadata").is_dir()

    def read(self, data_dir: Path) -> SceneRecord:
        origin, scale = _coordinates(data_dir / "coordinates.pt")
        names, paths, camera_ids, viewmats, test_names = [], [], [], [], []
        cameras: dict[int, Camera] = {}
        camera_of: dict[tuple, int] = {}
        for split in SPLITS:
            metadata_dir = data_dir / split / "metadata"
            if not metadata_dir.is_dir():
                if split == "train":
                    raise HicoError(f"{metadata_dir}: not found (expected the Mega-NeRF train/metadata/ folder)")
                continue
            for meta_path in sorted(metadata_dir.glob("*.pt")):
                # a symlinked file must not lead out of the dataset
                meta_path = resolve_inside(data_dir, meta_path.relative_to(data_dir).as_posix(), "Mega-NeRF metadata")
                image = _image_of(data_dir, split, meta_path)
                meta = _load_pt(meta_path)
                camera, c2w = _camera(meta, meta_path), _c2w(meta, meta_path)
                key = (camera.width, camera.height, tuple(np.round(camera.params, 9)))
                if key not in camera_of:
                    camera.camera_id = len(cameras) + 1
                    camera_of[key] = camera.camera_id
                    cameras[camera.camera_id] = camera
                # back to the source frame: undo the scale and shift, then the axis permutation
                c2w_source = np.eye(4)
                c2w_source[:3, :3] = DRB_FROM_SOURCE @ c2w[:, :3] @ GL_TO_CV
                c2w_source[:3, 3] = DRB_FROM_SOURCE @ (c2w[:, 3] * scale + origin)
                name = image.relative_to(data_dir).as_posix()
                names.append(name)
                paths.append(image)
                camera_ids.append(camera_of[key])
                viewmats.append(np.linalg.inv(c2w_source))
                if split == "val":
                    test_names.append(name)
        if not names:
            raise HicoError(f"{data_dir / 'train' / 'metadata'}: no .pt files (expected one per training image)")
        viewmats = np.stack(viewmats)
        points, colors = no_points()
        return SceneRecord(
            names=names, image_paths=paths, camera_ids=camera_ids, cameras=cameras, viewmats=viewmats,
            points=points, point_colors=colors, test_names=test_names,
            seed_points_at=partial(seed_points, data_dir, names, camera_ids, cameras, viewmats,
                                   f"{data_dir} (Mega-NeRF)", self.triangulate, self.random_points),
        )


def _load_pt(path: Path) -> dict[str, Any]:
    """The dict in a ``.pt`` file; tensors, numbers, lists and dicts only (nothing that runs code)."""
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 -- UnpicklingError for code objects, RuntimeError for bad zips
        reason = str(err).strip().splitlines()[0][:160] if str(err).strip() else type(err).__name__
        raise HicoError(f"{path}: refused or unreadable (expected a torch.save'd dict of tensors and numbers, "
                        f"loaded with weights_only=True; {reason})") from None
    if not isinstance(data, dict):
        raise HicoError(f"{path}: expected a dict, got {type(data).__name__}")
    return data


def _array(data: dict[str, Any], key: str, shape: tuple[int, ...], path: Path) -> np.ndarray:
    """Field ``key`` of ``data`` as a finite float64 array of ``shape``; HicoError naming file and field."""
    if key not in data:
        raise HicoError(f"{path}: field {key!r} missing (expected {_shape_text(shape)} numbers)")
    value = data[key]
    try:
        array = value.detach().to(torch.float64).numpy() if torch.is_tensor(value) else np.asarray(value, np.float64)
    except (TypeError, ValueError, RuntimeError):
        array = None
    if array is None or array.shape != shape or not np.isfinite(array).all():
        got = tuple(array.shape) if array is not None else type(value).__name__
        raise HicoError(f"{path}: field {key!r} is {got}; expected finite {_shape_text(shape)} numbers")
    return array


def _shape_text(shape: tuple[int, ...]) -> str:
    return "a single number" if not shape else "[" + ", ".join(map(str, shape)) + "]"


def _coordinates(path: Path) -> tuple[np.ndarray, float]:
    """(origin_drb [3], pose_scale_factor) of ``coordinates.pt``."""
    if not path.is_file():
        raise HicoError(f"{path}: not found (expected Mega-NeRF's coordinates.pt with origin_drb and pose_scale_factor)")
    data = _load_pt(path)
    origin = _array(data, "origin_drb", (3,), path)
    scale = float(_array(data, "pose_scale_factor", (), path))
    if scale <= 0:
        raise HicoError(f"{path}: field 'pose_scale_factor' is {scale:g}; expected a positive number")
    return origin, scale


def _c2w(meta: dict[str, Any], path: Path) -> np.ndarray:
    """[3, 4] camera->world (OpenGL camera axes); a [4, 4] matrix is cut to its top rows."""
    if torch.is_tensor(meta.get("c2w")) and tuple(meta["c2w"].shape) == (4, 4):
        meta = {**meta, "c2w": meta["c2w"][:3]}
    c2w = _array(meta, "c2w", (3, 4), path)
    rotation = c2w[:, :3]
    if abs(np.linalg.det(rotation) - 1.0) > 1e-3 or not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-3):
        raise HicoError(f"{path}: field 'c2w' has a rotation part that is not orthonormal (expected a rigid pose)")
    u, _, vt = np.linalg.svd(rotation)  # float32 storage: re-orthonormalise
    return np.concatenate([u @ vt, c2w[:, 3:]], axis=1)


def _camera(meta: dict[str, Any], path: Path) -> Camera:
    size = []
    for key in ("W", "H"):
        value = float(_array(meta, key, (), path))
        if value != math.floor(value) or value <= 0:
            raise HicoError(f"{path}: field {key!r} is {value:g}; expected a positive whole number of pixels")
        size.append(int(value))
    fx, fy, cx, cy = (float(v) for v in _array(meta, "intrinsics", (4,), path))
    check_intrinsics(f"{path}: field 'intrinsics'", size[0], size[1], fx, fy, cx, cy)
    return Camera(model="PINHOLE", width=size[0], height=size[1], params=[fx, fy, cx, cy])


def _image_of(data_dir: Path, split: str, meta_path: Path) -> Path:
    """``<split>/rgbs/<stem>.<jpg|png>``, as Mega-NeRF pairs images with metadata."""
    for suffix in IMAGE_SUFFIXES:
        candidate = data_dir / split / "rgbs" / f"{meta_path.stem}{suffix}"
        if candidate.is_file():
            return resolve_inside(data_dir, candidate.relative_to(data_dir).as_posix(), f"{meta_path}: image")
    raise HicoError(f"{meta_path}: no image {split}/rgbs/{meta_path.stem}.jpg or .png beside it "
                    "(expected one image per metadata file)")


__all__ = ["MegaNerfFormat"]
