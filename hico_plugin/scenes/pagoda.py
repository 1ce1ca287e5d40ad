"""``pagoda``: a tiered octagonal tower with overhanging, upturned eaves on every tier, fine brick
and tile textures, corner pillars and a spire; self-occluding and mostly non-planar."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hico_plugin.scenes.base import SCENES, SceneConfig, SceneEffects
from hico_plugin.scenes.orbits import orbit_rings
from hico_plugin.scenes.raycast import Ground, Revolution, Sphere, prism

TILE = (0.3, 0.33, 0.3)  # dark glazed tiles
WOOD = (0.55, 0.16, 0.1)  # red lacquered timber
BRICK = (0.72, 0.6, 0.45)


@dataclass
class PagodaEffects(SceneEffects):
    exposure: bool = True
    """Per-image exposure and white balance changes."""
    sky: bool = True
    """Gradient sky instead of black where rays miss the scene."""
    sensor_noise: bool = True
    """Shot and read noise on every image."""


@SCENES.register("pagoda")
@dataclass
class PagodaConfig(SceneConfig):
    """A tiered tower on a stone platform among trees, seen from drone orbits at three heights."""

    num_views: int = 72
    surface_spacing: float = 0.15
    sun_azimuth_deg: float = 120.0
    effects: PagodaEffects = field(default_factory=PagodaEffects)
    tiers: int = 5
    """Number of tiers."""
    sides: int = 8
    """Sides of the tower's regular polygon plan (8 = octagonal)."""
    base_radius: float = 5.0
    """Circumradius of the lowest tier's walls (metres)."""
    tier_height: float = 4.0
    """Height of the lowest tier's walls; each tier above is 12% smaller."""
    eave_overhang: float = 0.6
    """Eave overhang as a fraction of the tier radius."""

    def build_primitives(self):
        rng = np.random.default_rng([self.seed, 4])
        n = self.sides
        prims = [
            Ground(material="brick", color=(0.55, 0.53, 0.5), texture_scale=0.6, half_extent=60.0),
            prism((0, 0), 0.0, 1.2, self.base_radius * 1.9, self.base_radius * 1.8, n,
                  material="brick", color=(0.6, 0.58, 0.55), texture_scale=0.3, top_material="brick"),
        ]
        z, radius, height = 1.2, self.base_radius, self.tier_height
        for tier in range(self.tiers):
            top = z + height
            prims.append(prism((0, 0), z, top, radius, radius, n, material="brick", color=BRICK, texture_scale=0.12))
            if tier < 2:  # lacquered pillars at the corners of the lower tiers
                corners = np.arange(n) * 2 * np.pi / n
                for angle in corners:
                    prims.append(Revolution(material="wood", color=WOOD, texture_scale=0.5,
                                            base=(1.02 * radius * np.cos(angle), 1.02 * radius * np.sin(angle), z),
                                            height=height, r0=0.22, r1=0.22))
            # eaves: a shallow outer flare under a steeper inner slope, so the roof profile is concave
            # (upturned); the flat soffit underneath is timber
            out = radius * (1 + self.eave_overhang)
            mid = radius * (1 + 0.45 * self.eave_overhang)
            next_radius = radius * 0.88
            flare_top = top + 0.25 * height * 0.3
            prims.append(prism((0, 0), top - 0.3, flare_top, out, mid, n, material="roof_tiles", color=TILE,
                               texture_scale=0.18, bottom_material="wood"))
            slope_top = flare_top + 0.35 * height
            last = tier == self.tiers - 1
            upper_radius = 0.2 * radius if last else next_radius * 0.95
            prims.append(prism((0, 0), flare_top - 0.05, slope_top, mid * 0.98, upper_radius, n,
                               material="roof_tiles", color=TILE, texture_scale=0.18))
            z, radius, height = slope_top - 0.3, next_radius, height * 0.88
        # spire: stacked discs and balls on a mast (solids of revolution)
        mast_base = z + 0.3
        prims.append(Revolution(material="plain", color=(0.6, 0.5, 0.25), base=(0, 0, mast_base), height=5.0,
                                r0=0.18, r1=0.08))
        for k in range(4):
            prims.append(Revolution(material="plain", color=(0.65, 0.55, 0.3),
                                    base=(0, 0, mast_base + 0.6 + 0.8 * k), height=0.2, r0=0.7 - 0.12 * k,
                                    r1=0.6 - 0.12 * k))
        prims.append(Sphere(material="plain", color=(0.75, 0.62, 0.3), center=(0, 0, mast_base + 5.2), radius=0.35))
        # trees around the platform, partly occluding the tower from low views
        for angle in rng.uniform(0, 2 * np.pi, 7):
            dist = rng.uniform(2.3, 3.2) * self.base_radius
            x, y, r = dist * np.cos(angle), dist * np.sin(angle), rng.uniform(1.8, 3.0)
            prims.append(Revolution(material="wood", color=(0.35, 0.25, 0.18), base=(x, y, 0), height=2.5,
                                    r0=0.3, r1=0.2))
            prims.append(Sphere(material="foliage", color=(0.22, 0.42, 0.18), center=(x, y, 2.5 + 0.8 * r), radius=r))
        return prims

    def tower_height(self) -> float:
        return 1.2 + sum(self.tier_height * 0.88**k * 1.1 for k in range(self.tiers)) + 5.0

    def build_viewmats(self):
        h = self.tower_height()
        radii = [1.1 * h, 1.25 * h, 1.0 * h]
        heights = [0.3 * h, 0.75 * h, 1.3 * h]
        return orbit_rings(self.num_views, radii, heights, np.array([0, 0, 0.45 * h]), 0.08 * h, self.seed)
