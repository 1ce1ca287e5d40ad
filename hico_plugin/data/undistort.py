"""Undistortion of SIMPLE_RADIAL / RADIAL / OPENCV cameras to pinhole ones.

The pinhole camera is COLMAP's own choice (its image undistorter's camera, ``UndistortCamera`` with
default options, computed here without pycolmap); the pixel lookup evaluates COLMAP's distortion model
(``Camera.img_from_cam``), so no convention is translated by hand. Both use COLMAP's pixel convention
(pixel centres at +0.5); OpenCV's ``remap`` wants centres at integers, hence the -0.5.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from hico_plugin.data.camera_model import INVALID_CAMERA_ID, Camera

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")
SUPPORTED_MODELS = PINHOLE_MODELS + DISTORTED_MODELS

# UndistortCameraOptions' defaults: no blank pixels, the scale change clamped to [0.2, 2].
_BLANK_PIXELS, _MIN_SCALE, _MAX_SCALE = 0.0, 0.2, 2.0


def rescaled(camera: Camera, width: int, height: int) -> Camera:
    """A copy of ``camera`` at ``width`` x ``height`` pixels."""
    out = dataclasses.replace(camera)
    if (width, height) != (camera.width, camera.height):
        out.rescale(width, height)
    return out


def pinhole_of(camera: Camera) -> Camera:
    """The PINHOLE camera images of ``camera`` are undistorted to (the camera itself if pinhole)."""
    if camera.model in PINHOLE_MODELS:
        return dataclasses.replace(camera)
    if camera.model not in DISTORTED_MODELS:  # a model only pycolmap evaluates (transforms.json's fisheye)
        import pycolmap

        return Camera.from_pycolmap(pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera.to_pycolmap()))
    return _undistorted_camera(camera)


def _undistorted_camera(camera: Camera) -> Camera:
    """COLMAP's UndistortCamera with default options: the focal lengths kept, the image resized so the
    undistorted border of the distorted image leaves no blank pixel (by at most the scale limits), the
    principal point scaled with the size."""
    width, height = camera.width, camera.height
    fx, fy = camera.focal_length_x, camera.focal_length_y
    cx, cy = np.float64(camera.principal_point_x), np.float64(camera.principal_point_y)
    rows, cols = np.arange(height) + 0.5, np.arange(width) + 0.5
    # the pixel centres of the left, right, top and bottom border, unprojected in one go
    borders = [np.stack([np.full(height, 0.5), rows], axis=-1), np.stack([np.full(height, width - 0.5), rows], axis=-1),
               np.stack([cols, np.full(width, 0.5)], axis=-1), np.stack([cols, np.full(width, height - 0.5)], axis=-1)]
    rays = np.split(camera.cam_from_img(np.concatenate(borders)), np.cumsum([len(b) for b in borders])[:-1])

    def extent(rays: np.ndarray, axis: int) -> tuple[np.float64, np.float64]:
        """(min, max) of coordinate ``axis`` where the pinhole camera puts ``rays`` [N, 2]; rays COLMAP
        could not unproject (NaN) or whose norm overflows are left out."""
        with np.errstate(over="ignore"):
            rays = rays[rays[:, 0] * rays[:, 0] + rays[:, 1] * rays[:, 1] < np.inf]
        coordinate = (fx, fy)[axis] * rays[:, axis] + (cx, cy)[axis]
        return (np.min(coordinate, initial=np.finfo(np.float64).max),
                np.max(coordinate, initial=np.finfo(np.float64).min))

    (left_min_x, left_max_x), (right_min_x, right_max_x) = extent(rays[0], 0), extent(rays[1], 0)
    (top_min_y, top_max_y), (bottom_min_y, bottom_max_y) = extent(rays[2], 1), extent(rays[3], 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        # the scale that keeps every distorted pixel, and the one that leaves no blank pixel
        min_scale_x = _min(cx / (cx - left_min_x), (width - 0.5 - cx) / (right_max_x - cx))
        min_scale_y = _min(cy / (cy - top_min_y), (height - 0.5 - cy) / (bottom_max_y - cy))
        max_scale_x = _max(cx / (cx - left_max_x), (width - 0.5 - cx) / (right_min_x - cx))
        max_scale_y = _max(cy / (cy - top_max_y), (height - 0.5 - cy) / (bottom_min_y - cy))
        scale_x = 1.0 / (min_scale_x * _BLANK_PIXELS + max_scale_x * (1.0 - _BLANK_PIXELS))
        scale_y = 1.0 / (min_scale_y * _BLANK_PIXELS + max_scale_y * (1.0 - _BLANK_PIXELS))
    scale_x = _max(np.float64(_MIN_SCALE), _min(scale_x, np.float64(_MAX_SCALE)))
    scale_y = _max(np.float64(_MIN_SCALE), _min(scale_y, np.float64(_MAX_SCALE)))
    new_width, new_height = int(_max(np.float64(1.0), scale_x * width)), int(_max(np.float64(1.0), scale_y * height))
    return Camera(camera_id=INVALID_CAMERA_ID, model="PINHOLE", width=new_width, height=new_height,
                  params=[fx, fy, cx * new_width / width, cy * new_height / height])


def _min(a: np.float64, b: np.float64) -> np.float64:
    """std::min: ``a`` unless ``b`` is smaller (a NaN ``b`` is passed over, a NaN ``a`` kept)."""
    return b if b < a else a


def _max(a: np.float64, b: np.float64) -> np.float64:
    """std::max: ``a`` unless ``b`` is larger."""
    return b if a < b else a


def undistortion_maps(distorted: Camera, pinhole: Camera) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps [H', W'] float32 (x, y): where each pinhole pixel reads the distorted image."""
    fx, fy, cx, cy = pinhole.focal_length_x, pinhole.focal_length_y, pinhole.principal_point_x, pinhole.principal_point_y
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


def calibration_matrix(camera: Camera) -> np.ndarray:
    """[3, 3] K of a pinhole camera (COLMAP's pixel convention, as ``hico_plugin.cameras`` uses)."""
    fx, fy, cx, cy = camera.focal_length_x, camera.focal_length_y, camera.principal_point_x, camera.principal_point_y
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
