"""The learned environment: world ray directions, compositing behind the Gaussians, the switch, and
runs from when it was called "sky"."""

from __future__ import annotations

import math

import torch

from hico_plugin.cameras import Camera
from hico_plugin.data.sources import DataSourceConfig
from hico_plugin.model import HiCoModelConfig
from hico_plugin.model.effects.environment import EnvironmentConfig, ray_directions
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


def test_environment_depends_on_direction_only():
    environment = EnvironmentConfig(hidden_dim=8).setup()
    K = torch.tensor([[10.0, 0.0, 4.0], [0.0, 10.0, 3.0], [0.0, 0.0, 1.0]])
    viewmat = torch.eye(4)
    moved = viewmat.clone()
    moved[:3, 3] = torch.tensor([100.0, -50.0, 3.0])
    turned = viewmat.clone()
    turned[:3, :3] = _rotation_z(0.7)
    a, b, c = (environment(Camera(v, K, 8, 6)) for v in (viewmat, moved, turned))
    assert a.shape == (6, 8, 3) and bool(((a > 0) & (a < 1)).all())
    torch.testing.assert_close(a, b)
    assert not torch.allclose(a, c)


def test_a_strided_environment_interpolates_the_per_pixel_one_and_trains():
    torch.manual_seed(0)
    K = torch.tensor([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
    camera = Camera(torch.eye(4), K, 320, 240)
    per_pixel = EnvironmentConfig(stride=1).setup()
    strided = EnvironmentConfig(stride=4).setup()
    strided.load_state_dict(per_pixel.state_dict())
    exact, image = per_pixel(camera), strided(camera)
    assert image.shape == exact.shape == (240, 320, 3)
    # Close to the per-pixel field, which varies slowly with the direction.
    torch.testing.assert_close(image, exact, atol=2e-3, rtol=0)
    # The MLP ran on the 80x60 camera: pixel 6 lies at coarse coordinate (6 + 0.5) / 4 - 0.5 = 1.125.
    coarse = per_pixel(camera.scaled(0.25))
    w = torch.tensor([0.875, 0.125])
    torch.testing.assert_close(image[6, 6], torch.einsum("i,j,ijc->c", w, w, coarse[1:3, 1:3]))
    image.sum().backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in strided.parameters())


def test_model_composites_the_environment_only_where_alpha_leaves_room():
    dataset = DataSourceConfig(scene="tiny").setup()
    camera = dataset.cameras[int(dataset.train_indices[0])].scaled(0.5)
    with_environment = HiCoModelConfig(renderer=RendererConfig(use_compile=False), eval_lpips="none",
                                       effects="auto,environment=on").setup(dataset=dataset)
    with torch.no_grad():
        out, gaussians = with_environment.render(camera, ("rgb",))
        bare = with_environment.renderer(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                                         gaussians.colors, camera, outputs=("rgb", "alpha"))
        environment = with_environment.effects["environment"](camera)
    torch.testing.assert_close(out.rgb, bare.rgb + (1 - bare.alpha) * environment)
    groups = with_environment.param_groups()
    assert "environment" in groups and "environment" in with_environment.lr_schedules(100)
    assert "background" not in groups  # the environment replaces the constant background

    without = HiCoModelConfig(renderer=RendererConfig(use_compile=False), eval_lpips="none",
                              effects="auto,sky=off", background=(1.0, 0.0, 0.0)).setup(dataset=dataset)
    assert without.effect_choices["environment"].on is False  # "sky", the old name, still switches it
    assert "environment" not in without.effects and "environment" not in without.param_groups()
    with torch.no_grad():
        out, gaussians = without.render(camera, ("rgb",))
        bare = without.renderer(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                                gaussians.colors, camera, outputs=("rgb", "alpha"))
    torch.testing.assert_close(out.rgb, bare.rgb + (1 - bare.alpha) * torch.tensor([1.0, 0.0, 0.0]))


def test_a_run_from_when_the_environment_was_called_sky_loads_and_resumes(tmp_path):
    """A config.yml naming ``sky`` (config class, field, effect and optimizer group; no learned background)
    with a checkpoint holding ``effects.sky.*`` and the optimizer group ``sky`` loads and trains on."""
    import dataclasses

    from hico_plugin.cli.train import parse, train
    from hico_plugin.engine.config_io import load_config
    from hico_plugin.engine.loading import load_run

    train(parse(["hico-gs-lite", "--scene", "tiny", "--max-steps", "2", "--vis", "none", "--progress", "none",
                 "--output-dir", str(tmp_path), "--model.eval-lpips", "none",
                 "--model.renderer.no-use-compile", "--model.effects", "environment=on,exposure=off,lod=off"]))
    run = tmp_path
    text = (run / "config.yml").read_text()
    for today, before in (("environment=on", "sky=on"), ("  learn_background: true\n", ""),
                          ("environment: !dataclass:hico_plugin.model.effects.environment.EnvironmentConfig",
                           "sky: !dataclass:hico_plugin.model.effects.sky.SkyConfig"),
                          ("    environment: !dataclass:hico_plugin.engine", "    sky: !dataclass:hico_plugin.engine")):
        assert today in text
        text = text.replace(today, before)
    (run / "config.yml").write_text(text)
    (checkpoint,) = (run / "checkpoints").iterdir()
    payload = torch.load(checkpoint, weights_only=True)
    payload["model"] = {key.replace("effects.environment.", "effects.sky."): value
                        for key, value in payload["model"].items()}
    payload["optimizers"]["sky"] = payload["optimizers"].pop("environment")
    torch.save(payload, checkpoint)

    loaded = load_run(run / "config.yml")
    assert loaded.model.config.learn_background is False and "environment" in loaded.model.effects
    torch.testing.assert_close(loaded.model.effects["environment"].mlp[0].weight,
                               payload["model"]["effects.sky.mlp.0.weight"])
    trainer = dataclasses.replace(load_config(run / "config.yml"), max_steps=3, resume=True).setup()
    trainer.train()
    assert trainer.step == 3 and "environment" in trainer.optimizers
