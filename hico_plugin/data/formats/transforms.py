"""nerfstudio / instant-ngp ``transforms.json``, read as nerfstudio's writer writes it.

``transform_matrix``: camera->world, OpenGL camera axes (the OpenCV camera negates its y and z columns).
Intrinsics ``fl_x fl_y cx cy w h`` (or instant-ngp's ``camera_angle_x``) and distortion ``k1 k2 k3 k4 p1 p2`` sit
at the top level (shared) or in a frame; ``camera_model`` is OPENCV (default) or OPENCV_FISHEYE; pixel centres as
in COLMAP. The inverse of ``applied_transform`` (3x4) maps poses and points back to the original world frame.
``ply_file_path``: seed points in the file's world frame; ``mask_path`` and ``depth_file_path`` per frame.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from hico_plugin.data import images as image_io
from hico_plugin.data.camera_model import Camera
from hico_plugin.data.formats import DATA_FORMATS, DataFormat, SceneRecord
from hico_plugin.data.paths import resolve_inside
from hico_plugin.data.seed_points import no_points, seed_points
from hico_plugin.errors import HicoError

_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2", "camera_model",
               "camera_angle_x", "camera_angle_y")
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # right-multiplying a camera->world flips its y, z axes


@DATA_FORMATS.register("transforms")
@dataclass
class TransformsFormat(DataFormat):
    """nerfstudio / instant-ngp: DIR/transforms.json with frames, intrinsics and optional seed points."""

    file: str = "transforms.json"
    """Name of the JSON file inside the dataset directory."""
    triangulate: bool = True
    """Without ply_file_path: triangulate seed points from the known poses (SIFT + matching on the CPU,
    cached in the user cache directory) instead of drawing random ones."""
    random_points: int = 20_000
    """Seed points drawn at random (with a warning) when there is no ply_file_path and triangulation
    is off or finds too few points."""

    def detect(self, data_dir: Path) -> bool:
        return (data_dir / self.file).is_file()

    def read(self, data_dir: Path) -> SceneRecord:
        path = data_dir / self.file
        try:
            meta = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise HicoError(f"{path}: not valid JSON ({err})") from None
        frames = meta.get("frames") if isinstance(meta, dict) else None
        if not isinstance(frames, list) or not frames:
            raise HicoError(f"{path}: expected an object with a non-empty 'frames' list")
        entries, missing = [], []
        for index, frame in enumerate(frames):
            where = f"{path.name}: frames[{index}]"
            if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
                raise HicoError(f"{where}: expected 'file_path' and 'transform_matrix'")
            image = resolve_inside(data_dir, str(frame["file_path"]), f"{where}.file_path")
            if not image.is_file() and not image.suffix and image.with_suffix(".png").is_file():
                image = image.with_suffix(".png")  # instant-ngp/NeRF-synthetic list paths without suffix
            if not image.is_file():
                missing.append(str(frame["file_path"]))
                continue
            entries.append((index, frame, image))
        if not entries:
            raise HicoError(f"{path}: none of the {len(frames)} frames' images exist (first: {missing[0]!r})")
        notes = []
        if missing:
            notes.append(f"{path.name}: {len(missing)} of {len(frames)} frames skipped, image file missing: "
                         f"{', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}")
        entries.sort(key=lambda entry: str(entry[2].relative_to(data_dir)))

        applied = np.eye(4)
        if "applied_transform" in meta:
            applied[:3, :] = _matrix(meta["applied_transform"], (3, 4), f"{path.name}: applied_transform")
        to_original = np.linalg.inv(applied)

        cameras: dict[int, Camera] = {}
        camera_of: dict[tuple, int] = {}
        names, paths, camera_ids, viewmats, masks, depths = [], [], [], [], [], []
        for index, frame, image in entries:
            where = f"{path.name}: frames[{index}]"
            camera = _camera(meta, frame, image, where)
            key = (camera.model, camera.width, camera.height, tuple(np.round(camera.params, 9)))
            if key not in camera_of:
                camera_of[key] = len(cameras) + 1
                camera.camera_id = camera_of[key]
                cameras[camera.camera_id] = camera
            c2w = np.eye(4)
            c2w[:3, :] = _matrix(frame["transform_matrix"], (4, 4), f"{where}.transform_matrix")[:3, :]
            c2w = to_original @ c2w @ GL_TO_CV
            rotation = c2w[:3, :3]
            if abs(np.linalg.det(rotation) - 1.0) > 1e-3 or not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-3):
                raise HicoError(f"{where}.transform_matrix: rotation part is not orthonormal (expected a rigid pose)")
            # applied_transform may carry a scale; a camera frame stays rigid: re-orthonormalise
            u, _, vt = np.linalg.svd(rotation)
            c2w[:3, :3] = u @ vt
            names.append(str(image.relative_to(data_dir)))
            paths.append(image)
            camera_ids.append(camera_of[key])
            viewmats.append(np.linalg.inv(c2w))
            masks.append(resolve_inside(data_dir, str(frame["mask_path"]), f"{where}.mask_path")
                         if frame.get("mask_path") else None)
            depths.append(resolve_inside(data_dir, str(frame["depth_file_path"]), f"{where}.depth_file_path")
                          if frame.get("depth_file_path") else None)
        viewmats = np.stack(viewmats)
        seeds_at = None
        if meta.get("ply_file_path"):
            points, colors = _ply_points(meta, data_dir, path, to_original)
        else:
            points, colors = no_points()
            seeds_at = partial(seed_points, data_dir, names, camera_ids, cameras, viewmats, path.name,
                               self.triangulate, self.random_points)
        return SceneRecord(
            names=names, image_paths=paths, camera_ids=camera_ids, cameras=cameras, viewmats=viewmats,
            points=points, point_colors=colors, seed_points_at=seeds_at, mask_paths=masks,
            depth_paths=depths if any(d is not None for d in depths) else None,
            has_ground_truth=(data_dir / "ground_truth").is_dir(), notes=notes,
        )


def _ply_points(meta: dict, data_dir: Path, path: Path, to_original: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ``ply_file_path`` cloud in the original world frame: [P, 3] float64, [P, 3] uint8, read by
    COLMAP's PLY import (pycolmap imported here: only captures with a point cloud file pay for it)."""
    import pycolmap

    ply = resolve_inside(data_dir, str(meta["ply_file_path"]), f"{path.name}: ply_file_path")
    if not ply.is_file():
        raise HicoError(f"{path.name}: ply_file_path {meta['ply_file_path']!r} not found at {ply}")
    cloud = pycolmap.Reconstruction()
    try:
        cloud.import_PLY(str(ply))
    except Exception as err:  # noqa: BLE001 -- pycolmap raises bare RuntimeError on bad files
        raise HicoError(f"{ply}: not a readable PLY point cloud ({str(err).strip()[-200:]})") from None
    if cloud.num_points3D() == 0:
        raise HicoError(f"{ply}: the point cloud is empty (expected seed points)")
    ordered = [cloud.points3D[i] for i in sorted(cloud.points3D)]
    xyz = np.array([p.xyz for p in ordered], dtype=np.float64)
    xyz = xyz @ to_original[:3, :3].T + to_original[:3, 3]
    return xyz, np.array([p.color for p in ordered], dtype=np.uint8)


