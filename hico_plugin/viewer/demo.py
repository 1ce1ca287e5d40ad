"""An analytic scene (ray-cast spheres on a checkered ground) that implements ViewableModel.

It lets the viewer be tried without a trained run (``hico-view --demo``) and gives the tests exact
render outputs: the depth normal n_d comes from finite differences of the depth, as in a real render,
so the n_r vs n_d disagreement shows up at silhouettes. Each surface carries an octree level (spheres:
their own; ground: from distance, like the LOD rule), so the level map and the LOD range work.
CLCA has no meaning here: ``clca_enabled`` is ignored.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from hico_plugin.cameras import Camera, Cameras
from hico_plugin.visualization.options import RenderOptions

_SPHERES = torch.tensor(  # x, y, z, radius, level, r, g, b
    [
        [0.0, 0.0, 1.0, 1.0, 0, 0.85, 0.25, 0.2],
        [2.2, 0.8, 0.5, 0.5, 1, 0.2, 0.6, 0.9],
        [-1.8, 1.5, 0.35, 0.35, 2, 0.95, 0.8, 0.2],
        [-0.6, -2.0, 0.25, 0.25, 3, 0.3, 0.85, 0.4],
    ]
)
NUM_LEVELS = 4
GROUND_RADIUS = 8.0


def ground_level(distance: Tensor) -> Tensor:
    """Octree level of the ground seen at ``distance``: finer nearby, one level per doubling."""
    return (NUM_LEVELS - 1 - torch.log2(distance.clamp(min=1e-6) / 2.5)).clamp(0, NUM_LEVELS - 1).floor()


def orbit_cameras(count: int, radius: float = 7.0, height: float = 3.0, width: int = 160, height_px: int = 120) -> Cameras:
    """``count`` cameras on a circle around the origin looking at (0, 0, 0.5), z up."""
    angles = torch.arange(count, dtype=torch.float64) * (2 * math.pi / count)
    centers = torch.stack([radius * torch.cos(angles), radius * torch.sin(angles), torch.full_like(angles, height)], -1)
    forward = F.normalize(torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64) - centers, dim=-1)
    right = F.normalize(torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(forward)), dim=-1)
    down = torch.linalg.cross(forward, right)
    camera_to_world = torch.stack([right, down, forward], dim=-1)  # columns: OpenCV x, y, z axes
    viewmats = torch.eye(4, dtype=torch.float64).repeat(count, 1, 1)
    viewmats[:, :3, :3] = camera_to_world.transpose(1, 2)
    viewmats[:, :3, 3] = -(camera_to_world.transpose(1, 2) @ centers.unsqueeze(-1)).squeeze(-1)
    focal = 0.9 * width
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height_px / 2], [0.0, 0.0, 1.0]])
    return Cameras(viewmats.float(), K.expand(count, 3, 3).clone(), torch.full((count,), width), torch.full((count,), height_px))


class DemoModel:
    """Ray-cast render of four spheres on a ground plane; anchors sampled on the surfaces."""

    def render_for_display(self, camera: Camera, options: RenderOptions) -> dict[str, Tensor]:
        height, width = camera.height, camera.width
        rows, cols = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
        K = camera.K.float()
        rays_camera = torch.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], torch.ones_like(cols)], -1)
        camera_to_world = camera.viewmat[:3, :3].T.float()
        rays = rays_camera @ camera_to_world.T  # [H, W, 3], z_camera = 1 so ray parameter t = depth
        origin = camera.center.float()
        # Ground plane z = 0 (level from distance, as the LOD rule picks finer levels nearby).
        t_ground = torch.where(rays[..., 2] < -1e-6, -origin[2] / rays[..., 2], torch.full_like(rays[..., 0], math.inf))
        on_disc = (origin[:2] + rays[..., :2] * t_ground[..., None]).norm(dim=-1) < GROUND_RADIUS
        t_ground = torch.where(on_disc, t_ground, math.inf)
        ground_levels = ground_level(t_ground * options.distance_scale)
        candidates_t, candidates_level = [t_ground], [ground_levels]
        for x, y, z, radius, level, *_ in _SPHERES.tolist():
            offset = origin - torch.tensor([x, y, z])
            a = (rays * rays).sum(-1)
            b = 2 * (rays * offset).sum(-1)
            c = float(offset @ offset) - radius**2
            disc = b * b - 4 * a * c
            t = (-b - disc.clamp(min=0).sqrt()) / (2 * a)
            candidates_t.append(torch.where((disc > 0) & (t > 0), t, torch.full_like(t, math.inf)))
            candidates_level.append(torch.full_like(t, level))
        all_t, all_levels = torch.stack(candidates_t), torch.stack(candidates_level)
        if options.level_range is not None:  # LOD override: surfaces of other levels are not drawn
            low, high = options.level_range
            all_t = torch.where((all_levels >= low) & (all_levels <= high), all_t, math.inf)
        depth, surface = all_t.min(0)
        hit = torch.isfinite(depth)
        depth = torch.where(hit, depth, torch.zeros_like(depth))
        points = origin + rays * depth[..., None]
        sphere_centers = _SPHERES[:, :3][(surface - 1).clamp(min=0)]
        normal = torch.where((surface == 0)[..., None], torch.tensor([0.0, 0.0, 1.0]), F.normalize(points - sphere_centers, dim=-1))
        albedo = _SPHERES[:, 5:][(surface - 1).clamp(min=0)]
        checker = ((points[..., 0].floor() + points[..., 1].floor()) % 2)[..., None] * 0.25 + 0.6
        albedo = torch.where((surface == 0)[..., None], checker.expand(-1, -1, 3), albedo)
        light = F.normalize(torch.tensor([0.4, 0.3, 1.0]), dim=0)
        shade = 0.3 + 0.7 * (normal @ light).clamp(min=0)[..., None]
        sky = torch.tensor([0.75, 0.85, 1.0]).expand(height, width, 3)
        rgb = torch.where(hit[..., None], albedo * shade, sky)
        world_to_camera = camera.viewmat[:3, :3].float()
        normal_camera = torch.where(hit[..., None], normal @ world_to_camera.T, torch.zeros(3))
        return {
            "rgb": rgb,
            "depth": depth[..., None],
            "plane_depth": depth[..., None],
            "alpha": hit.float()[..., None],
            "normal": normal_camera,
            "depth_normal": depth_to_normal(depth, K) * hit[..., None],
            "distance": ((points - origin) @ world_to_camera.T * normal_camera).sum(-1, keepdim=True).abs(),
            "level": torch.where(hit, all_levels.gather(0, surface[None])[0], torch.zeros_like(depth))[..., None],
        }

    def viewer_anchors(self) -> tuple[Tensor, Tensor]:
        generator = torch.Generator().manual_seed(0)
        ground = torch.cat([torch.rand(1500, 2, generator=generator) * 10 - 5, torch.zeros(1500, 1)], -1)
        # Seen from the orbit (radius 7): distance to the nearest camera ring point decides the level.
        ground_levels = ground_level(7.0 - ground[:, :2].norm(dim=-1) + 1.0).long()
        directions = F.normalize(torch.randn(len(_SPHERES), 300, 3, generator=generator), dim=-1)
        on_spheres = (_SPHERES[:, None, :3] + directions * _SPHERES[:, None, 3:4]).reshape(-1, 3)
        sphere_levels = _SPHERES[:, 4].long().repeat_interleave(300)
        return torch.cat([ground, on_spheres]), torch.cat([ground_levels, sphere_levels])

    def stats(self) -> dict[str, float]:
        return {"num_anchors": 1500 + 300 * len(_SPHERES)}


def depth_to_normal(depth: Tensor, K: Tensor) -> Tensor:
    """depth: [H, W] -> camera-frame normals [H, W, 3] from central differences of back-projected points."""
    height, width = depth.shape
    rows, cols = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    points = torch.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], torch.ones_like(cols)], -1) * depth[..., None]
    padded = F.pad(points.permute(2, 0, 1)[None], (1, 1, 1, 1), mode="replicate")[0].permute(1, 2, 0)
    d_x = padded[1:-1, 2:] - padded[1:-1, :-2]
    d_y = padded[2:, 1:-1] - padded[:-2, 1:-1]
    return -F.normalize(torch.linalg.cross(d_x, d_y), dim=-1)


class DemoDataset:
    """Orbit cameras around the demo scene; images are renders of DemoModel."""

    def __init__(self, num_cameras: int = 24):
        self.cameras = orbit_cameras(num_cameras)
        self.train_indices = list(range(num_cameras))
        self._model = DemoModel()

    def image(self, index: int) -> Tensor:
        rgb = self._model.render_for_display(self.cameras[index], RenderOptions())["rgb"]
        return (rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
