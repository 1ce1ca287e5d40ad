"""The scene normalisation: COLMAP's world frame <-> the normalised frame training works in.

``world_normalised = (world_colmap - centre) * scale``. Camera frames are scaled with the world so
viewmats stay rigid: a viewmat ``[R | t]`` in COLMAP's frame becomes ``[R | scale * (R @ centre + t)]``,
and camera-space depths are multiplied by ``scale``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class SceneTransform:
    """Similarity (centre, isotropic scale) from COLMAP's world frame to the normalised frame."""

    centre: Tensor  # [3] float64, in COLMAP units
    scale: float  # normalised units per COLMAP unit

    @classmethod
    def identity(cls) -> SceneTransform:
        return cls(torch.zeros(3, dtype=torch.float64), 1.0)

    @classmethod
    def from_camera_centres(cls, centres: Tensor, fallback_points: Tensor | None = None) -> SceneTransform:
        """nerfstudio's auto-scale: centre on the mean camera centre, scale so the farthest camera
        centre lies at distance 1 (``centres``: [C, 3]). With one camera (or all cameras at one
        spot) the spread of ``fallback_points`` [P, 3] sets the scale instead."""
        centres = centres.to(torch.float64)
        centre = centres.mean(dim=0)
        radius = float((centres - centre).norm(dim=-1).max())
        if radius <= 1e-9 and fallback_points is not None and len(fallback_points) > 0:
            radius = float((fallback_points.to(torch.float64) - centre).norm(dim=-1).median())
        return cls(centre, 1.0 / radius if radius > 1e-9 else 1.0)

    def points_from_colmap(self, points: Tensor) -> Tensor:
        """[..., 3] COLMAP world -> [..., 3] normalised (dtype of ``points``)."""
        return ((points.to(torch.float64) - self.centre.to(points.device)) * self.scale).to(points.dtype)

    def points_to_colmap(self, points: Tensor) -> Tensor:
        """[..., 3] normalised -> [..., 3] COLMAP world (dtype of ``points``)."""
        return (points.to(torch.float64) / self.scale + self.centre.to(points.device)).to(points.dtype)

    def viewmats_from_colmap(self, viewmats: Tensor) -> Tensor:
        """[..., 4, 4] world->camera in COLMAP's frame -> the same cameras in the normalised frame."""
        out = viewmats.to(torch.float64).clone()
        rot = out[..., :3, :3]
        out[..., :3, 3] = self.scale * (rot @ self.centre.to(out.device) + out[..., :3, 3])
        return out.to(viewmats.dtype)

    def viewmats_to_colmap(self, viewmats: Tensor) -> Tensor:
        """[..., 4, 4] world->camera in the normalised frame -> COLMAP's frame."""
        out = viewmats.to(torch.float64).clone()
        rot = out[..., :3, :3]
        out[..., :3, 3] = out[..., :3, 3] / self.scale - rot @ self.centre.to(out.device)
        return out.to(viewmats.dtype)

    def to_dict(self) -> dict:
        """JSON-friendly form (written next to outputs so they can be mapped back)."""
        return {"centre": [float(v) for v in self.centre], "scale": float(self.scale)}

    @classmethod
    def from_dict(cls, data: dict) -> SceneTransform:
        return cls(torch.tensor(data["centre"], dtype=torch.float64), float(data["scale"]))
