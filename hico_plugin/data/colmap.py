"""Reading a COLMAP sparse model (binary or text, with or without rigs/frames) through pycolmap."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from hico_plugin.data.checks import check_intrinsics
from hico_plugin.data.colmap_bin import check_binary_model
from hico_plugin.data.undistort import SUPPORTED_MODELS
from hico_plugin.errors import HicoError

MODEL_FILES = ("cameras", "images", "points3D")


@dataclass
class ColmapModel:
    """The registered images of a sparse model, sorted by name, and its points (COLMAP's frame)."""

    names: list[str]  # [N] image names, sorted
    camera_ids: list[int]  # [N] camera of each image
    cameras: dict[int, pycolmap.Camera]  # the cameras the images use
    viewmats: np.ndarray  # [N, 4, 4] float64 world->camera
    points: np.ndarray  # [P, 3] float64
    point_colors: np.ndarray  # [P, 3] uint8
    tracks: "SfmTracks"  # which image observes which point


class SfmTracks:
    """Which view observes which sparse point, from the reconstruction the model was read from. The
    observations are listed on first use, for the points asked for: the effects analysis needs a
    subset, and the checks that may refuse a run before training need none."""

    def __init__(self, reconstruction: pycolmap.Reconstruction, point_ids: list[int], points: np.ndarray,
                 names: list[str]):
        self._reconstruction = reconstruction
        self.points = points  # [P, 3] float64, COLMAP's frame: ColmapModel.points
        self._point_ids = point_ids  # the order of ColmapModel.points
        view_of_name = {name: view for view, name in enumerate(names)}
        self._view_of_image = {image_id: view_of_name[image.name] for image_id, image in reconstruction.images.items()
                               if image.name in view_of_name}

    def __len__(self) -> int:
        return len(self._point_ids)

    def observations(self, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(view [O], point [O]) int64: each observation of the points ``points[::stride]`` by a
        registered view; ``point`` indexes that strided list."""
        views, points = [], []
        for row, point_id in enumerate(self._point_ids[::stride]):
            for element in self._reconstruction.points3D[point_id].track.elements:
                view = self._view_of_image.get(element.image_id)
                if view is not None:
                    views.append(view)
                    points.append(row)
        return np.array(views, np.int64), np.array(points, np.int64)


def find_model_dir(data_dir: Path) -> Path:
    """``data_dir/sparse/0``, or a HicoError saying what is missing."""
    model_dir = data_dir / "sparse" / "0"
    if not model_dir.is_dir():
        raise HicoError(f"{model_dir}: not found (expected the COLMAP sparse model in DIR/sparse/0)")
    for ext in (".bin", ".txt"):
        if all((model_dir / f"{name}{ext}").is_file() for name in MODEL_FILES):
            return model_dir
    raise HicoError(
        f"{model_dir}: expected cameras, images and points3D as .bin or .txt files, found "
        f"{sorted(p.name for p in model_dir.iterdir()) or 'nothing'}"
    )


def read_colmap_model(model_dir: Path) -> ColmapModel:
    """Read and check the model in ``model_dir``; every problem is one HicoError line."""
    if (model_dir / "images.bin").is_file():
        check_binary_model(model_dir)  # before pycolmap, which trusts the counts in the file
    try:
        reconstruction = pycolmap.Reconstruction(str(model_dir))
    except Exception as err:  # noqa: BLE001 -- pycolmap raises bare RuntimeError/ValueError on bad files
        message = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
        raise HicoError(f"{model_dir}: cannot read the COLMAP model ({message})") from None

    images = [image for image in reconstruction.images.values() if image.has_pose]
    if not images:
        raise HicoError(f"{model_dir}: the model has no registered images (expected at least one posed image)")
    images.sort(key=lambda image: image.name)
    names = [image.name for image in images]
    duplicates = sorted(name for name, count in Counter(names).items() if count > 1)
    if duplicates:
        raise HicoError(f"{model_dir}/images: duplicate image names {duplicates[:5]} (expected unique names)")

    cameras = {image.camera_id: reconstruction.cameras[image.camera_id] for image in images}
    for camera_id, camera in sorted(cameras.items()):
        if camera.model.name not in SUPPORTED_MODELS:
            raise HicoError(
                f"{model_dir}/cameras: camera {camera_id} has model {camera.model.name}; "
                f"supported models: {', '.join(SUPPORTED_MODELS)}"
            )
        if not np.isfinite(camera.params).all() or camera.width <= 0 or camera.height <= 0:
            raise HicoError(f"{model_dir}/cameras: camera {camera_id} has non-finite parameters or an empty size")
        check_intrinsics(f"{model_dir}/cameras: camera {camera_id}", camera.width, camera.height,
                         camera.focal_length_x, camera.focal_length_y,
                         camera.principal_point_x, camera.principal_point_y)

    viewmats = np.tile(np.eye(4), (len(images), 1, 1))
    viewmats[:, :3, :] = np.stack([image.cam_from_world().matrix() for image in images])
    bad_poses = [name for name, ok in zip(names, np.isfinite(viewmats).all(axis=(1, 2))) if not ok]
    if bad_poses:
        raise HicoError(f"{model_dir}/images: NaN/inf pose for {bad_poses[:5]} (expected finite poses)")

    points3d = reconstruction.points3D
    if len(points3d) == 0:
        raise HicoError(f"{model_dir}/points3D: the point cloud is empty (expected sparse points to seed anchors)")
    point_ids = sorted(points3d)  # a stable order, whatever the map's
    by_id = [points3d[point_id] for point_id in point_ids]
    points = np.array([point.xyz for point in by_id], dtype=np.float64)
    colors = np.array([point.color for point in by_id], dtype=np.uint8)
    if not np.isfinite(points).all():
        count = int((~np.isfinite(points).all(axis=1)).sum())
        raise HicoError(f"{model_dir}/points3D: {count} points have NaN/inf coordinates (expected finite points)")
    return ColmapModel(names, [image.camera_id for image in images], cameras, viewmats, points, colors,
                       SfmTracks(reconstruction, point_ids, points, names))
