"""``DataParserConfig``: a dataset directory in any registered format -> ``Dataset``."""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Any, Literal, Optional

import numpy as np
import torch
import tyro

from hico_plugin import storage
from hico_plugin.cameras import Cameras
from hico_plugin.config import InstantiateConfig
from hico_plugin.data.camera_model import Camera
from hico_plugin.data.checks import MIN_LOADED_SIZE, check_image_sizes
from hico_plugin.data.dataset import CameraSource, Dataset
from hico_plugin.data.formats import DATA_FORMATS, DataFormat, SceneRecord
from hico_plugin.data.images import MAX_LONG_SIDE, downscale_factor
from hico_plugin.data.paths import resolve_inside
from hico_plugin.data.splits import extrapolation_split, sparse_views
from hico_plugin.data.transform import SceneTransform, frame_differences
from hico_plugin.data.undistort import calibration_matrix, pinhole_of, rescaled
from hico_plugin.errors import HicoError

# A dataset format named on the command line (``hico-train ... --data DIR transforms --file x.json``), one
# subcommand per registered format, installed plug-ins' included; None = detect. tyro asks for the
# subcommands when it parses, not at import: reading the registry loads plug-ins, which may import this module.
FormatChoice = Annotated[Optional[DataFormat], tyro.conf.OmitArgPrefixes, tyro.conf.arg(constructor_factory=lambda: Optional[
    DATA_FORMATS.subcommands()])]


def detect_format(data_dir: Path) -> DataFormat:
    """The first registered format, by name, whose ``detect`` accepts DIR (colmap before transforms:
    nerfstudio's COLMAP output holds both, and sparse/0 carries the points)."""
    for _, candidate in sorted(DATA_FORMATS.defaults().items()):
        if candidate.detect(data_dir):
            return candidate
    raise HicoError(
        f"data directory {data_dir}: no known dataset layout (expected sparse/0 (COLMAP), transforms.json "
        f"(nerfstudio / instant-ngp), train/ + val/ with rgbs/ and metadata/ (Mega-NeRF); registered formats: "
        f"{', '.join(DATA_FORMATS.names())}). For plain photos run: hico-process images {data_dir} --output OUT"
    )


