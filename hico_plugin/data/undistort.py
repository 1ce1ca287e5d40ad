"""Undistortion of SIMPLE_RADIAL / RADIAL / OPENCV cameras to pinhole ones.

The pinhole camera is COLMAP's own choice (``pycolmap.undistort_camera``, the image undistorter's
camera); the pixel lookup evaluates COLMAP's distortion model itself (``Camera.img_from_cam``), so no
convention is translated by hand. Both use COLMAP's pixel convention (pixel centres at +0.5); OpenCV's
``remap`` wants centres at integers, hence the -0.5.
"""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")
SUPPORTED_MODELS = PINHOLE_MODELS + DISTORTED_MODELS


def copy_camera(camera: pycolmap.Camera) -> pycolmap.Camera:
    return pycolmap.Camera(camera.todict())


def rescaled(camera: pycolmap.Camera, width: int, height: int) -> pycolmap.Camera:
    """A copy of ``camera`` at ``width`` x ``height`` pixels."""
    out = copy_camera(camera)
    if (width, height) != (camera.width, camera.height):
        out.rescale(width, height)
    return out


def pinhole_of(camera: pycolmap.Camera) -> pycolmap.Camera:
    """The PINHOLE camera images of ``camera`` are undistorted to (the camera itself if pinhole)."""
    if camera.model.name in PINHOLE_MODELS:
        return copy_camera(camera)
    return pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera)


def pinhole_twin(camera: pycolmap.Camera) -> pycolmap.Camera:
    """A PINHOLE camera with ``camera``'s id, size, focal lengths and principal point: its distortion dropped."""
    twin = pycolmap.Camera.create_from_model_name(camera.camera_id, "PINHOLE", 1.0, camera.width, camera.height)
    twin.params = [camera.focal_length_x, camera.focal_length_y, camera.principal_point_x, camera.principal_point_y]
    return twin


def max_distortion_px(camera: pycolmap.Camera, samples: int = 65) -> float:
    """The largest distance, in pixels, between where ``camera`` and its ``pinhole_twin`` put the same
    ray, over a ``samples`` x ``samples`` grid spanning the whole image (its edges, corners included).
    The grid points are the twin's pixels; COLMAP's distortion models are smooth over the image, so
    the grid's maximum is the image's to well under a pixel. A ray the model cannot place counts as
    infinitely far (such a camera is never taken for a pinhole one)."""
    fx, fy = camera.focal_length_x, camera.focal_length_y
    cx, cy = camera.principal_point_x, camera.principal_point_y
    grid_x, grid_y = np.meshgrid(np.linspace(0.0, camera.width, samples), np.linspace(0.0, camera.height, samples))
    rays = np.stack([(grid_x.ravel() - cx) / fx, (grid_y.ravel() - cy) / fy, np.ones(grid_x.size)], axis=-1)
    moved = camera.img_from_cam(rays)
    distance = np.hypot(moved[:, 0] - grid_x.ravel(), moved[:, 1] - grid_y.ravel())
    return float(np.nan_to_num(distance, nan=np.inf).max())


def undistortion_maps(distorted: pycolmap.Camera, pinhole: pycolmap.Camera) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps [H', W'] float32 (x, y): where each pinhole pixel reads the distorted image."""
    fx, fy, cx, cy = _pinhole_params(pinhole)
    xs = (np.arange(pinhole.width) + 0.5 - cx) / fx
    ys = (np.arange(pinhole.height) + 0.5 - cy) / fy
    grid_x, grid_y = np.meshgrid(xs, ys)
    rays = np.stack([grid_x.ravel(), grid_y.ravel(), np.ones(grid_x.size)], axis=-1)
    pixels = distorted.img_from_cam(rays) - 0.5
    shape = (pinhole.height, pinhole.width)
    return pixels[:, 0].reshape(shape).astype(np.float32), pixels[:, 1].reshape(shape).astype(np.float32)


def remap(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray], nearest: bool = False) -> np.ndarray:
    """``image`` [H, W, ...] (distorted) -> [H', W', ...] (pinhole); zeros outside the source."""
    interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    out = cv2.remap(image, maps[0], maps[1], interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.reshape(*maps[0].shape, *image.shape[2:])


def _pinhole_params(camera: pycolmap.Camera) -> tuple[float, float, float, float]:
    params = camera.params
    if camera.model.name == "SIMPLE_PINHOLE":
        return params[0], params[0], params[1], params[2]
    return params[0], params[1], params[2], params[3]


def calibration_matrix(camera: pycolmap.Camera) -> np.ndarray:
    """[3, 3] K of a pinhole camera (COLMAP's pixel convention, as ``hico_plugin.cameras`` uses)."""
    fx, fy, cx, cy = _pinhole_params(camera)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
