"""A learned sky: colour as a function of the world ray direction, composited behind the Gaussians.

Urban captures see sky in a large part of the frame (30 % of the built-in city-block's pixels), where
no anchor exists; a constant background cannot match a gradient sky, and Gaussians pushed there to
fake it become floaters. A small MLP on the unit ray direction needs no up axis (COLMAP frames have
none) and stays smooth: ``rgb = rgb_gaussians + (1 - alpha) * sky(direction)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from hico_plugin.cameras import Camera
from hico_plugin.config import InstantiateConfig
from hico_plugin.model.effects import EFFECTS
from hico_plugin.rasterizer.geometry import pixel_rays


@dataclass
class SkyConfig(InstantiateConfig):
    """Directional sky behind the Gaussians (on when --model.effects finds or forces ``sky``)."""

    hidden_dim: int = 32
    """Hidden width of the direction MLP."""

    def setup(self, **kwargs) -> "SkyModel":
        return SkyModel(self)


@EFFECTS.register("sky")
class SkyModel(nn.Module):
    """Sky colour of each pixel of a camera: [H,W,3] in (0,1)."""

    finding = "sky"

    def __init__(self, config: SkyConfig):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(3, config.hidden_dim), nn.ReLU(),
                                 nn.Linear(config.hidden_dim, config.hidden_dim), nn.ReLU(),
                                 nn.Linear(config.hidden_dim, 3))

    def forward(self, camera: Camera) -> Tensor:
        return torch.sigmoid(self.mlp(ray_directions(camera)))


def ray_directions(camera: Camera) -> Tensor:
    """Unit world-space directions through the pixel centres (the rasterizer's rays): [H,W,3]."""
    dirs_cam = pixel_rays(camera.K[None], camera.width, camera.height)[0]
    dirs_world = dirs_cam @ camera.viewmat[:3, :3].to(camera.K)  # R^T d, row-vector form
    return dirs_world / dirs_world.norm(dim=-1, keepdim=True)