@dataclass
class DataParserConfig(InstantiateConfig):
    """A dataset directory: COLMAP, nerfstudio / instant-ngp transforms.json, Mega-NeRF or hico-process output
    (detected, or named with a format subcommand); optional DIR/masks and DIR/ground_truth."""

    data: Path = Path("data")
    """Dataset directory."""
    format: FormatChoice = None
    """Dataset layout; default: detected from the directory's contents."""
    downscale: int = 0
    """Load images at 1/N resolution (from <images>_N/ when it exists, else resized on load); 0 = the
    smallest power of two that brings the long side to --max-long-side."""
    max_long_side: int = MAX_LONG_SIDE
    """Longest image side in pixels that --downscale 0 aims for (nerfstudio's default; hico-process
    extracts features at the size this loads the photos at)."""
    test_every: int = 8
    """Every Nth view (sorted by name, index % N == 0) goes to the test split; 0 = no test split. A
    layout with its own held-out views (Mega-NeRF val/) uses those instead."""
    test_names: tuple[str, ...] = ()
    """Explicit test image names; when given, they replace --test-every."""
    test_list: Optional[Path] = None
    """A text file of test image names, one a line (replaces --test-every)."""
    split: Literal["interleaved", "extrapolate"] = "interleaved"
    """interleaved: --test-every / --test-names; extrapolate: the 1/test-every views at one end of the
    cameras' principal axis, with a gap of unused views so that every test camera is farther from the
    training cameras than any training camera from its neighbour (data/splits.py)."""
    train_every: int = 1
    """Sparse views: train on every Nth training view only (e.g. 4)."""
    masks: bool = True
    """Use the format's masks, or DIR/masks/<name>.png (white = keep) when it exists."""
    normalize: bool = True
    """Centre on the mean camera centre and scale the farthest camera to distance 1, so the scene's
    units (mm or km) do not matter."""
    orient: bool = True
    """With --normalize: rotate the scene so its vertical (the direction perpendicular to the cameras'
    right axes, level in hand-held and drone photos) is +z, whatever the source's axes (the sky and
    ground effects and the viewer assume z-up). Outputs are mapped back."""
    orient_method: Literal["manhattan", "vertical", "up"] = "manhattan"
    """How --orient turns the scene: "vertical", its vertical (perpendicular to the cameras' right axes,
    nerfstudio's name) to +z; "manhattan", that and its walls (the dominant vertical planes of the
    sparse points) onto x and y, so the anchor grid runs along them whatever the source's axes; "up",
    the cameras' mean up to +z (it leans toward where they look; how older runs were turned)."""
    cache_mb: int = 512
    """Budget of the in-memory cache of decoded images (LRU, in MB); 512 holds about 90 photos at
    1600x1200. A larger capture decodes the rest again when drawn, which costs little beside a step."""
    cache_dir: Optional[Path] = None
    """Where undistorted images are cached; default $HICO_CACHE_DIR/datasets/<hash of DIR>
    (~/.cache/hico_plugin/...), never inside the dataset folder."""

    def __post_init__(self) -> None:
        # accept plain strings from Python callers and YAML configs
        self.data = Path(self.data)
        self.cache_dir = Path(self.cache_dir) if self.cache_dir is not None else None
        self.test_list = Path(self.test_list) if self.test_list is not None else None
        self.test_names = tuple(self.test_names)

    def setup(self, announce: bool = True, frame: dict | None = None, **kwargs: Any) -> Dataset:
        return self.parse(announce, frame)

    def validate(self) -> None:
        """A HicoError for an argument that is wrong whatever the dataset holds: checked before the
        dataset is read (and by hico-train before it takes the run directory)."""
        if self.data is not None and not self.data.is_dir():  # None: a built-in scene (DataSourceConfig)
            raise HicoError(f"data directory {self.data}: not found (expected a dataset folder, e.g. images/ + sparse/0)")
        if self.downscale < 0:
            raise HicoError(f"--downscale: expected 0 (auto) or a whole number >= 1, got {self.downscale}")
        if self.test_every < 0:
            raise HicoError(f"--test-every: expected 0 (no test split) or a positive number, got {self.test_every}")
        if self.split not in ("interleaved", "extrapolate"):
            raise HicoError(f"--split: expected interleaved or extrapolate, got '{self.split}'")
        if self.orient_method not in ("manhattan", "vertical", "up"):
            raise HicoError(f"--orient-method: expected manhattan, vertical or up, got '{self.orient_method}'")

    def parse(self, announce: bool = True, frame: dict | None = None) -> Dataset:
        """Read, check and normalise the dataset; images stay on disk until first used. Its notes (frames skipped,
        the automatic downscale, ...) are printed when ``announce`` and kept in ``Dataset.notes``.

        ``frame``: the scene frame a checkpoint was trained in (``Dataset.frame()``): the views load in it when
        today's normalisation places the cameras the same (``frame_differences``), else in today's, which the
        caller's ``check_frame`` then refuses."""
        self.validate()
        data_dir = self.data
        record = (self.format or detect_format(data_dir)).read(data_dir)
        notes = list(record.notes)
        missing = [str(path) for path in record.image_paths if not path.is_file()]
        if missing:
            raise HicoError(
                f"{missing[0]}: image listed in the dataset but not on disk ({len(missing)} of {len(record.image_paths)} missing)"
            )
        downscale = self.downscale or self._auto_downscale(record, notes)
        image_paths = [self._downscaled_path(path, downscale) for path in record.image_paths]
        train_indices, test_indices = self._split(record.names, record.test_names)
        if self.split == "extrapolate":
            rotations, translations = record.viewmats[:, :3, :3], record.viewmats[:, :3, 3:]
            centres = -(np.transpose(rotations, (0, 2, 1)) @ translations)[..., 0]
            train_indices, test_indices = extrapolation_split(centres, self.test_every)
        train_indices = sparse_views(train_indices, self.train_every)

        sources = {cid: self._camera_source(camera, downscale) for cid, camera in record.cameras.items()}
        for camera_id, source in sources.items():  # the size training sees, after --downscale
            width, height = source.pinhole.width, source.pinhole.height
            if min(width, height) < MIN_LOADED_SIZE:
                raise HicoError(f"{data_dir}: camera {camera_id} loads at {width}x{height} px; expected "
                                f"at least {MIN_LOADED_SIZE}x{MIN_LOADED_SIZE} (lower --downscale)")
        check_image_sizes(image_paths, [sources[camera_id].full_size for camera_id in record.camera_ids])
        if record.seed_points_at is not None:  # the slow step, once every check above has passed
            long_side = _long_side(record)  # at the loading size, the rule _downscaled applies to the photos
            points, colors = record.seed_points_at(notes, max(_downscaled((long_side, long_side), downscale)))
            record = replace(record, points=points, point_colors=colors, seed_points_at=None)
        if len(record.points) == 0:
            raise HicoError(f"{data_dir}: the dataset has no seed points (expected a point cloud, e.g. "
                            "sparse/0/points3D with points, or transforms.json's ply_file_path)")
        viewmats_world = torch.from_numpy(record.viewmats)
        points_world = torch.from_numpy(record.points)
        transform = SceneTransform.identity()
        if self.normalize:
            transform = SceneTransform.from_cameras(viewmats_world, points=points_world, orient=self.orient,
                                                    orient_method=self.orient_method)
        if frame is not None and not frame_differences(frame, transform.to_dict()):
            transform = SceneTransform.from_dict(frame)
        pinholes = [sources[camera_id].pinhole for camera_id in record.camera_ids]
        cameras = Cameras(
            viewmats=transform.viewmats_from_colmap(viewmats_world).to(torch.float32),
            Ks=torch.from_numpy(np.stack([calibration_matrix(camera) for camera in pinholes])).to(torch.float32),
            widths=torch.tensor([camera.width for camera in pinholes], dtype=torch.int64),
            heights=torch.tensor([camera.height for camera in pinholes], dtype=torch.int64),
        )
        dataset = Dataset(
            data_dir=data_dir,
            image_names=record.names,
            image_paths=image_paths,
            camera_ids=record.camera_ids,
            sources=sources,
            cameras=cameras,
            transform=transform,
            points=transform.points_from_colmap(points_world).to(torch.float32),
            point_colors=torch.from_numpy(record.point_colors),
            train_indices=train_indices,
            test_indices=test_indices,
            mask_paths=self._mask_paths(record),
            undistorted_dir=self._undistorted_dir(record, downscale)
            if any(s.needs_undistortion for s in sources.values())
            else None,
            cache_bytes=self.cache_mb * 2**20,
            metadata=self._metadata(),
            tracks=record.tracks,
            depth_paths=record.depth_paths,
            notes=notes,
        )
        if announce:
            for note in notes:
                print(note, file=sys.stderr)
        return dataset

    def _auto_downscale(self, record: SceneRecord, notes: list[str]) -> int:
        long_side = _long_side(record)
        factor = downscale_factor(long_side, self.max_long_side)
        if factor > 1:
            notes.append(f"downscale: images have a {long_side} px long side; loading at 1/{factor} "
                         f"(--max-long-side {self.max_long_side}; --downscale 1 keeps full resolution)")
        return factor

    def _downscaled_path(self, path: Path, factor: int) -> Path:
        """``DIR/<folder>_N/<rest>`` when it exists (nerfstudio's images_N layout), else ``path``."""
        if factor == 1:
            return path
        parts = path.relative_to(self.data).parts
        candidate = self.data / f"{parts[0]}_{factor}" / Path(*parts[1:]) if len(parts) > 1 else None
        return candidate if candidate is not None and candidate.is_file() else path

    def _split(self, names: list[str], layout_test_names: list[str] | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(train, test) LongTensors of view indices (views are sorted by name). The layout's own
        held-out views (Mega-NeRF val/), when it has them, replace --test-every; --test-names and
        --test-list replace both."""
        test_names = self.test_names
        if self.test_list is not None:
            try:
                test_names = tuple(line.strip() for line in self.test_list.read_text().splitlines() if line.strip())
            except OSError as err:
                raise HicoError(f"--test-list {self.test_list}: cannot be read ({err.strerror or err})") from None
        if not test_names and self.test_list is None and layout_test_names:
            test_names = tuple(layout_test_names)
        if test_names:
            position = {name: i for i, name in enumerate(names)}
            unknown = [name for name in test_names if name not in position]
            if unknown:
                field = "--test-list" if self.test_list is not None else "--test-names"
                raise HicoError(f"{field}: {unknown[:5]} are not registered images of the dataset")
            is_test = np.zeros(len(names), dtype=bool)
            is_test[[position[name] for name in test_names]] = True
        elif self.test_every > 0:
            is_test = np.arange(len(names)) % self.test_every == 0
        else:  # 0 (validate refused a negative one)
            is_test = np.zeros(len(names), dtype=bool)
        if is_test.all():
            field = "--test-names" if self.test_names else f"--test-every {self.test_every}"
            raise HicoError(f"{field}: the test split takes all {len(names)} images, leaving none to train on")
        return torch.from_numpy(np.flatnonzero(~is_test)), torch.from_numpy(np.flatnonzero(is_test))

    def _camera_source(self, camera: Camera, downscale: int) -> CameraSource:
        full_size = (camera.width, camera.height)
        pinhole = pinhole_of(camera)
        return CameraSource(
            full_size=full_size,
            model=camera.model,
            distorted=rescaled(camera, *_downscaled(full_size, downscale)),
            pinhole=rescaled(pinhole, *_downscaled((pinhole.width, pinhole.height), downscale)),
        )

    def _mask_paths(self, record: SceneRecord) -> list[Path | None]:
        if not self.masks:
            return [None] * len(record.names)
        if record.mask_paths is not None:
            missing = [str(path) for path in record.mask_paths if path is not None and not path.is_file()]
            if missing:
                raise HicoError(f"{missing[0]}: mask listed in the dataset but not on disk ({len(missing)} missing)")
            return list(record.mask_paths)
        mask_dir = self.data / "masks"
        if not mask_dir.is_dir():
            return [None] * len(record.names)
        paths = []
        for name in record.names:
            what = f"masks: mask of image '{name}'"
            candidates = (resolve_inside(mask_dir, f"{name}.png", what),
                          resolve_inside(mask_dir, Path(name).with_suffix(".png").as_posix(), what))
            paths.append(next((path for path in candidates if path.is_file()), None))
        return paths

    def _undistorted_dir(self, record: SceneRecord, downscale: int) -> Path:
        """A folder keyed by everything the undistorted pixels depend on."""
        key_source = json.dumps(
            [str(record.image_paths[0].parent.relative_to(self.data)), downscale]
            + [
                [cid, c.model, c.width, c.height, list(map(float, c.params))]
                for cid, c in sorted(record.cameras.items())
            ]
        )
        key = hashlib.sha1(key_source.encode()).hexdigest()[:12]
        if self.cache_dir is not None:
            base = self.cache_dir
        else:  # never inside the user's dataset folder: it may be shared, versioned or read-only
            base = storage.cache_dir("datasets") / hashlib.sha1(str(self.data.resolve()).encode()).hexdigest()[:12]
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


def _long_side(record: SceneRecord) -> int:
    """The longest side, in pixels, of the record's full-resolution photos."""
    return max(max(camera.width, camera.height) for camera in record.cameras.values())
