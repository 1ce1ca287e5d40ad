"""Scene configs: the registry of built-in scenes and what each one is made of."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from hico_plugin.config import InstantiateConfig
from hico_plugin.registry import Registry
from hico_plugin.scenes.orbits import intrinsics
from hico_plugin.scenes.raycast import Primitive, RayCaster

SCENES: Registry[type["SceneConfig"]] = Registry("scene")


@dataclass
class SceneEffects:
    """Base of a scene's effect switches: every bool field is one declared effect
    (``exposure``, ``sky``, ``sensor_noise``, ``multi_distance``); a scene declares an effect by
    having the field, and only declared effects can be switched on."""

    def declared(self) -> list[str]:
        return [f.name for f in fields(self)]

    def enabled(self) -> list[str]:
        return [name for name in self.declared() if getattr(self, name)]


@dataclass
class Scene:
    """Everything needed to render and write a built-in scene."""

    name: str
    config: "SceneConfig"
    primitives: list[Primitive]
    viewmats: np.ndarray  # [C, 4, 4] world->camera
    K: np.ndarray  # [3, 3]
    width: int
    height: int
    sun: np.ndarray  # [3] unit vector towards the sun
    caster: RayCaster

    @property
    def enabled_effects(self) -> list[str]:
        return self.config.effects.enabled()


@dataclass
class SceneConfig(InstantiateConfig):
    """Parameters shared by all built-in scenes (world z is up, units are metres)."""

    num_views: int = 96
    """Number of rendered views."""
    width: int = 320
    """Image width in pixels."""
    height: int = 240
    """Image height in pixels."""
    fov_x_deg: float = 60.0
    """Horizontal field of view in degrees."""
    pixel_samples: int = 2
    """Rays per pixel side: a pixel's colour is the mean of an n x n grid of rays over its footprint,
    as a camera integrates light over each pixel (1 = one ray through the centre). Point samples
    alias window grids, tiles and road markings differently in every view, a pattern no
    view-consistent model can reproduce. Depth, normals and surface points come from the centre ray."""
    seed: int = 0
    """Seed for layout, camera jitter, effects and sparse points."""
    sun_azimuth_deg: float = 35.0
    """Sun azimuth (degrees from +x towards +y)."""
    sun_elevation_deg: float = 50.0
    """Sun elevation above the horizon in degrees."""
    ambient: float = 0.35
    """Share of light that is ambient (the rest is the Lambertian sun term)."""
    shadows: bool = True
    """Cast sun shadows (shadow rays)."""
    sparse_points: int = 4000
    """Target number of SfM-like sparse points."""
    sparse_noise: float = 0.002
    """Sparse point position noise, as a fraction of the distance to the observing camera."""
    min_feature_gradient: float = 0.0
    """Least gradient (8-bit grey levels per pixel, after a 1 px blur) where a sparse point can be found, as
    SIFT drops low-contrast keypoints (Lowe 2004, Sec. 4); 0 lets any pixel with texture propose one."""
    surface_spacing: float = 0.1
    """Spacing (metres) of the dense ground-truth surface samples."""
    sfm: bool = False
    """Replace the known poses and sampled points by real SfM (pycolmap SIFT + matching + incremental
    mapping) on the rendered images, aligned to the ground-truth frame. Slow: minutes on CPU."""
    effects: SceneEffects = field(default_factory=SceneEffects)
    """Effects this scene declares; each can be switched off."""

    def build_primitives(self) -> list[Primitive]:
        raise NotImplementedError

    def build_viewmats(self) -> np.ndarray:
        """World->camera [num_views, 4, 4]."""
        raise NotImplementedError

    def setup(self, name: str = "") -> Scene:
        primitives = self.build_primitives()
        azimuth, elevation = np.radians(self.sun_azimuth_deg), np.radians(self.sun_elevation_deg)
        sun = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
        extent = max(np.abs(p.bounding_sphere()[0]).max() + p.bounding_sphere()[1] for p in primitives)
        return Scene(
            name=name,
            config=self,
            primitives=primitives,
            viewmats=self.build_viewmats(),
            K=intrinsics(self.width, self.height, self.fov_x_deg),
            width=self.width,
            height=self.height,
            sun=sun,
            caster=RayCaster(primitives, eps=1e-6 * extent),
        )
