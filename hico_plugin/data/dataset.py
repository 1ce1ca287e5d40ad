"""A parsed scene: cameras and sparse points up front, images loaded lazily into a bounded cache."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hico_plugin.cameras import Cameras
from hico_plugin.data import images as image_io
from hico_plugin.data.cache import ByteLRUCache
from hico_plugin.data.camera_model import Camera
from hico_plugin.data.paths import resolve_inside
from hico_plugin.data.transform import SceneTransform, frame_differences
from hico_plugin.data.undistort import PINHOLE_MODELS, remap, undistortion_maps
from hico_plugin.errors import HicoError
from hico_plugin.field.octree import MAX_SEED_POINTS, anchor_seed_points, distance_range

# Undistortion maps are two float32 images per camera; a few hundred MB covers thousands of views.
_MAPS_CACHE_BYTES = 256 * 2**20


@dataclass
class CameraSource:
    """How files of one COLMAP camera become loaded images: checked against ``full_size``, resized to
    ``distorted`` (the camera at the loaded resolution) and, unless pinhole, remapped to ``pinhole``."""

    full_size: tuple[int, int]  # (width, height) of the camera in sparse/0
    model: str  # COLMAP model name as stored in sparse/0
    distorted: Camera  # at the loaded resolution
    pinhole: Camera  # at the loaded resolution; what ``Dataset.cameras`` holds

    @property
    def needs_undistortion(self) -> bool:
        return self.model not in PINHOLE_MODELS


class Dataset:
    """All registered views of a COLMAP scene in the normalised frame (see ``SceneTransform``).

    Views are sorted by image name; view ``i`` is ``cameras[i]`` / ``image(i)`` / ``image_names[i]``.
    ``cameras`` are pinhole at the loaded resolution (downscaled, undistorted).
    """

    def __init__(
        self,
        *,
        data_dir: Path,
        image_names: list[str],
        image_paths: list[Path],
        camera_ids: list[int],
        sources: dict[int, CameraSource],
        cameras: Cameras,
        transform: SceneTransform,
        points: Tensor,
        point_colors: Tensor,
        train_indices: Tensor,
        test_indices: Tensor,
        mask_paths: list[Path | None],
        undistorted_dir: Path | None,
        cache_bytes: int,
        metadata: dict[str, Any],
        tracks: Any = None,
        depth_paths: list[Path | None] | None = None,
        notes: list[str] | None = None,
    ):
        self.data_dir = data_dir
        self.image_names = image_names
        self.image_paths = image_paths
        self.camera_ids = camera_ids
        self.sources = sources
        self.cameras = cameras
        self.transform = transform
        self.points = points
        self.point_colors = point_colors
        self.train_indices = train_indices
        self.test_indices = test_indices
        self.mask_paths = mask_paths
        self.undistorted_dir = undistorted_dir
        self.metadata = metadata
        self.tracks = tracks  # the format's SfM tracks (data.colmap.SfmTracks, aligned with the points) or None
        self.depth_paths = depth_paths  # [N] the format's depth maps (transforms.json depth_file_path)
        self.notes = notes or []  # what reading the dataset found worth saying (printed once by its reader)
        self._cache = ByteLRUCache(cache_bytes)
        self._maps = ByteLRUCache(_MAPS_CACHE_BYTES)
        self._surface_points: Tensor | None = None
        self._distance_ranges: dict[tuple[float, int], tuple[float, float]] = {}

    def __len__(self) -> int:
        return len(self.image_names)

    @property
    def cache(self) -> ByteLRUCache:
        """The decoded-image cache (images, masks, ground truth) shared by all views."""
        return self._cache

    # ------------------------------------------------------------------ images and masks
    def image(self, i: int) -> Tensor:
        """uint8 [H, W, 3] RGB of view ``i`` at the loaded resolution (cached, least recently used
        evicted first). The tensor shares the cache's memory: copy it before changing it in place."""
        return torch.from_numpy(self._cache.get(("image", i), lambda: self.load_image(i)))

    def mask(self, i: int) -> Tensor | None:
        """bool [H, W, 1] (True = pixel to train on) of view ``i``, or None without a mask file."""
        if self.mask_paths[i] is None:
            return None
        return torch.from_numpy(self._cache.get(("mask", i), lambda: self.load_mask(i)))

    def load_image(self, i: int) -> np.ndarray:
        """Decode view ``i`` from disk (no cache): uint8 [H, W, 3]. Undistorted views are read from,
        or written to, the undistortion cache."""
        source = self.sources[self.camera_ids[i]]
        cached = self._undistorted_path(i)
        if cached is not None and cached.is_file():
            try:
                image = image_io.read_rgb(cached, "cached undistorted image")
                if image.shape[:2] == (source.pinhole.height, source.pinhole.width):
                    return image
            except HicoError:
                pass  # a damaged cache entry is rebuilt from the original below
        image = self._to_loaded(image_io.read_rgb(self.image_paths[i]), i, self.image_paths[i], nearest=False)
        if cached is not None:
            image_io.write_png_atomic(cached, image)
        return image

    def load_mask(self, i: int) -> np.ndarray:
        path = self.mask_paths[i]
        assert path is not None
        mask = image_io.read_mask(path).astype(np.uint8)
        return self._to_loaded(mask, i, path, nearest=True).astype(bool)[..., None]

    def verify_images(self, on_progress: Callable[[int, int], None] | None = None) -> None:
        """Decode every image and mask once (filling the undistortion cache); one HicoError naming
        the first bad file and how many are bad."""
        problems = []
        for i in range(len(self)):
            try:
                self.load_image(i)
                if self.mask_paths[i] is not None:
                    self.load_mask(i)
            except HicoError as err:
                problems.append(str(err))
            if on_progress is not None:
                on_progress(i + 1, len(self))
        if problems:
            more = f" (and {len(problems) - 1} more bad files)" if len(problems) > 1 else ""
            raise HicoError(problems[0] + more)

    # ------------------------------------------------------------------ ground truth (built-in scenes)
    def gt_depth(self, i: int) -> Tensor | None:
        """float32 [H, W, 1] camera z in the normalised frame (0 = no surface), or None."""
        path = self._gt_path("depth", i)
        if path is None:
            return None

        def load() -> np.ndarray:
            depth = self._load_npy(path, ndim=2)
            return (self._to_loaded(depth, i, path, nearest=True) * np.float32(self.transform.scale))[..., None]

        return torch.from_numpy(self._cache.get(("depth", i), load))

    def gt_normal(self, i: int) -> Tensor | None:
        """float32 [H, W, 3] unit normals in camera coordinates (OpenCV axes; 0 = no surface), or None."""
        path = self._gt_path("normal", i)
        if path is None:
            return None

        def load() -> np.ndarray:
            normal = self._load_npy(path, ndim=3)
            if normal.shape[2] != 3:
                raise HicoError(f"{path}: expected float [H, W, 3] normals, got shape {normal.shape}")
            return self._to_loaded(normal, i, path, nearest=True)

        return torch.from_numpy(self._cache.get(("normal", i), load))

    @property
    def gt_surface_points(self) -> Tensor | None:
        """float32 [M, 3] dense ground-truth surface samples in the normalised frame, or None."""
        path = self.data_dir / "ground_truth" / "surface_points.npy"
        if self._surface_points is None and path.is_file():
            points = self._load_npy(path, ndim=2)
            if points.shape[1] != 3 or not np.isfinite(points).all():
                raise HicoError(f"{path}: expected finite float [M, 3] points, got shape {points.shape}")
            self._surface_points = self.transform.points_from_colmap(torch.from_numpy(points))
        return self._surface_points

    # ------------------------------------------------------------------ scene extent
    def camera_distance_range(self, dist_ratio: float = 0.999, max_points: int = MAX_SEED_POINTS) -> tuple[float, float]:
        """(dist_min, dist_max) from the training cameras to the sparse points: the octree's figure
        (``field.octree.distance_range`` of the points the octree is built from), measured once per
        setting and shared by the octree, the LOD effect's finding, hico-inspect and the mesh depth."""
        key = (dist_ratio, max_points)
        if key not in self._distance_ranges:
            centres = self.cameras.centers[self.train_indices].float()
            self._distance_ranges[key] = distance_range(anchor_seed_points(self.points, max_points), centres, dist_ratio)
        return self._distance_ranges[key]

    def frame(self) -> dict:
        """The scene frame the views are loaded in (the normalisation); checkpoints record it, so a model
        is never loaded into another one (engine.checkpoints.check_frame)."""
        return self.transform.to_dict()

    def frame_differences(self, stored: dict) -> list[str]:
        """The parts in which a checkpoint's recorded ``frame()`` places the cameras elsewhere than this
        dataset's (``data.transform.frame_differences``); empty when its model can be loaded here."""
        return frame_differences(stored, self.frame())

    def cameras_extent(self) -> float:
        """NeRF++ radius of the train cameras: 1.1 x the largest distance of a centre from their mean
        (the positional learning-rate scale)."""
        centres = self.cameras.centers[self.train_indices]
        return 1.1 * float((centres - centres.mean(dim=0)).norm(dim=-1).max())

    # ------------------------------------------------------------------ helpers
    def _to_loaded(self, array: np.ndarray, i: int, path: Path, nearest: bool) -> np.ndarray:
        """A per-view array as stored (the camera's full size or an exact downscale of it) -> the
        loaded resolution, undistorted when the camera has distortion."""
        camera_id = self.camera_ids[i]
        source = self.sources[camera_id]
        height, width = array.shape[:2]
        if not image_io.is_downscale_of((width, height), source.full_size):
            raise HicoError(
                f"{path}: size {width}x{height} disagrees with camera {camera_id} in sparse/0 "
                f"({source.full_size[0]}x{source.full_size[1]}; expected that size or an exact downscale)"
            )
        array = image_io.resize(array, source.distorted.width, source.distorted.height, nearest=nearest)
        if not source.needs_undistortion:
            return array
        maps = self._maps.get(camera_id, lambda: np.stack(undistortion_maps(source.distorted, source.pinhole)))
        return remap(array, (maps[0], maps[1]), nearest=nearest)

    def _undistorted_path(self, i: int) -> Path | None:
        if self.undistorted_dir is None or not self.sources[self.camera_ids[i]].needs_undistortion:
            return None
        return resolve_inside(self.undistorted_dir, f"{self.image_names[i]}.png", f"image '{self.image_names[i]}'")

    def _gt_path(self, kind: str, i: int) -> Path | None:
        name = Path(self.image_names[i]).with_suffix(".npy").as_posix()
        path = resolve_inside(self.data_dir / "ground_truth" / kind, name, f"ground_truth/{kind} of image '{self.image_names[i]}'")
        return path if path.is_file() else None

    @staticmethod
    def _load_npy(path: Path, ndim: int) -> np.ndarray:
        try:
            array = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as err:
            raise HicoError(f"{path}: unreadable .npy file ({err})") from None
        if array.ndim != ndim or not np.issubdtype(array.dtype, np.floating):
            raise HicoError(
                f"{path}: expected a float array with {ndim} dimensions, got {array.dtype} {array.shape}"
            )
        return np.ascontiguousarray(array, dtype=np.float32)
