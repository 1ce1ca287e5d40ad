"""The indoor room: a closed room with no sky, cameras inside it, sparse points only where texture is."""

from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest

from hico_plugin.errors import HicoError
from hico_plugin.scenes import SCENES
from hico_plugin.scenes.generate import generate_scene, scene_config

TWIN = dict(num_views=24, width=128, height=96, pixel_samples=1)


def test_room_is_a_closed_room_seen_from_inside(tmp_path):
    path = generate_scene("room", tmp_path / "room", **TWIN)
    meta = json.loads((path / "scene.json").read_text())
    assert "room" in SCENES.names() and meta["declared_effects"] == ["exposure"]
    assert meta["timings_s"]["total"] < 10
    depths = np.stack([np.load(f) for f in sorted((path / "ground_truth" / "depth").glob("*.npy"))])
    assert depths.shape == (24, 96, 128) and (depths > 0).all()  # every ray meets a wall, the floor or the ceiling
    config = scene_config("room")
    half = np.array(config.size[:2]) / 2
    rec = pycolmap.Reconstruction(str(path / "sparse" / "0"))
    centres = np.array([image.projection_center() for image in rec.images.values()])
    assert (np.abs(centres[:, :2]) < half).all() and (centres[:, 2] < config.size[2]).all()
    # SfM-like points: on the flowers of the paper, the floor's grain and the bust, not on the smooth ceiling
    xyz = np.array([point.xyz for point in rec.points3D.values()])
    on_ceiling = (xyz[:, 2] > config.size[2] - 0.05) & (np.abs(xyz[:, :2]) < half - 0.2).all(axis=1)
    on_walls = (np.abs(xyz[:, :2]) > half - 0.05).any(axis=1)
    assert on_walls.mean() > 0.5 and on_ceiling.mean() < 0.005, (on_walls.mean(), on_ceiling.mean())


def test_cameras_outside_the_room_are_refused(tmp_path):
    with pytest.raises(HicoError, match="orbit_radius 2.5 puts cameras in or behind the walls"):
        generate_scene("room", tmp_path / "room", orbit_radius=2.5, **TWIN)
