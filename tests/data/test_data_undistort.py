"""How far a camera's distortion moves pixels from its pinhole twin."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from hico_plugin.data.undistort import max_distortion_px, pinhole_twin


def test_max_distortion_is_the_corner_shift_of_a_radial_camera():
    # SIMPLE_RADIAL f=100, principal point (100, 50), k=0.01 on 200x100: the corner's ray (-1, -0.5)
    # has r^2 = 1.25 and lands at (1 + k r^2) times its pinhole position, so it moves by
    # f * k * r^2 * r = 100 * 0.0125 * sqrt(1.25) = 1.3975 px, the most of any pixel (radial, growing).
    camera = pycolmap.Camera.create_from_model_name(3, "SIMPLE_RADIAL", 100.0, 200, 100)
    camera.params = [100.0, 100.0, 50.0, 0.01]
    assert max_distortion_px(camera) == pytest.approx(100 * 0.0125 * np.sqrt(1.25), rel=1e-9)
    twin = pinhole_twin(camera)
    assert (twin.camera_id, twin.model.name, twin.width, twin.height) == (3, "PINHOLE", 200, 100)
    assert np.allclose(twin.params, [100.0, 100.0, 100.0, 50.0])
    assert max_distortion_px(twin) == 0.0


def test_a_fisheye_is_never_near_pinhole():
    """Equidistant projection (theta, not tan theta) even with zero coefficients."""
    camera = pycolmap.Camera.create_from_model_name(1, "OPENCV_FISHEYE", 100.0, 200, 100)
    assert max_distortion_px(camera) > 10
