"""``room``: a bust on a pedestal in a closed room with papered walls, a plaster ceiling and a wooden
floor, seen from inside by cameras circling the bust: an indoor capture with no sky, where the smooth
paper between the flowers and the ceiling give SfM no features (as on the wall behind the fox of
instant-ngp's phone capture), so much of each photo is surface that no sparse point explains."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hico_plugin.errors import HicoError
from hico_plugin.scenes.base import SCENES, SceneConfig, SceneEffects
from hico_plugin.scenes.orbits import orbit_rings
from hico_plugin.scenes.raycast import Revolution, Sphere, box

PAPER = (0.9, 0.86, 0.76)
WALL_THICKNESS = 0.1
ORBIT_REACH = 1.1 * 1.08  # the widest ring's radius over orbit_radius, with orbit_rings' 8 % jitter


@dataclass
class RoomEffects(SceneEffects):
    exposure: bool = True
    """Per-image exposure and white balance changes (a phone's auto exposure)."""


@SCENES.register("room")
@dataclass
class RoomConfig(SceneConfig):
    """A closed room (walls, ceiling, floor) around a bust on a pedestal; cameras orbit the bust inside."""

    num_views: int = 48
    fov_x_deg: float = 75.0
    """Wide enough that views looking across the room see the ceiling above the far wall."""
    ambient: float = 0.6
    shadows: bool = False
    """No cast shadows: the light is the room's own diffuse light, and the sun would be blocked by the ceiling."""
    surface_spacing: float = 0.05
    min_feature_gradient: float = 8.0
    """High enough that the smooth paper and the ceiling stay point-free, as SfM leaves them."""
    effects: RoomEffects = field(default_factory=RoomEffects)
    size: tuple[float, float, float] = (6.0, 5.0, 2.8)
    """Inner width (x), depth (y) and height (z) of the room in metres."""
    orbit_radius: float = 1.8
    """Distance of the cameras from the bust (metres); must stay inside the walls."""

    def build_primitives(self):
        width, depth, height = self.size
        t = WALL_THICKNESS
        paper = dict(material="wallpaper", color=PAPER, texture_scale=0.7)
        # slabs whose inner faces bound the room: a camera inside sees each from the room side
        walls = [box((sx * (width + t) / 2, 0, height / 2), (t, depth + 2 * t, height), **paper) for sx in (-1, 1)]
        walls += [box((0, sy * (depth + t) / 2, height / 2), (width + 2 * t, t, height), **paper) for sy in (-1, 1)]
        return [
            *walls,
            box((0, 0, -t / 2), (width, depth, t), material="wood", color=(0.5, 0.34, 0.22), texture_scale=0.6),
            box((0, 0, height + t / 2), (width, depth, t), material="plaster", color=(0.93, 0.92, 0.9),
                texture_scale=2.0),
            Revolution(material="wood", color=(0.32, 0.22, 0.16), texture_scale=0.3, base=(0, 0, 0), height=1.0,
                       r0=0.28, r1=0.2),
            Revolution(material="plaster", color=(0.8, 0.78, 0.74), texture_scale=0.08, base=(0, 0, 1.0),
                       height=0.3, r0=0.3, r1=0.1),
            Sphere(material="plaster", color=(0.82, 0.8, 0.76), texture_scale=0.08, center=(0, 0, 1.45),
                   radius=0.17),
        ]

    def build_viewmats(self):
        radius = self.orbit_radius
        if ORBIT_REACH * radius >= min(self.size[:2]) / 2:
            raise HicoError(f"scene 'room': orbit_radius {radius} puts cameras in or behind the walls of a "
                            f"{self.size[0]} x {self.size[1]} m room; expected < {min(self.size[:2]) / (2 * ORBIT_REACH):.2f}")
        return orbit_rings(self.num_views, [radius, 1.1 * radius, 0.9 * radius], [1.2, 1.55, 1.9],
                           np.array([0.0, 0.0, 1.3]), 0.1, self.seed)
