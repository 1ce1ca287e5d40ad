"""The learned sky: world ray directions, compositing behind the Gaussians, and the switch."""

from __future__ import annotations

import math

import torch

from hico_plugin.cameras import Camera
from hico_plugin.data.sources import DataSourceConfig
from hico_plugin.model import HiCoModelConfig
from hico_plugin.model.effects.sky import SkyConfig, ray_directions
from hico_plugin.rasterizer.renderer import RendererConfig


def _rotation_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_ray_directions_are_unit_world_rays_through_pixel_centres():
    # A camera looking along world +x: camera z (forward) = world x, camera x = world -y, camera y = world -z.
    cam_to_world = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    viewmat = torch.eye(4)
    viewmat[:3, :3] = cam_to_world.T
    viewmat[:3, 3] = torch.tensor([5.0, -2.0, 1.0])  # translation must not matter for directions
    K = torch.tensor([[4.0, 0.0, 1.5], [0.0, 4.0, 1.5], [0.0, 0.0, 1.0]])
    dirs = ray_directions(Camera(viewmat, K, 3, 3))
    assert dirs.shape == (3, 3, 3)
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones(3, 3))
    torch.testing.assert_close(dirs[1, 1], torch.tensor([1.0, 0.0, 0.0]))  # centre pixel: straight ahead
    # Pixel (u=2.5, v=1.5) is right of centre: camera +x, world -y.
    expected = torch.tensor([1.0, -0.25, 0.0])
    torch.testing.assert_close(dirs[1, 2], expected / expected.norm())


def test_sky_depends_on_direction_only():
    sky = SkyConfig(hidden_dim=8).setup()
    K = torch.tensor([[10.0, 0.0, 4.0], [0.0, 10.0, 3.0], [0.0, 0.0, 1.0]])
    viewmat = torch.eye(4)
    moved = viewmat.clone()
    moved[:3, 3] = torch.tensor([100.0, -50.0, 3.0])
    turned = viewmat.clone()
    turned[:3, :3] = _rotation_z(0.7)
    a, b, c = (sky(Camera(v, K, 8, 6)) for v in (viewmat, moved, turned))
    assert a.shape == (6, 8, 3) and bool(((a > 0) & (a < 1)).all())
    torch.testing.assert_close(a, b)
    assert not torch.allclose(a, c)


def test_model_composites_sky_only_where_alpha_leaves_room():
    dataset = DataSourceConfig(scene="tiny").setup()
    camera = dataset.cameras[int(dataset.train_indices[0])].scaled(0.5)
    with_sky = HiCoModelConfig(renderer=RendererConfig(use_compile=False), eval_lpips="none",
                               effects="auto,sky=on").setup(dataset=dataset)
    with torch.no_grad():
        out, gaussians = with_sky.render(camera, ("rgb",))
        bare = with_sky.renderer(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                                 gaussians.colors, camera, outputs=("rgb", "alpha"))
        sky = with_sky.effects["sky"](camera)
    torch.testing.assert_close(out.rgb, bare.rgb + (1 - bare.alpha) * sky)
    assert "sky" in with_sky.param_groups() and "sky" in with_sky.lr_schedules(100)

    without = HiCoModelConfig(renderer=RendererConfig(use_compile=False), eval_lpips="none",
                              effects="auto,sky=off", background=(1.0, 0.0, 0.0)).setup(dataset=dataset)
    assert "sky" not in without.effects and "sky" not in without.param_groups()
    with torch.no_grad():
        out, gaussians = without.render(camera, ("rgb",))
        bare = without.renderer(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                                gaussians.colors, camera, outputs=("rgb", "alpha"))
    torch.testing.assert_close(out.rgb, bare.rgb + (1 - bare.alpha) * torch.tensor([1.0, 0.0, 0.0]))