def _matrix(value: Any, shape: tuple[int, int], where: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        array = np.zeros(0)
    if array.shape[0] in (3, 4) and array.shape[1:] == (4,):
        array = array[: shape[0]]
    if array.shape != shape or not np.isfinite(array).all():
        raise HicoError(f"{where}: expected a finite {shape[0]}x{shape[1]} matrix")
    return array


def _camera(meta: dict, frame: dict, image: Path, where: str) -> Camera:
    values = {key: frame.get(key, meta.get(key)) for key in _INTRINSICS}
    width, height = values["w"], values["h"]
    if width is None or height is None:
        height, width = image_io.read_rgb(image).shape[:2]
    width, height = int(width), int(height)
    fx, fy = values["fl_x"], values["fl_y"]
    if fx is None and values["camera_angle_x"] is not None:
        fx = 0.5 * width / math.tan(0.5 * float(values["camera_angle_x"]))
    if fy is None and values["camera_angle_y"] is not None:
        fy = 0.5 * height / math.tan(0.5 * float(values["camera_angle_y"]))
    if fx is None:
        raise HicoError(f"{where}: no focal length (expected fl_x or camera_angle_x, in the frame or at the top)")
    fy = fx if fy is None else fy
    cx = width / 2 if values["cx"] is None else values["cx"]
    cy = height / 2 if values["cy"] is None else values["cy"]
    k1, k2, k3, k4, p1, p2 = (float(values[k] or 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
    model = values["camera_model"] or "OPENCV"
    if model == "OPENCV_FISHEYE":
        params = [fx, fy, cx, cy, k1, k2, k3, k4]
    elif model == "OPENCV":
        if k3 or k4:
            model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, 0.0, 0.0]
        elif k1 or k2 or p1 or p2:
            params = [fx, fy, cx, cy, k1, k2, p1, p2]
        else:
            model, params = "PINHOLE", [fx, fy, cx, cy]
    else:
        raise HicoError(f"{where}: camera_model {model!r} is not supported (expected OPENCV or OPENCV_FISHEYE)")
    params = [float(v) for v in params]
    if not all(math.isfinite(v) for v in params) or width <= 0 or height <= 0 or params[0] <= 0 or params[1] <= 0:
        raise HicoError(f"{where}: intrinsics must be finite with a positive focal length and size")
    return Camera(model=model, width=width, height=height, params=params)
