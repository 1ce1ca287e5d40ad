"""What the three files of a COLMAP sparse model hold, as arrays (``colmap_bin`` and ``colmap_text``
fill it; ``colmap`` checks it).

COLMAP writes only registered images to images.bin / images.txt (``Reconstruction::RegImageIds``), each
with its ``cam_from_world``; models with rigs (COLMAP 4's rigs and frames files) store there the pose
composed with the camera's ``sensor_from_rig``, so every listed image is posed, as pycolmap reads
it, and the rigs and frames files need not be read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hico_plugin.data.camera_model import Camera


@dataclass
class ModelFiles:
    """The rows of cameras, images and points3D in file order."""

    cameras: dict[int, Camera]  # by camera id
    image_ids: np.ndarray  # [I] int64
    image_names: list[str]  # [I]
    image_camera_ids: np.ndarray  # [I] int64
    cam_from_world: np.ndarray  # [I, 7] float64: quaternion qw, qx, qy, qz, then translation tx, ty, tz
    point_ids: np.ndarray  # [P] uint64
    points: np.ndarray  # [P, 3] float64
    colors: np.ndarray  # [P, 3] uint8
    track_lengths: np.ndarray  # [P] int64 observations of each point
    track_image_ids: np.ndarray  # [sum(track_lengths)] int64: the observing images, point after point


def pose_matrices(cam_from_world: np.ndarray) -> np.ndarray:
    """[N, 7] (qw, qx, qy, qz, tx, ty, tz) -> [N, 4, 4] float64 world->camera matrices, the quaternion
    taken as stored (not normalised), as Eigen's ``toRotationMatrix`` behind COLMAP's Rigid3d does.
    A corrupt file's huge or NaN entries give non-finite matrices, which the caller refuses."""
    w, x, y, z = cam_from_world[:, :4].T
    matrices = np.tile(np.eye(4), (len(cam_from_world), 1, 1))
    with np.errstate(over="ignore", invalid="ignore"):
        tx, ty, tz = 2.0 * x, 2.0 * y, 2.0 * z
        twx, twy, twz = tx * w, ty * w, tz * w
        txx, txy, txz = tx * x, ty * x, tz * x
        tyy, tyz, tzz = ty * y, tz * y, tz * z
        matrices[:, :3, :3] = np.stack([
            np.stack([1.0 - (tyy + tzz), txy - twz, txz + twy], axis=-1),
            np.stack([txy + twz, 1.0 - (txx + tzz), tyz - twx], axis=-1),
            np.stack([txz - twy, tyz + twx, 1.0 - (txx + tyy)], axis=-1),
        ], axis=1)
    matrices[:, :3, 3] = cam_from_world[:, 4:]
    return matrices
