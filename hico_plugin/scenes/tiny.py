"""``tiny``: a checkered box on a checkered plane, 12 small views, for unit tests (about a second)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hico_plugin.scenes.base import SCENES, SceneConfig, SceneEffects
from hico_plugin.scenes.orbits import orbit_rings
from hico_plugin.scenes.raycast import Ground, box


@dataclass
class TinyEffects(SceneEffects):
    """``tiny`` declares no effects: plain shaded images."""


@SCENES.register("tiny")
@dataclass
class TinyConfig(SceneConfig):
    """A 1 m checkered box on a 6 m checkered ground plane, seen from one ring of cameras."""

    num_views: int = 12
    width: int = 64
    height: int = 48
    pixel_samples: int = 1
    """One ray per pixel: unit tests want speed, and tiny's checkers are many pixels wide."""
    sparse_points: int = 300
    surface_spacing: float = 0.05
    effects: TinyEffects = field(default_factory=TinyEffects)
    distance: float = 4.0
    """Distance of the camera ring from the box (metres)."""

    def build_primitives(self):
        return [
            Ground(material="checker", color=(0.8, 0.75, 0.6), texture_scale=0.5, half_extent=3.0),
            box((0, 0, 0.5), (1, 1, 1), yaw=0.3, material="checker", color=(0.7, 0.3, 0.25), texture_scale=0.25),
        ]

    def build_viewmats(self):
        return orbit_rings(
            self.num_views, [self.distance * 0.8], [self.distance * 0.6], np.array([0, 0, 0.4]), 0.1, self.seed
        )
