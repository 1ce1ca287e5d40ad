"""The undistort stage: registered photos -> OUT/images, OUT/masks and the PINHOLE model OUT/sparse/0.

Resampling blurs (an undistorter's bilinear lookup is a low-pass filter: Parker, Kenyon & Troxel, "Comparison of
interpolating methods for image resampling", IEEE TMI 1983), so a camera whose distortion moves no pixel by more
than ``keep_below_px`` (``KEEP_BELOW_PX``, half a pixel) keeps its ingested photos and is written PINHOLE with its
own focal lengths and principal point; the others go through COLMAP's undistorter (``keep_below_px`` 0 resamples
all). Output goes to temporary folders first, so a crash leaves no half-written dataset behind.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap

from hico_plugin.data import images as image_io
from hico_plugin.errors import HicoError
from hico_plugin.process.stages import Report

KEEP_BELOW_PX = 0.5


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


def camera_choices(reconstruction: pycolmap.Reconstruction,
                   keep_below_px: float = KEEP_BELOW_PX) -> list[dict[str, Any]]:
    """Per camera (by id): model, size, the largest pixel displacement of its distortion and whether
    its photos are kept as taken (a displacement of at most ``keep_below_px``)."""
    choices = []
    for camera_id in sorted(reconstruction.cameras):
        camera = reconstruction.cameras[camera_id]
        moved = max_distortion_px(camera)
        choices.append({"camera_id": camera_id, "model": camera.model.name, "width": camera.width,
                        "height": camera.height, "max_displacement_px": moved, "kept": moved <= keep_below_px})
    return choices


def describe(choice: dict[str, Any]) -> str:
    """One summary line for a camera of ``camera_choices``."""
    done = ("photos kept as taken, camera written as PINHOLE" if choice["kept"]
            else "photos undistorted to PINHOLE")
    return (f"camera {choice['camera_id']} ({choice['model']}, {choice['width']}x{choice['height']}): distortion "
            f"moves pixels by at most {choice['max_displacement_px']:.2f} px; {done}")


def undistort(model_dir: Path, input_dir: Path, masks: Path, out: Path, report: Report,
              keep_below_px: float = KEEP_BELOW_PX) -> dict[str, Any]:
    """The registered photos of ``model_dir`` (read from ``input_dir``) and their masks (``masks``, if
    any photo had transparency) as a pinhole dataset in ``out``, photos of cameras whose distortion
    moves no pixel by more than ``keep_below_px`` kept as taken; returns {"cameras": camera_choices}."""
    staging = out / "colmap" / "undistorted"
    masks_staging = staging.with_name("undistorted_masks")
    for folder in (staging, masks_staging):
        if folder.exists():
            shutil.rmtree(folder)
    staging.mkdir(parents=True)
    model = pycolmap.Reconstruction(str(model_dir))
    choices = camera_choices(model, keep_below_px)
    kept = {choice["camera_id"] for choice in choices if choice["kept"]}
    images = [image for image in model.images.values() if image.has_pose]
    remapped = [image.name for image in images if image.camera_id not in kept]
    report(0, len(images))
    if remapped:
        pycolmap.undistort_images(staging, model_dir, input_dir, image_names=remapped, output_type="COLMAP")
        _take_undistorted(model, pycolmap.Reconstruction(str(staging / "sparse")), kept)
        shutil.rmtree(staging / "sparse")
    for image in images:
        if image.camera_id in kept:
            target = staging / "images" / image.name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(input_dir / image.name, target)
    for camera_id in kept:
        model.cameras[camera_id] = pinhole_twin(model.cameras[camera_id])
    (staging / "sparse").mkdir()
    model.write_binary(str(staging / "sparse"))
    masks_out = _undistort_masks(images, kept, model_dir, masks, masks_staging)
    for name in ("images", "sparse", "masks"):
        if (out / name).exists():
            shutil.rmtree(out / name)
    (staging / "images").rename(out / "images")
    (out / "sparse").mkdir()
    (staging / "sparse").rename(out / "sparse" / "0")
    if masks_out is not None:
        masks_out.rename(out / "masks")
        shutil.rmtree(masks_out.parent)
    shutil.rmtree(staging)
    report(len(images), len(images))
    return {"cameras": choices}


def _take_undistorted(model: pycolmap.Reconstruction, undistorted: pycolmap.Reconstruction, kept: set[int]) -> None:
    """The undistorter's cameras and keypoints into ``model`` for the cameras not ``kept`` (it writes
    every camera undistorted, whatever images it was given)."""
    for camera_id in set(model.cameras) - kept:
        model.cameras[camera_id] = undistorted.cameras[camera_id]
    for image in model.images.values():
        if image.camera_id not in kept:
            for point, moved in zip(image.points2D, undistorted.images[image.image_id].points2D):
                point.xy = moved.xy


def _undistort_masks(images: list[pycolmap.Image], kept: set[int], model_dir: Path, masks: Path,
                     staging: Path) -> Path | None:
    """The masks (white = scene, nerfstudio's masks/<name>.png) of the dataset's images when any photo
    had transparency (then every photo has one): a kept photo's as it is, the others through the same
    undistortion as their image, then back to black and white at half intensity."""
    if not masks.is_dir():
        return None
    source = staging / "input"
    remapped = [image.name for image in images if image.camera_id not in kept]
    for name in remapped:
        mask = image_io.decode(masks / f"{name}.png", cv2.IMREAD_GRAYSCALE, "mask")
        target = source / name
        target.parent.mkdir(parents=True, exist_ok=True)
        # Under the image's name and format (the undistorter reads by name); JPEG's loss on a black
        # and white image is undone by the threshold below.
        ok, encoded = cv2.imencode(Path(name).suffix.lower(), mask)
        if not ok:
            raise HicoError(f"{target}: mask cannot be encoded")
        target.write_bytes(encoded.tobytes())
    if remapped:
        pycolmap.undistort_images(staging / "out", model_dir, source, image_names=remapped, output_type="COLMAP")
    result = staging / "masks"
    for image in images:
        remapped_mask = image.camera_id not in kept
        path = staging / "out" / "images" / image.name if remapped_mask else masks / f"{image.name}.png"
        mask = image_io.decode(path, cv2.IMREAD_GRAYSCALE, "undistorted mask" if remapped_mask else "mask")
        target = result / Path(image.name).with_suffix(".png")
        target.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(target), np.where(mask > 127, 255, 0).astype(np.uint8))
    return result
