"""``ColmapDataParserConfig``: a COLMAP dataset directory -> ``Dataset``."""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hico_plugin.cameras import Cameras
from hico_plugin.config import InstantiateConfig
from hico_plugin.data.checks import MIN_LOADED_SIZE, check_image_sizes
from hico_plugin.data.colmap import ColmapModel, find_model_dir, read_colmap_model
from hico_plugin.data.dataset import CameraSource, Dataset
from hico_plugin.data.paths import resolve_inside
from hico_plugin.data.transform import SceneTransform
from hico_plugin.data.undistort import calibration_matrix, pinhole_of, rescaled
from hico_plugin.errors import HicoError
from hico_plugin.registry import Registry

DATAPARSERS: Registry[type[InstantiateConfig]] = Registry("data parser")


@DATAPARSERS.register("colmap")
@dataclass
class ColmapDataParserConfig(InstantiateConfig):
    """A COLMAP dataset: DIR/images, DIR/sparse/0, optional DIR/masks and DIR/ground_truth."""

    data: Path = Path("data")
    """Dataset directory holding images/ and sparse/0/ (cameras, images, points3D as .bin or .txt)."""
    images_dir: str = "images"
    """Name of the image folder inside the dataset directory."""
    downscale: int = 1
    """Load images at 1/N resolution: from <images_dir>_N/ when it exists, else resized on load."""
    test_every: int = 8
    """Every Nth view (sorted by name, index % N == 0) goes to the test split; 0 = no test split."""
    test_names: tuple[str, ...] = ()
    """Explicit test image names; when given, they replace --test-every."""
    masks: bool = True
    """Use DIR/masks/<name>.png (white = keep) when it exists."""
    normalize: bool = True
    """Centre on the mean camera centre and scale the farthest camera to distance 1."""
    cache_mb: int = 2048
    """Budget of the in-memory cache of decoded images (LRU, in MB)."""
    cache_dir: Path | None = None
    """Where undistorted images are cached; default DIR/.hico_cache, or ~/.cache/hico_plugin when DIR
    is read-only."""

    def __post_init__(self) -> None:
        # accept plain strings from Python callers and YAML configs
        self.data = Path(self.data)
        self.cache_dir = Path(self.cache_dir) if self.cache_dir is not None else None
        self.test_names = tuple(self.test_names)

    def setup(self, **kwargs: Any) -> Dataset:
        return self.parse()

    def parse(self) -> Dataset:
        """Read, check and normalise the dataset; images stay on disk until first used."""
        data_dir = self.data
        if not data_dir.is_dir():
            raise HicoError(
                f"data directory {data_dir}: not found (expected a COLMAP dataset with images/ and sparse/0)"
            )
        if self.downscale < 1:
            raise HicoError(f"--downscale: expected a whole number >= 1, got {self.downscale}")
        model_dir = find_model_dir(data_dir)
        model = read_colmap_model(model_dir)
        image_dir = self._image_dir()
        image_paths = [resolve_inside(image_dir, name, f"{model_dir}/images: image '{name}'") for name in model.names]
        missing = [str(path) for path in image_paths if not path.is_file()]
        if missing:
            raise HicoError(
                f"{missing[0]}: image listed in sparse/0 but not on disk ({len(missing)} of {len(image_paths)} missing)"
            )
        train_indices, test_indices = self._split(model.names)

        sources = {camera_id: self._camera_source(camera) for camera_id, camera in model.cameras.items()}
        for camera_id, source in sources.items():  # the size training sees, after --downscale
            width, height = source.pinhole.width, source.pinhole.height
            if min(width, height) < MIN_LOADED_SIZE:
                raise HicoError(f"{model_dir}/cameras: camera {camera_id} loads at {width}x{height} px; expected "
                                f"at least {MIN_LOADED_SIZE}x{MIN_LOADED_SIZE} (lower --downscale)")
        check_image_sizes(image_paths, [sources[camera_id].full_size for camera_id in model.camera_ids])
        viewmats_colmap = torch.from_numpy(model.viewmats)
        points_colmap = torch.from_numpy(model.points)
        transform = SceneTransform.identity()
        if self.normalize:
            rotations, translations = viewmats_colmap[:, :3, :3], viewmats_colmap[:, :3, 3:]
            centres = -(rotations.transpose(1, 2) @ translations).squeeze(-1)
            transform = SceneTransform.from_camera_centres(centres, fallback_points=points_colmap)
        pinholes = [sources[camera_id].pinhole for camera_id in model.camera_ids]
        cameras = Cameras(
            viewmats=transform.viewmats_from_colmap(viewmats_colmap).to(torch.float32),
            Ks=torch.from_numpy(np.stack([calibration_matrix(camera) for camera in pinholes])).to(torch.float32),
            widths=torch.tensor([camera.width for camera in pinholes], dtype=torch.int64),
            heights=torch.tensor([camera.height for camera in pinholes], dtype=torch.int64),
        )
        return Dataset(
            data_dir=data_dir,
            image_names=model.names,
            image_paths=image_paths,
            camera_ids=model.camera_ids,
            sources=sources,
            cameras=cameras,
            transform=transform,
            points=transform.points_from_colmap(points_colmap).to(torch.float32),
            point_colors=torch.from_numpy(model.point_colors),
            train_indices=train_indices,
            test_indices=test_indices,
            mask_paths=self._mask_paths(model.names),
            undistorted_dir=self._undistorted_dir(model)
            if any(s.needs_undistortion for s in sources.values())
            else None,
            cache_bytes=self.cache_mb * 2**20,
            metadata=self._metadata(),
        )

    def _image_dir(self) -> Path:
        downscaled = self.data / f"{self.images_dir}_{self.downscale}"
        if self.downscale > 1 and downscaled.is_dir():
            return downscaled
        image_dir = self.data / self.images_dir
        if not image_dir.is_dir():
            raise HicoError(f"{image_dir}: image folder not found (set --images-dir to the folder of the images)")
        return image_dir

    def _split(self, names: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
        """(train, test) LongTensors of view indices (views are sorted by name)."""
        if self.test_names:
            position = {name: i for i, name in enumerate(names)}
            unknown = [name for name in self.test_names if name not in position]
            if unknown:
                raise HicoError(f"--test-names: {unknown[:5]} are not registered images of the dataset")
            is_test = np.zeros(len(names), dtype=bool)
            is_test[[position[name] for name in self.test_names]] = True
        elif self.test_every > 0:
            is_test = np.arange(len(names)) % self.test_every == 0
        elif self.test_every == 0:
            is_test = np.zeros(len(names), dtype=bool)
        else:
            raise HicoError(
                f"--test-every: expected 0 (no test split) or a positive number, got {self.test_every}"
            )
        if is_test.all():
            field = "--test-names" if self.test_names else f"--test-every {self.test_every}"
            raise HicoError(f"{field}: the test split takes all {len(names)} images, leaving none to train on")
        return torch.from_numpy(np.flatnonzero(~is_test)), torch.from_numpy(np.flatnonzero(is_test))

    def _camera_source(self, camera) -> CameraSource:
        full_size = (camera.width, camera.height)
        pinhole = pinhole_of(camera)
        return CameraSource(
            full_size=full_size,
            model=camera.model.name,
            distorted=rescaled(camera, *_downscaled(full_size, self.downscale)),
            pinhole=rescaled(pinhole, *_downscaled((pinhole.width, pinhole.height), self.downscale)),
        )

    def _mask_paths(self, names: list[str]) -> list[Path | None]:
        mask_dir = self.data / "masks"
        if not self.masks or not mask_dir.is_dir():
            return [None] * len(names)
        paths = []
        for name in names:
            what = f"masks: mask of image '{name}'"
            candidates = (resolve_inside(mask_dir, f"{name}.png", what),
                          resolve_inside(mask_dir, Path(name).with_suffix(".png").as_posix(), what))
            paths.append(next((path for path in candidates if path.is_file()), None))
        return paths

    def _undistorted_dir(self, model: ColmapModel) -> Path:
        """A folder keyed by everything the undistorted pixels depend on."""
        key_source = json.dumps(
            [self.images_dir, self.downscale]
            + [
                [cid, c.model.name, c.width, c.height, list(map(float, c.params))]
                for cid, c in sorted(model.cameras.items())
            ]
        )
        key = hashlib.sha1(key_source.encode()).hexdigest()[:12]
        if self.cache_dir is not None:
            base = self.cache_dir
        elif os.access(self.data, os.W_OK):
            base = self.data / ".hico_cache"
        else:
            user_cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "hico_plugin"
            base = user_cache / hashlib.sha1(str(self.data.resolve()).encode()).hexdigest()[:12]
        return base / f"undistorted_{key}"

    def _metadata(self) -> dict[str, Any]:
        path = self.data / "scene.json"
        if not path.is_file():
            return {}
        try:
            metadata = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise HicoError(f"{path}: not valid JSON ({err})") from None
        if not isinstance(metadata, dict):
            raise HicoError(f"{path}: expected a JSON object")
        return metadata


def _downscaled(size: tuple[int, int], factor: int) -> tuple[int, int]:
    return max(1, round(size[0] / factor)), max(1, round(size[1] / factor))
