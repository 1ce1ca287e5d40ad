"""The pinhole camera a distorted one is undistorted to is COLMAP's (pycolmap.undistort_camera), and the
remap reads where COLMAP's distortion puts each pinhole pixel."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from hico_plugin.data.camera_model import Camera
from hico_plugin.data.undistort import DISTORTED_MODELS, pinhole_of, rescaled, undistortion_maps
from helpers_cameras import random_camera

# instant-ngp's fox (data/nerf/fox/transforms.json): a phone's OPENCV camera, portrait
FOX = Camera(model="OPENCV", width=1080, height=1920,
             params=[1375.52, 1374.49, 554.558, 965.268, 0.0578421, -0.0805099, -0.000980296, 0.00015575])


def colmaps_pinhole(camera: Camera) -> pycolmap.Camera:
    return pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera.to_pycolmap())


def assert_same_pinhole(camera: Camera) -> None:
    ours, theirs = pinhole_of(camera), colmaps_pinhole(camera)
    assert (ours.model, ours.width, ours.height, ours.camera_id) == (
        theirs.model.name, theirs.width, theirs.height, theirs.camera_id), camera
    assert np.allclose(ours.params, theirs.params, rtol=1e-6, atol=0), camera


@pytest.mark.parametrize("model", DISTORTED_MODELS)
def test_pinhole_is_colmaps_choice(model):
    """Random realistic cameras (k up to +-0.3) in landscape, square and portrait images."""
    rng = np.random.default_rng(DISTORTED_MODELS.index(model))
    for aspect in (16 / 9, 4 / 3, 1.0, 3 / 4, 9 / 16, 2.0):
        for _ in range(12):
            camera = random_camera(rng, model)
            width = camera.width
            camera.rescale(width, max(16, round(width / aspect)))
            assert_same_pinhole(camera)


def test_pinhole_of_the_fox_is_colmaps():
    assert_same_pinhole(FOX)
    assert (pinhole_of(FOX).width, pinhole_of(FOX).height) == (1067, 1897)


def test_pinhole_camera_is_its_own_pinhole_and_rescaled_copies():
    camera = Camera(camera_id=2, model="SIMPLE_PINHOLE", width=200, height=100, params=[90.0, 100.0, 50.0])
    same = pinhole_of(camera)
    assert same is not camera and same.todict().keys() == camera.todict().keys()
    assert (same.camera_id, same.model, same.width, same.height) == (2, "SIMPLE_PINHOLE", 200, 100)
    half = rescaled(camera, 100, 50)
    assert (half.width, half.height, camera.width) == (100, 50, 200)
    assert np.array_equal(half.params, [45.0, 50.0, 25.0]) and np.array_equal(camera.params, [90.0, 100.0, 50.0])


def test_a_fisheye_goes_to_pycolmaps_undistorter():
    camera = Camera(model="OPENCV_FISHEYE", width=320, height=240, params=[150, 150, 160, 120, 0.05, 0.0, 0.0, 0.0])
    assert_same_pinhole(camera)


def test_undistortion_maps_read_where_colmap_projects():
    pinhole = pinhole_of(FOX)
    ys, xs = np.mgrid[: pinhole.height, : pinhole.width]
    rays = np.stack([(xs.ravel() + 0.5 - pinhole.principal_point_x) / pinhole.focal_length_x,
                     (ys.ravel() + 0.5 - pinhole.principal_point_y) / pinhole.focal_length_y,
                     np.ones(xs.size)], axis=-1)
    expected = (FOX.to_pycolmap().img_from_cam(rays) - 0.5).astype(np.float32)
    map_x, map_y = undistortion_maps(FOX, pinhole)
    assert np.array_equal(map_x.ravel(), expected[:, 0]) and np.array_equal(map_y.ravel(), expected[:, 1])
