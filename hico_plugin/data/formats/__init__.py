"""Dataset formats: each reads one on-disk layout into a ``SceneRecord`` (cameras in COLMAP's conventions, OpenCV
axes), and registers itself in ``DATA_FORMATS``.

A format is a dataclass config with ``detect(data_dir) -> bool`` and ``read(data_dir) -> SceneRecord``; ``--data
DIR`` takes the first registered format whose ``detect`` accepts DIR unless one is named as a subcommand (``--data
DIR transforms``). An outside package adds a layout, and its subcommand, with
``@DATA_FORMATS.register("my-layout")`` on a ``DataFormat`` dataclass (``tests/plugin_example/``).
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hico_plugin.data.camera_model import Camera
from hico_plugin.registry import Registry


@dataclass
class SceneRecord:
    """What a format reads: views sorted by name, cameras with their distortion, poses, seed points."""

    names: list[str]  # [N] view names (unique; also the undistortion cache's file names)
    image_paths: list[Path]  # [N] full-resolution image files, inside the dataset folder
    camera_ids: list[int]  # [N] camera of each view
    cameras: dict[int, Camera]  # any COLMAP model; undistorted to pinhole on load
    viewmats: np.ndarray  # [N, 4, 4] float64 world->camera, OpenCV axes (x right, y down, z forward)
    points: np.ndarray  # [P, 3] float64 seed points in the same world frame
    point_colors: np.ndarray  # [P, 3] uint8
    # A layout without a point cloud leaves points empty and gives this instead: (notes, long side in px
    # the photos load at) -> (points, colors), called by the parser once it has chosen that size
    seed_points_at: Callable[[list[str], int], tuple[np.ndarray, np.ndarray]] | None = None
    mask_paths: list[Path | None] | None = None  # [N] white = keep; None: the default masks/ folder
    depth_paths: list[Path | None] | None = None  # [N] metric depth maps (.npy/.png) when the format has them
    tracks: Any = None  # SfM tracks (data.colmap.SfmTracks) when the format has them, for analyses
    test_names: list[str] | None = None  # the layout's own held-out views (Mega-NeRF val/); replaces --test-every
    has_ground_truth: bool = False  # DIR/ground_truth holds exact depth / normals / surface points
    notes: list[str] = field(default_factory=list)  # warnings to print once (missing frames, random points)


@dataclass
class DataFormat:
    """Base of a registered dataset format config."""

    def detect(self, data_dir: Path) -> bool:
        raise NotImplementedError

    def read(self, data_dir: Path) -> SceneRecord:
        raise NotImplementedError


DATA_FORMATS: Registry[type[DataFormat]] = Registry("dataset format")


# Every module of this package registers its format on import, so a new built-in format is one file here.
for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")
