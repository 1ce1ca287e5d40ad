"""Reading a COLMAP sparse model (binary or text, with or without rigs/frames) and checking it."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hico_plugin.data.camera_model import Camera
from hico_plugin.data.checks import check_intrinsics
from hico_plugin.data.colmap_bin import read_binary_model
from hico_plugin.data.colmap_files import pose_matrices
from hico_plugin.data.colmap_text import read_text_model
from hico_plugin.data.undistort import SUPPORTED_MODELS
from hico_plugin.errors import HicoError

MODEL_FILES = ("cameras", "images", "points3D")


@dataclass
class ColmapModel:
    """The registered images of a sparse model, sorted by name, and its points (COLMAP's frame)."""

    names: list[str]  # [N] image names, sorted
    camera_ids: list[int]  # [N] camera of each image
    cameras: dict[int, Camera]  # the cameras the images use
    viewmats: np.ndarray  # [N, 4, 4] float64 world->camera
    points: np.ndarray  # [P, 3] float64
    point_colors: np.ndarray  # [P, 3] uint8
    tracks: "SfmTracks"  # which image observes which point


class SfmTracks:
    """Which view observes which sparse point: the tracks of points3D, as arrays. The observations are
    listed when asked for, for the points asked for: the effects analysis needs a subset, and the
    checks that may refuse a run before training need none."""

    def __init__(self, points: np.ndarray, track_starts: np.ndarray, track_lengths: np.ndarray,
                 track_image_ids: np.ndarray, view_image_ids: np.ndarray):
        """points: [P, 3]; track_starts, track_lengths: [P] where each point's observing images lie in
        ``track_image_ids`` [T]; view_image_ids: [N] (N >= 1) the image id of each view."""
        self.points = points  # [P, 3] float64, COLMAP's frame: ColmapModel.points
        self._starts, self._lengths, self._track_image_ids = track_starts, track_lengths, track_image_ids
        self._views_by_id = np.argsort(view_image_ids)  # image id -> view, by binary search
        self._sorted_ids = view_image_ids[self._views_by_id]

    def __len__(self) -> int:
        return len(self.points)

    def observations(self, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(view [O], point [O]) int64: each observation of the points ``points[::stride]`` by a
        registered view; ``point`` indexes that strided list."""
        starts, lengths = self._starts[::stride], self._lengths[::stride]
        before = np.cumsum(lengths) - lengths
        elements = np.repeat(starts - before, lengths) + np.arange(int(lengths.sum()))
        image_ids = self._track_image_ids[elements]
        slot = np.minimum(np.searchsorted(self._sorted_ids, image_ids), len(self._sorted_ids) - 1)
        known = self._sorted_ids[slot] == image_ids  # tracks may list images that are no view
        points = np.repeat(np.arange(len(starts), dtype=np.int64), lengths)
        return self._views_by_id[slot[known]].astype(np.int64), points[known]


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
    """Read and check the model in ``model_dir`` (binary when all three .bin files are there, as
    COLMAP chooses); every problem is one HicoError line."""
    binary = all((model_dir / f"{name}.bin").is_file() for name in MODEL_FILES)
    files = read_binary_model(model_dir) if binary else read_text_model(model_dir)
    ext = ".bin" if binary else ".txt"

    if not len(files.image_ids):
        raise HicoError(f"{model_dir}: the model has no registered images (expected at least one posed image)")
    for ids, what, name in ((files.image_ids, "image", "images"), (files.point_ids, "point", "points3D")):
        unique, counts = np.unique(ids, return_counts=True)
        if (counts > 1).any():
            raise HicoError(f"{model_dir}/{name}{ext}: {what} ids {unique[counts > 1][:5].tolist()} listed more "
                            "than once (expected unique ids)")
    order = sorted(range(len(files.image_names)), key=lambda i: files.image_names[i])
    names = [files.image_names[i] for i in order]
    duplicates = sorted(name for name, count in Counter(names).items() if count > 1)
    if duplicates:
        raise HicoError(f"{model_dir}/images: duplicate image names {duplicates[:5]} (expected unique names)")
    camera_ids = [int(files.image_camera_ids[i]) for i in order]

    missing = sorted(set(camera_ids) - set(files.cameras))
    if missing:
        raise HicoError(f"{model_dir}/images{ext}: images use cameras {missing[:5]}, which cameras{ext} does not "
                        "list (expected every image's camera in it)")
    cameras = {camera_id: files.cameras[camera_id] for camera_id in camera_ids}
    for camera_id, camera in sorted(cameras.items()):
        if camera.model not in SUPPORTED_MODELS:
            raise HicoError(
                f"{model_dir}/cameras: camera {camera_id} has model {camera.model}; "
                f"supported models: {', '.join(SUPPORTED_MODELS)}"
            )
        if not np.isfinite(camera.params).all() or camera.width <= 0 or camera.height <= 0:
            raise HicoError(f"{model_dir}/cameras: camera {camera_id} has non-finite parameters or an empty size")
        check_intrinsics(f"{model_dir}/cameras: camera {camera_id}", camera.width, camera.height,
                         camera.focal_length_x, camera.focal_length_y,
                         camera.principal_point_x, camera.principal_point_y)

    viewmats = pose_matrices(files.cam_from_world[order])
    bad_poses = [name for name, ok in zip(names, np.isfinite(viewmats).all(axis=(1, 2))) if not ok]
    if bad_poses:
        raise HicoError(f"{model_dir}/images: NaN/inf pose for {bad_poses[:5]} (expected finite poses)")

    if len(files.point_ids) == 0:
        raise HicoError(f"{model_dir}/points3D: the point cloud is empty (expected sparse points to seed anchors)")
    by_id = np.argsort(files.point_ids, kind="stable")  # a stable order, whatever the file's
    points = files.points[by_id]
    if not np.isfinite(points).all():
        count = int((~np.isfinite(points).all(axis=1)).sum())
        raise HicoError(f"{model_dir}/points3D: {count} points have NaN/inf coordinates (expected finite points)")
    track_starts = np.cumsum(files.track_lengths) - files.track_lengths
    tracks = SfmTracks(points, track_starts[by_id], files.track_lengths[by_id], files.track_image_ids,
                       files.image_ids[order])
    return ColmapModel(names, camera_ids, cameras, viewmats, points, files.colors[by_id], tracks)
