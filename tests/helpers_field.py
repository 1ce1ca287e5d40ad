"""Small anchor fields and cameras for the field's and the strategies' tests."""

import math

import numpy as np
import torch

from hico_plugin.cameras import Camera, Cameras
from hico_plugin.engine.schedule import LRSchedule
from hico_plugin.field import AnchorField, FieldConfig, OctreeGrid
from hico_plugin.model.hico import default_optimizers
from hico_plugin.scenes.orbits import look_at as orbit_look_at

K = torch.tensor([[100.0, 0.0, 64.0], [0.0, 100.0, 48.0], [0.0, 0.0, 1.0]])


def look_at(eye, target=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """world->camera 4x4 (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    return torch.from_numpy(orbit_look_at(np.array([eye], dtype=np.float64), np.array([target], dtype=np.float64))[0]).float()


def ring_cameras(center=(0.0, 0.0, 0.0), radius=8.0, count=8) -> Cameras:
    c = torch.tensor(center)
    eyes = [(c + torch.tensor([radius * math.cos(a), radius * math.sin(a), 2.0])).tolist()
            for a in np.linspace(0, 2 * math.pi, count, endpoint=False)]
    eyes.append((c + torch.tensor([2.5, 0.5, 1.0])).tolist())  # one close view: more levels
    viewmats = torch.stack([look_at(e, tuple(c.tolist())) for e in eyes])
    n = len(eyes)
    return Cameras(viewmats, K.expand(n, 3, 3).clone(), torch.full((n,), 128), torch.full((n,), 96))


def point_clouds():
    gen = torch.Generator().manual_seed(0)
    yield torch.randn(2000, 3, generator=gen) * 2, (0.0, 0.0, 0.0)
    # All coordinates positive and far from the origin: the base method's x1.1 cube would shrink.
    yield torch.rand(1500, 3, generator=gen) * 4 + 20, (22.0, 22.0, 22.0)
    plane = torch.rand(1500, 3, generator=gen) * 6 - 3
    plane[:, 2] = 0.01 * torch.randn(1500, generator=gen)
    yield plane, (0.0, 0.0, 0.0)


def make_field(**config_changes) -> AnchorField:
    points, _ = next(point_clouds())
    return FieldConfig(**config_changes).setup(points=points, train_cameras=ring_cameras(), schedule_scale=0.1)


def hand_grid(num_levels=3) -> OctreeGrid:
    return OctreeGrid(origin=(0.0, 0.0, 0.0), cube_size=8.0, voxel_size=1.0, num_levels=num_levels, fork=2,
                      d_std=10.0, init_level=1)


def hand_field(positions, levels, camera_centers, **config_changes) -> AnchorField:
    config = FieldConfig(**config_changes)
    return AnchorField(config, torch.tensor(positions, dtype=torch.float32), torch.tensor(levels),
                       hand_grid(), torch.tensor(camera_centers, dtype=torch.float32))


def camera_at(eye, target) -> Camera:
    return Camera(look_at(eye, target), K, 128, 96)


def field_schedules(field) -> dict[str, LRSchedule]:
    """The model's default schedules for the field's groups (scene extent 1, 30k steps)."""
    return {name: default_optimizers()[name].schedule(30_000) for name in field.param_groups()}
