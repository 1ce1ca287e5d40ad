"""Render one view of a scene: Lambertian shaded albedo plus exact depth and normals."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from hico_plugin.scenes.raycast import RayCaster, group_by_primitive
from hico_plugin.scenes.textures import MATERIALS


@dataclass
class View:
    """Per-pixel results of one view, all [H, W, ...]."""

    albedo: np.ndarray  # [H, W, 3] texture colour in [0, 1], 0 where no surface
    shading: np.ndarray  # [H, W] ambient + sun term (with cast shadows), 0 where no surface
    hit: np.ndarray  # [H, W] bool
    depth: np.ndarray  # [H, W] camera z, 0 where no surface
    normal: np.ndarray  # [H, W, 3] unit camera-frame normals facing the camera, 0 where no surface
    points: np.ndarray  # [H, W, 3] world hit points, 0 where no surface
    dirs_world: np.ndarray  # [H, W, 3] unit ray directions

    @property
    def rgb(self) -> np.ndarray:
        """Plain shaded colour [H, W, 3] = albedo x shading (no effects)."""
        return self.albedo * self.shading[..., None]


@functools.lru_cache(maxsize=32)  # supersampling shifts the principal point: n^2 + 1 K per view
def _pixel_dirs(K: tuple[float, ...], width: int, height: int) -> np.ndarray:
    """Unit camera-frame directions through pixel centres, row-major [H*W, 3] (shared by all views
    with the same intrinsics)."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1)
    dirs = pixels @ np.linalg.inv(np.reshape(K, (3, 3))).T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs.flags.writeable = False
    return dirs


def camera_rays(viewmat: np.ndarray, K: np.ndarray, width: int, height: int):
    """Rays through pixel centres (+0.5): origin [3], unit world dirs [H*W, 3], camera-frame z of
    each unit dir [H*W] (depth = t * z)."""
    dirs_cam = _pixel_dirs(tuple(K.ravel()), width, height)
    rotation = viewmat[:3, :3]
    origin = -rotation.T @ viewmat[:3, 3]
    return origin, dirs_cam @ rotation, dirs_cam[:, 2]


def render_view(
    caster: RayCaster,
    viewmat: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    sun: np.ndarray,
    ambient: float,
    shadows: bool,
) -> View:
    """Ray-cast one pinhole view. viewmat: [4, 4] world->camera, K: [3, 3], sun: [3] unit, towards
    the sun."""
    origin, dirs, dir_z = camera_rays(viewmat, K, width, height)
    origins = np.broadcast_to(origin, dirs.shape)
    hits = caster.cast(origin, dirs, caster.screen_candidates(viewmat, K, width, height))
    hit = hits.primitive >= 0
    t = np.where(hit, hits.t, 0.0)
    points = np.where(hit[:, None], origins + dirs * t[:, None], 0.0)
    normals, uv = caster.surface(points, hits)

    albedo = np.zeros_like(points)
    for index, rays in group_by_primitive(hits.primitive):
        prim = caster.primitives[index]
        up = normals[rays, 2]
        for name, select in (
            (prim.material, np.ones(len(rays), bool)),
            (prim.top_material, up > 0.9),
            (prim.bottom_material, up < -0.9),
        ):
            if name is None or not select.any():
                continue
            sub = rays[select]
            albedo[sub] = MATERIALS.get(name)(uv[sub], points[sub], np.asarray(prim.color), prim.texture_scale)

    direct = np.clip(normals @ sun, 0.0, None) * hit
    if shadows:
        lit = np.flatnonzero(direct > 0)
        offset = points[lit] + normals[lit] * (10 * caster.eps)
        direct[lit[caster.occluded(offset, sun)]] = 0.0
    shading = np.where(hit, ambient + (1 - ambient) * direct, 0.0)

    normals_cam = normals @ viewmat[:3, :3].T
    facing_away = (normals_cam * (dirs @ viewmat[:3, :3].T)).sum(1) > 0
    normals_cam[facing_away] *= -1

    shape = (height, width)
    return View(
        albedo=np.clip(albedo, 0.0, 1.0).reshape(*shape, 3),
        shading=shading.reshape(shape),
        hit=hit.reshape(shape),
        depth=(t * dir_z).reshape(shape),
        normal=normals_cam.reshape(*shape, 3),
        points=points.reshape(*shape, 3),
        dirs_world=dirs.reshape(*shape, 3),
    )
