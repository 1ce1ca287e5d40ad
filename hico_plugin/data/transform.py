"""The scene normalisation: COLMAP's world frame <-> the normalised frame training works in.

``world_normalised = rotation @ (world_colmap - centre) * scale``: the rotation turns the vertical (``scene_up``)
to +z and the walls onto the x and y axes (``scene_heading``); centre and scale make the cameras' spread a unit
sphere, so any units or up axis train the same. A viewmat ``[R | t]`` in COLMAP's frame becomes
``[R @ rotation.T | scale * (R @ centre + t)]``; camera-space depths scale by ``scale``, normals are unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor


# RMS share of the cameras' right axes off their mean direction below which their headings are too
# alike to fix the vertical (about 10 degrees; nerfstudio's "vertical" orientation uses the same bound)
MIN_HEADING_SPREAD = 0.17


def scene_up(viewmats: Tensor, method: str = "vertical") -> Tensor:
    """The scene's up direction [3] (unit, float64) from world->camera viewmats [C, 4, 4] (OpenCV axes: row 0 of R
    is a camera's right axis, row 1 negated its up axis).

    Level photos keep the right axis horizontal while the up axis tilts with the pitch, so "vertical"
    (nerfstudio's) is the stacked right axes' right-singular vector of smallest singular value, or, when they are
    nearly parallel, the mean up made orthogonal to the mean right axis. ``method`` "up" is the cameras' mean up
    (how runs before "vertical" were oriented). The sign follows the mean up."""
    viewmats = viewmats.to(torch.float64)
    rights, mean_up = viewmats[:, 0, :3], -viewmats[:, 1, :3].mean(dim=0)
    if method == "up":
        return mean_up / mean_up.norm().clamp_min(1e-12)
    _, singular, vh = torch.linalg.svd(rights, full_matrices=True)
    if len(singular) >= 2 and float(singular[1]) > MIN_HEADING_SPREAD * len(rights) ** 0.5:
        up = vh[2]
    else:
        right = rights.mean(dim=0) / rights.mean(dim=0).norm().clamp_min(1e-12)
        up = mean_up - (mean_up @ right) * right
    up = up if float(up @ mean_up) >= 0 else -up
    return up / up.norm().clamp_min(1e-12)


# heading: at most this many sparse points (strided) give normals, each from its NEIGHBOURS nearest
# points; a patch is planar when its least variance is under PLANAR_RATIO of the next, a wall when its
# normal is within WALL_TILT_DEG of horizontal. The heading is the one (modulo 90 degrees) that most
# walls share within HEADING_TOLERANCE_DEG; it counts when at least MIN_HEADING_SHARE of the walls
# share it (walls at random headings: 2 x 1.5 / 90 = 3 %).
HEADING_MAX_POINTS = 4096
NEIGHBOURS = 12
PLANAR_RATIO = 0.05
WALL_TILT_DEG = 15.0
MIN_WALL_NORMALS = 20
HEADING_TOLERANCE_DEG = 1.5
MIN_HEADING_SHARE = 0.2


def scene_heading(points: Tensor) -> float:
    """The turn (radians) about +z after which the dominant vertical planes of a z-up scene (walls, facades) face
    the x and y axes, from its sparse points [P, 3]; 0 when no direction dominates.

    The anchor octree is a grid along the axes, so a wall at an angle crosses its cells in steps and the surface
    is placed less exactly (benchmarks/RESULTS.md, "Figures behind the defaults"). The normals of planar,
    near-horizontal patches vote with their heading modulo 90 degrees (a Manhattan world); the most shared heading
    wins, not the mean, so buildings turned off the street grid do not pull it."""
    points = points.to(torch.float32)[:: max(1, -(-len(points) // HEADING_MAX_POINTS))]
    if len(points) <= NEIGHBOURS:
        return 0.0
    nearest = torch.cdist(points, points).topk(NEIGHBOURS + 1, largest=False).indices  # [P, k+1], self included
    patches = points[nearest].double()
    centred = patches - patches.mean(dim=1, keepdim=True)
    values, vectors = torch.linalg.eigh(centred.transpose(1, 2) @ centred)  # ascending eigenvalues
    normals = vectors[:, :, 0]
    walls = (values[:, 0] < PLANAR_RATIO * values[:, 1]) & (normals[:, 2].abs() < math.sin(math.radians(WALL_TILT_DEG)))
    if int(walls.sum()) < MIN_WALL_NORMALS:
        return 0.0
    quarter = 4.0 * torch.atan2(normals[walls, 1], normals[walls, 0])  # heading x 4: period 90 degrees -> 360
    tolerance = 4.0 * math.radians(HEADING_TOLERANCE_DEG)
    candidates = torch.linspace(-math.pi, math.pi, 721, dtype=torch.float64)[:-1]  # 0.125 degree steps of heading
    near = torch.cos(quarter[None, :] - candidates[:, None]) > math.cos(tolerance)  # [candidates, walls]
    best = int(near.sum(dim=1).argmax())
    inliers = quarter[near[best]]
    if len(inliers) < MIN_HEADING_SHARE * len(quarter):
        return 0.0
    return float(torch.atan2(inliers.sin().mean(), inliers.cos().mean())) / 4.0


def rotation_about_z(angle: float) -> Tensor:
    """[3, 3] float64 rotation by ``angle`` radians about +z."""
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def rotation_to_z(direction: Tensor) -> Tensor:
    """The smallest rotation [3, 3] float64 taking the unit vector ``direction`` [3] to +z (a half
    turn about x when it points down)."""
    direction = direction.to(torch.float64)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    axis = torch.linalg.cross(direction, z)
    cos, sin = float(direction @ z), float(axis.norm())
    if sin < 1e-12:
        return torch.eye(3, dtype=torch.float64) if cos > 0 else torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    k = axis / sin
    cross = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + sin * cross + (1.0 - cos) * cross @ cross


@dataclass
class SceneTransform:
    """Similarity (rotation, centre, isotropic scale) from COLMAP's world frame to the normalised frame."""

    centre: Tensor  # [3] float64, in COLMAP units
    scale: float  # normalised units per COLMAP unit
    rotation: Tensor = field(default_factory=lambda: torch.eye(3, dtype=torch.float64))  # [3, 3] COLMAP -> normalised axes

    @classmethod
    def identity(cls) -> SceneTransform:
        return cls(torch.zeros(3, dtype=torch.float64), 1.0)

    @classmethod
    def from_cameras(cls, viewmats: Tensor, points: Tensor | None = None, orient: bool = True,
                     orient_method: str = "manhattan") -> SceneTransform:
        """The scene normalisation, decided here only (nerfstudio's auto-orient and auto-scale): rotate
        the scene's up (``scene_up``) to +z (``orient``) and, with ``orient_method`` "manhattan", its
        walls onto the x and y axes (``scene_heading`` of the sparse ``points`` [P, 3]); centre on the mean
        camera centre, scale so the farthest camera centre lies at distance 1 (``viewmats``: [C, 4, 4]
        world->camera). With one camera (or all at one spot) the spread of ``points`` sets the scale."""
        viewmats = viewmats.to(torch.float64)
        rotations, translations = viewmats[:, :3, :3], viewmats[:, :3, 3:]
        centres = -(rotations.transpose(1, 2) @ translations).squeeze(-1)
        centre = centres.mean(dim=0)
        radius = float((centres - centre).norm(dim=-1).max())
        if radius <= 1e-9 and points is not None and len(points) > 0:
            radius = float((points.to(torch.float64) - centre).norm(dim=-1).median())
        rotation = torch.eye(3, dtype=torch.float64)
        if orient:
            rotation = rotation_to_z(scene_up(viewmats, "up" if orient_method == "up" else "vertical"))
            if orient_method == "manhattan" and points is not None and len(points) > 0:
                upright = (points.to(torch.float64) - centre) @ rotation.T
                rotation = rotation_about_z(-scene_heading(upright)) @ rotation
        return cls(centre, 1.0 / radius if radius > 1e-9 else 1.0, rotation)

    def points_from_colmap(self, points: Tensor) -> Tensor:
        """[..., 3] COLMAP world -> [..., 3] normalised (dtype of ``points``)."""
        centred = points.to(torch.float64) - self.centre.to(points.device)
        return (centred @ self.rotation.to(points.device).T * self.scale).to(points.dtype)

    def points_to_colmap(self, points: Tensor) -> Tensor:
        """[..., 3] normalised -> [..., 3] COLMAP world (dtype of ``points``)."""
        rotated = points.to(torch.float64) @ self.rotation.to(points.device)
        return (rotated / self.scale + self.centre.to(points.device)).to(points.dtype)

    def directions_to_colmap(self, directions: Tensor) -> Tensor:
        """[..., 3] directions (normals, axes) in normalised axes -> COLMAP's axes (dtype kept)."""
        return (directions.to(torch.float64) @ self.rotation.to(directions.device)).to(directions.dtype)

    def viewmats_from_colmap(self, viewmats: Tensor) -> Tensor:
        """[..., 4, 4] world->camera in COLMAP's frame -> the same cameras in the normalised frame."""
        out = viewmats.to(torch.float64).clone()
        rot = out[..., :3, :3].clone()
        out[..., :3, 3] = self.scale * (rot @ self.centre.to(out.device) + out[..., :3, 3])
        out[..., :3, :3] = rot @ self.rotation.to(out.device).T
        return out.to(viewmats.dtype)

    def viewmats_to_colmap(self, viewmats: Tensor) -> Tensor:
        """[..., 4, 4] world->camera in the normalised frame -> COLMAP's frame."""
        out = viewmats.to(torch.float64).clone()
        rot = out[..., :3, :3] @ self.rotation.to(out.device)
        out[..., :3, :3] = rot
        out[..., :3, 3] = out[..., :3, 3] / self.scale - rot @ self.centre.to(out.device)
        return out.to(viewmats.dtype)

    def to_dict(self) -> dict:
        """JSON-friendly form (written next to outputs so they can be mapped back)."""
        return {"centre": [float(v) for v in self.centre], "scale": float(self.scale),
                "rotation": [[float(v) for v in row] for row in self.rotation]}

    @classmethod
    def from_dict(cls, data: dict) -> SceneTransform:
        rotation = torch.tensor(data.get("rotation", torch.eye(3).tolist()), dtype=torch.float64)
        return cls(torch.tensor(data["centre"], dtype=torch.float64), float(data["scale"]), rotation)


def _close(a: Any, b: Any) -> bool:
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    try:
        return bool(np.allclose(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64), rtol=1e-6, atol=1e-9))
    except (TypeError, ValueError):
        return a == b


def frame_differences(stored: dict, today: dict) -> list[str]:
    """The parts (keys of ``SceneTransform.to_dict``) in which a recorded frame and one computed today
    place the cameras differently, sorted; empty when a model of ``stored`` can be loaded in ``stored``.

    The centre, the scale and the up axis (the rotation's last row) come from the cameras alone, so a
    difference there means other cameras or another rule. The heading about the up axis comes from the
    seed points, which a fresh triangulation (an emptied cache, another machine) reproduces only to
    within its random sampling, so it is not compared: the recorded one is kept."""
    keys = set(stored) | set(today)
    changed = []
    for key in keys:
        a, b = stored.get(key), today.get(key)
        if key == "rotation" and a is not None and b is not None:
            a, b = np.asarray(a, dtype=np.float64)[-1], np.asarray(b, dtype=np.float64)[-1]
        if not _close(a, b):
            changed.append(key)
    return sorted(changed)
