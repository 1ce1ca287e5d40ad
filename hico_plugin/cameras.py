"""Pinhole cameras, the one camera type every boundary shares.

Conventions (gsplat's, used everywhere in this package):
- ``viewmat`` is always world->camera, a 4x4 rigid transform, OpenCV axes (x right, y down, z forward).
- ``K`` is the 3x3 pinhole intrinsic matrix in pixels; pixel centres sit at +0.5.
- ``index`` is the camera's position in its dataset (the key of the appearance embedding).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class Camera:
    """One pinhole camera."""

    viewmat: Tensor  # [4, 4] world->camera
    K: Tensor  # [3, 3]
    width: int
    height: int
    index: int = -1  # position in the dataset; -1 for a free (viewer / novel) camera

    @property
    def center(self) -> Tensor:
        """Camera centre in world coordinates: [3]."""
        rot = self.viewmat[:3, :3]
        return -rot.T @ self.viewmat[:3, 3]

    def to(self, device: torch.device | str) -> "Camera":
        return Camera(self.viewmat.to(device), self.K.to(device), self.width, self.height, self.index)

    def scaled(self, factor: float) -> "Camera":
        """The same camera at ``factor`` times the resolution (intrinsics rescaled)."""
        width = max(1, int(round(self.width * factor)))
        height = max(1, int(round(self.height * factor)))
        K = self.K.clone()
        K[0] *= width / self.width
        K[1] *= height / self.height
        return Camera(self.viewmat, K, width, height, self.index)


@dataclass
class Cameras:
    """A set of pinhole cameras stored as stacked tensors."""

    viewmats: Tensor  # [C, 4, 4] world->camera
    Ks: Tensor  # [C, 3, 3]
    widths: Tensor  # [C] int64
    heights: Tensor  # [C] int64

    def __len__(self) -> int:
        return self.viewmats.shape[0]

    def __getitem__(self, i: int) -> Camera:
        return Camera(self.viewmats[i], self.Ks[i], int(self.widths[i]), int(self.heights[i]), int(i))

    @property
    def centers(self) -> Tensor:
        """Camera centres in world coordinates: [C, 3]."""
        rot = self.viewmats[:, :3, :3]
        return -(rot.transpose(1, 2) @ self.viewmats[:, :3, 3:4]).squeeze(-1)

    def to(self, device: torch.device | str) -> "Cameras":
        return Cameras(self.viewmats.to(device), self.Ks.to(device), self.widths, self.heights)
