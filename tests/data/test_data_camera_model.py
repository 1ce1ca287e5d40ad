"""The plain camera against pycolmap's: every method, the five models it evaluates, random parameters."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from hico_plugin.data.camera_model import MODEL_NAMES, NUM_PARAMS, Camera
from helpers_cameras import random_camera

MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def close(ours: np.ndarray, theirs: np.ndarray, tolerance: float = 1e-9) -> bool:
    """Equal NaNs, and the other entries equal to ``tolerance`` relative (absolute below 1)."""
    if not np.array_equal(np.isnan(ours), np.isnan(theirs)):
        return False
    finite = ~np.isnan(theirs)
    return bool((np.abs(ours[finite] - theirs[finite]) <= tolerance * np.maximum(1.0, np.abs(theirs[finite]))).all())


@pytest.mark.parametrize("model", MODELS)
def test_every_method_agrees_with_pycolmap(model):
    rng = np.random.default_rng(MODELS.index(model))
    for _ in range(40):
        ours = random_camera(rng, model)
        theirs = ours.to_pycolmap()
        assert (ours.focal_length_x, ours.focal_length_y, ours.principal_point_x, ours.principal_point_y) == (
            theirs.focal_length_x, theirs.focal_length_y, theirs.principal_point_x, theirs.principal_point_y)
        # points in front, on and behind the camera (NaN there, as pycolmap)
        points = np.concatenate([rng.uniform(-1.0, 1.0, (400, 2)), rng.uniform(-0.2, 2.0, (400, 1))], axis=1)
        points[:5, 2] = [0.0, 1e-17, -1.0, 1e-3, 5.0]
        assert close(ours.img_from_cam(points), theirs.img_from_cam(points))
        normalised = rng.uniform(-0.8, 0.8, (50, 2))
        assert close(ours.img_from_cam(normalised), theirs.img_from_cam(np.concatenate([normalised, np.ones((50, 1))], 1)))
        # pixels inside and well outside the image: the iteration converges, or fails, where COLMAP's does
        pixels = rng.uniform(-0.3, 1.3, (600, 2)) * [ours.width, ours.height]
        assert close(ours.cam_from_img(pixels), theirs.cam_from_img(pixels))
        width, height = (int(v) for v in rng.integers(16, 3000, 2))
        ours.rescale(width, height)
        theirs.rescale(width, height)
        assert (ours.width, ours.height) == (theirs.width, theirs.height)
        assert close(ours.params, theirs.params, 1e-15)


def test_cam_from_img_inverts_img_from_cam():
    camera = Camera(model="OPENCV", width=640, height=480, params=[500, 510, 320, 240, -0.25, 0.08, 0.002, -0.001])
    rays = np.random.default_rng(0).uniform(-0.6, 0.6, (1000, 2))
    assert np.abs(camera.cam_from_img(camera.img_from_cam(rays)) - rays).max() < 1e-9


def test_todict_has_pycolmaps_keys_and_values_and_round_trips():
    camera = random_camera(np.random.default_rng(1), "OPENCV", camera_id=3)
    ours, theirs = camera.todict(), camera.to_pycolmap().todict()
    assert ours.keys() == theirs.keys()
    theirs["model"] = theirs["model"].name
    for key, value in theirs.items():
        assert np.array_equal(ours[key], value), key
    back = Camera.from_pycolmap(camera.to_pycolmap())
    assert back.todict().keys() == ours.keys()
    assert all(np.array_equal(back.todict()[key], value) for key, value in ours.items())
    assert back.params.dtype == np.float64 and back.params is not camera.params


def test_model_table_is_pycolmaps():
    for model_id, name in enumerate(MODEL_NAMES):
        assert pycolmap.CameraModelId(model_id).name == name
        assert len(pycolmap.Camera.create_from_model_name(1, name, 100.0, 10, 10).params) == NUM_PARAMS[name]


def test_other_models_are_evaluated_by_pycolmap():
    """transforms.json's OPENCV_FISHEYE and FULL_OPENCV cameras: evaluated through pycolmap."""
    for model, params in (("OPENCV_FISHEYE", [300, 310, 320, 240, 0.1, -0.05, 0.01, 0.0]),
                          ("FULL_OPENCV", [300, 310, 320, 240, -0.1, 0.05, 0.001, 0.0, 0.01, 0.0, 0.0, 0.0])):
        ours = Camera(model=model, width=640, height=480, params=params)
        theirs = ours.to_pycolmap()
        points = np.random.default_rng(0).uniform(0.1, 1.0, (20, 3))
        assert np.array_equal(ours.img_from_cam(points), theirs.img_from_cam(points))
        pixels = points[:, :2] * 500
        assert np.array_equal(ours.cam_from_img(pixels), theirs.cam_from_img(pixels), equal_nan=True)


def test_bad_model_or_parameter_count_is_refused():
    with pytest.raises(ValueError, match="unknown COLMAP camera model"):
        Camera(model="PINHOLES", width=10, height=10, params=[1, 1, 5, 5])
    with pytest.raises(ValueError, match="PINHOLE takes 4 parameters"):
        Camera(model="PINHOLE", width=10, height=10, params=[1, 5, 5])
