"""viser camera <-> our Camera.

viser reports a browser camera as ``wxyz`` / ``position`` with ``P_world = R(wxyz) p_camera + position``
(camera->world) in OpenCV axes (+Z forward, +X right, +Y down) and a *vertical* field of view in
radians; frustums it draws take the same pose and fov. Our Camera holds the inverse, the
world->camera ``viewmat``, plus a pinhole K with square pixels and the principal point at the centre.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from viser import transforms as vtf

from hico_plugin.cameras import Camera


def render_size(aspect: float, longest_side: int) -> tuple[int, int]:
    """(width, height) with ``width / height ~= aspect`` and the longer side equal to ``longest_side``."""
    if not math.isfinite(aspect) or aspect <= 0:
        aspect = 1.0
    if aspect >= 1.0:
        return longest_side, max(1, round(longest_side / aspect))
    return max(1, round(longest_side * aspect)), longest_side


def viser_to_camera(wxyz: np.ndarray, position: np.ndarray, fov_y: float, width: int, height: int) -> Camera:
    """A viser camera pose (camera->world, OpenCV axes) + vertical fov -> Camera of ``width`` x ``height``."""
    rotation = vtf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix()  # camera->world
    viewmat = np.eye(4)
    viewmat[:3, :3] = rotation.T
    viewmat[:3, 3] = -rotation.T @ np.asarray(position, dtype=np.float64)
    focal = 0.5 * height / math.tan(0.5 * fov_y)
    K = np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])
    return Camera(
        torch.as_tensor(viewmat, dtype=torch.float32), torch.as_tensor(K, dtype=torch.float32), int(width), int(height)
    )


def camera_to_viser(camera: Camera) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Camera -> (wxyz [4], position [3], vertical fov in radians, aspect = width / height), the pose
    and lens a viser frustum or browser camera needs to show the same view."""
    viewmat = camera.viewmat.detach().double().cpu().numpy()
    rotation = viewmat[:3, :3].T  # camera->world
    position = -rotation @ viewmat[:3, 3]
    wxyz = vtf.SO3.from_matrix(rotation).wxyz
    fy = float(camera.K[1, 1])
    fov_y = 2.0 * math.atan(0.5 * camera.height / fy)
    return wxyz, position, fov_y, camera.width / camera.height
