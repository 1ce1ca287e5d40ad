"""A learned environment: colour as a function of the world ray direction, composited behind the Gaussians.

Where no reconstructed point explains the photos (``analysis.uncovered_cells``: open sky, featureless walls) the
render shows what lies behind the Gaussians; a constant cannot match a gradient sky or a lit wall, and Gaussians
pushed there become floaters. A small MLP on the unit ray direction needs no up axis and stays smooth: ``rgb =
rgb_gaussians + (1 - alpha) * environment(direction)``, exact for a distant background and an approximation for
near surfaces that still pays (benchmarks/RESULTS.md, "Figures behind the defaults").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding
from hico_plugin.analysis.uncovered_cells import environment_finding
from hico_plugin.cameras import Camera
from hico_plugin.config import InstantiateConfig
from hico_plugin.engine.optimizers import ParamGroupOptimizerConfig
from hico_plugin.model.effects.base import EFFECTS, Effect, EffectInputs
from hico_plugin.rasterizer import RenderOutputs
from hico_plugin.rasterizer.geometry import pixel_rays


@dataclass
class EnvironmentConfig(InstantiateConfig):
    """Directional background behind the Gaussians (on when --model.effects finds or forces ``environment``)."""

    hidden_dim: int = 32
    """Hidden width of the direction MLP."""
    stride: int = 4
    """The MLP runs at every stride-th pixel (a camera with 1/stride the resolution) and the image
    takes its bilinear interpolation; 1: every pixel. A background far behind the scene changes slowly
    with the direction, and per pixel this MLP costs more than all the decoder's MLPs together."""

    def setup(self, **kwargs) -> "EnvironmentModel":
        return EnvironmentModel(self)


@EFFECTS.register("environment")
class EnvironmentEffect(Effect):
    """What lies behind the Gaussians where no reconstructed point explains the photos
    (``analysis.uncovered_cells``): a learned directional colour composited where the Gaussians leave
    the image uncovered, ``rgb + (1 - alpha) * environment(direction)``."""

    finding = "environment"
    stage = 0  # behind the Gaussians, before the camera's response
    replaces_background = True

    def detect(self, evidence: DatasetEvidence) -> EffectFinding:
        return environment_finding(evidence)

    def background_when_off(self, finding: EffectFinding) -> tuple[float, float, float] | None:
        colour = finding.figures.get("unexplained_colour")
        return tuple(colour) if finding.present and colour is not None else None

    def build(self, inputs: EffectInputs) -> "EnvironmentModel":
        return inputs.model_config.environment.setup()

    def default_lrs(self) -> dict[str, ParamGroupOptimizerConfig]:
        # a small MLP like the colour MLP, a little faster: the environment is simple
        return {"environment": ParamGroupOptimizerConfig(0.01, 1e-4)}

    def apply(self, module: "EnvironmentModel", out: RenderOutputs, camera: Camera) -> Tensor:
        return out.rgb + (1.0 - out.alpha) * module(camera)


class EnvironmentModel(nn.Module):
    """Environment colour of each pixel of a camera: [H,W,3] in (0,1)."""

    def __init__(self, config: EnvironmentConfig):
        super().__init__()
        self.stride = max(1, config.stride)
        self.mlp = nn.Sequential(nn.Linear(3, config.hidden_dim), nn.ReLU(),
                                 nn.Linear(config.hidden_dim, config.hidden_dim), nn.ReLU(),
                                 nn.Linear(config.hidden_dim, 3))

    def forward(self, camera: Camera) -> Tensor:
        if self.stride == 1:
            return torch.sigmoid(self.mlp(ray_directions(camera)))
        # Camera.scaled keeps the pixel-centre correspondence that align_corners=False interpolates.
        coarse = torch.sigmoid(self.mlp(ray_directions(camera.scaled(1.0 / self.stride))))
        fine = F.interpolate(coarse.permute(2, 0, 1)[None], size=(camera.height, camera.width),
                             mode="bilinear", align_corners=False)
        return fine[0].permute(1, 2, 0)


def ray_directions(camera: Camera) -> Tensor:
    """Unit world-space directions through the pixel centres (the rasterizer's rays): [H,W,3]."""
    dirs_cam = pixel_rays(camera.K[None], camera.width, camera.height)[0]
    dirs_world = dirs_cam @ camera.viewmat[:3, :3].to(camera.K)  # R^T d, row-vector form
    return dirs_world / dirs_world.norm(dim=-1, keepdim=True)
