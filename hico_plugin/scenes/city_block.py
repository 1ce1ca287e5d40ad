"""``city-block``: a 3 x 3 grid of city blocks with facades, windows, flat and pitched roofs, trees
and streets, seen from aerial orbits at several distances."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hico_plugin.scenes.base import SCENES, SceneConfig, SceneEffects
from hico_plugin.scenes.buildings import block_buildings, block_centers
from hico_plugin.scenes.orbits import orbit_rings
from hico_plugin.scenes.raycast import Ground


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

    def build_primitives(self):
        rng = np.random.default_rng([self.seed, 3])
        pitch, floor = self.block_pitch, self.floor_height
        half = self.blocks * pitch / 2 + pitch
        prims = [
            Ground(material="street", color=(0.3, 0.3, 0.32), texture_scale=pitch, half_extent=half)
        ]
        lot = 0.6 * pitch  # usable block size inside the pavements
        for cx, cy in block_centers(self.blocks, pitch):
            prims += block_buildings(rng, cx, cy, lot, floor, self.max_floors)
        return prims

    def build_viewmats(self):
        span = self.blocks * self.block_pitch
        if self.effects.multi_distance:
            radii, heights = [0.5 * span, 0.85 * span, 1.6 * span], [0.5 * span, 0.75 * span, 1.4 * span]
        else:
            radii, heights = [0.8 * span], [0.7 * span]
        return orbit_rings(self.num_views, radii, heights, np.zeros(3), 0.2 * span, self.seed)
