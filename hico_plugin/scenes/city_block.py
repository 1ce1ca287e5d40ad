"""``city-block``: a 3 x 3 grid of city blocks with facades, windows, flat and pitched roofs, trees
and streets, seen from aerial orbits at several distances."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hico_plugin.scenes.base import SCENES, SceneConfig, SceneEffects
from hico_plugin.scenes.orbits import orbit_rings
from hico_plugin.scenes.raycast import Ground, Revolution, Sphere, box, roof

WALL_COLORS = [(0.78, 0.72, 0.62), (0.62, 0.6, 0.58), (0.72, 0.55, 0.45), (0.85, 0.82, 0.75), (0.55, 0.6, 0.66)]


@dataclass
class CityBlockEffects(SceneEffects):
    exposure: bool = False
    """Per-image exposure and white balance changes (what an appearance embedding absorbs). Off by
    default: city-block stands in for MatrixCity, whose synthetic aerial renders are photometrically
    consistent (paper Sec. 4); test views' unknown gains would otherwise cap every method's PSNR."""
    sky: bool = True
    """Gradient sky instead of black where rays miss the scene."""
    multi_distance: bool = True
    """Camera rings at 1x, 2x and 4x distance (several LOD levels); off: one mid-distance ring."""


@SCENES.register("city-block")
@dataclass
class CityBlockConfig(SceneConfig):
    """Buildings with window-grid facades, flat gravel and tiled pitched roofs, on a street grid."""

    num_views: int = 72
    surface_spacing: float = 0.4
    effects: CityBlockEffects = field(default_factory=CityBlockEffects)
    blocks: int = 3
    """Blocks per side of the square grid."""
    block_pitch: float = 30.0
    """Distance between neighbouring block centres (metres); streets run between blocks."""
    floor_height: float = 3.2
    """Storey height (window grid period, metres)."""
    max_floors: int = 7
    """Tallest building, in storeys."""

    def _block_centers(self) -> np.ndarray:
        offsets = (np.arange(self.blocks) - (self.blocks - 1) / 2) * self.block_pitch
        return np.stack(np.meshgrid(offsets, offsets), -1).reshape(-1, 2)

    def build_primitives(self):
        rng = np.random.default_rng([self.seed, 3])
        pitch, floor = self.block_pitch, self.floor_height
        half = self.blocks * pitch / 2 + pitch
        prims = [
            Ground(material="street", color=(0.3, 0.3, 0.32), texture_scale=pitch, half_extent=half)
        ]
        lot = 0.6 * pitch  # usable block size inside the pavements
        for cx, cy in self._block_centers():
            layout = rng.integers(0, 3)
            if layout == 0:  # one large building, maybe with a setback tower
                footprints = [(cx, cy, lot, lot * rng.uniform(0.7, 1.0))]
            elif layout == 1:  # two slabs
                w = lot / 2 - 0.6
                footprints = [(cx - lot / 4, cy, w, lot), (cx + lot / 4, cy, w, lot * rng.uniform(0.6, 1.0))]
            else:  # a tower and two houses
                footprints = [
                    (cx - lot / 4, cy, lot / 2 - 0.6, lot),
                    (cx + lot / 4, cy - lot / 4, lot / 2 - 0.6, lot / 2 - 0.6),
                    (cx + lot / 4, cy + lot / 4, lot / 2 - 0.6, lot / 2 - 0.6),
                ]
            for x, y, sx, sy in footprints:
                floors = int(rng.integers(2, self.max_floors + 1))
                height = floors * floor
                yaw = 0.0 if rng.uniform() > 0.2 else rng.uniform(-0.35, 0.35)
                if yaw:  # rotated buildings must still fit on their lot
                    scale = 1.0 / (abs(np.cos(yaw)) + abs(np.sin(yaw)))
                    sx, sy = sx * scale, sy * scale
                wall = WALL_COLORS[rng.integers(len(WALL_COLORS))]
                prims.append(
                    box((x, y, height / 2), (sx, sy, height), yaw=yaw, material="facade", color=wall,
                        texture_scale=floor, top_material="roof_flat")
                )
                if floors <= 4 and rng.uniform() < 0.7:  # pitched roof, ridge along the long side
                    along_x = sx >= sy
                    size = (sx, sy) if along_x else (sy, sx)
                    prims.append(
                        roof((x, y, height), size, rise=0.35 * min(sx, sy), hip=bool(rng.uniform() < 0.5),
                             yaw=yaw + (0 if along_x else np.pi / 2), material="roof_tiles",
                             color=(0.55, 0.25, 0.18), texture_scale=0.45)
                    )
                elif floors >= 6 and rng.uniform() < 0.6:  # setback upper storeys
                    extra = int(rng.integers(2, 4)) * floor
                    prims.append(
                        box((x, y, height + extra / 2), (0.6 * sx, 0.6 * sy, extra), yaw=yaw, material="facade",
                            color=wall, texture_scale=floor, top_material="roof_flat")
                    )
                else:  # rooftop plant room
                    prims.append(
                        box((x + 0.15 * sx, y, height + 1.2), (0.25 * sx, 0.3 * sy, 2.4), yaw=yaw,
                            material="plaster", color=(0.6, 0.6, 0.6), texture_scale=1.0)
                    )
            for _ in range(int(rng.integers(0, 3))):  # street trees on the pavement corners
                tx = cx + rng.choice([-1, 1]) * (lot / 2 + 1.5)
                ty = cy + rng.uniform(-lot / 2, lot / 2)
                radius = rng.uniform(1.8, 2.8)
                prims.append(Revolution(material="wood", color=(0.35, 0.25, 0.18), base=(tx, ty, 0), height=3.0,
                                        r0=0.25, r1=0.18))
                prims.append(Sphere(material="foliage", color=(0.25, 0.45, 0.2), texture_scale=1.0,
                                    center=(tx, ty, 3.0 + radius * 0.8), radius=radius))
        return prims

    def build_viewmats(self):
        span = self.blocks * self.block_pitch
        if self.effects.multi_distance:
            radii, heights = [0.5 * span, 0.85 * span, 1.6 * span], [0.5 * span, 0.75 * span, 1.4 * span]
        else:
            radii, heights = [0.8 * span], [0.7 * span]
        return orbit_rings(self.num_views, radii, heights, np.zeros(3), 0.2 * span, self.seed)
