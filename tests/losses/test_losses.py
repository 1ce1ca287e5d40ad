"""Analytic cases for the photometric and DNGC losses."""

from __future__ import annotations

import math

import pytest
import torch

from hico_plugin.errors import HicoError
from hico_plugin.losses import (
    LOSSES,
    DNGCLossConfig,
    Losses,
    PhotometricLossConfig,
    default_losses,
    dngc_losses,
    edge_aware_smoothness,
    edge_weights,
    normal_consistency_loss,
    warmup_weight,
)
from hico_plugin.rasterizer.base import RenderOutputs

H, W = 12, 16
K = torch.tensor([[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def plane_render(plane_normal, plane_distance: float):
    """Exact render outputs of an opaque plane n . X = -d (n unit, facing the camera) seen through K.

    n_d is computed as the paper's Sec. 3.1 describes it (back-projection with integer pixel
    coordinates, central differences, a x b, zero border), independently of the loss code.
    """
    n = torch.tensor(plane_normal, dtype=torch.float64)
    n = n / n.norm()
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    depth = plane_distance / -(rays @ n)
    points = depth[..., None] * rays
    a = points[1:-1, 2:] - points[1:-1, :-2]
    b = points[:-2, 1:-1] - points[2:, 1:-1]
    depth_normal = torch.zeros(H, W, 3, dtype=torch.float64)
    depth_normal[1:-1, 1:-1] = torch.nn.functional.normalize(torch.linalg.cross(a, b), dim=-1)
    return dict(
        rgb=torch.full((H, W, 3), 0.5, dtype=torch.float64),
        alpha=torch.ones(H, W, 1, dtype=torch.float64),
        normal=n.expand(H, W, 3).clone(),
        depth_normal=depth_normal,
        distance=torch.full((H, W, 1), plane_distance, dtype=torch.float64),
    )


@pytest.mark.parametrize("plane_normal", [(0.0, 0.0, -1.0), (0.3, -0.4, -1.0)])
def test_plane_gives_zero_dngc(plane_normal):
    images = plane_render(plane_normal, 2.5)
    terms = dngc_losses(**images)
    assert terms["nc"].item() == pytest.approx(0.0, abs=1e-9)
    assert terms["ns"].item() == pytest.approx(0.0, abs=1e-12)
    assert terms["ds"].item() == pytest.approx(0.0, abs=1e-12)


def test_normal_consistency_known_value_and_alpha_weighting():
    normal = torch.zeros(2, 2, 3)
    normal[..., 2] = -1.0
    depth_normal = normal.clone()
    depth_normal[0, 0] = torch.tensor([1.0, 0.0, 0.0])  # ||(0,0,-1) - (1,0,0)||_1 = 2
    alpha = torch.tensor([[0.5, 1.0], [1.0, 0.5]])[..., None]
    assert normal_consistency_loss(normal, depth_normal, alpha).item() == pytest.approx(0.5 * 2 / 3.0)
    # n_r scaled by alpha (as composited) changes nothing: both are normalised.
    assert normal_consistency_loss(normal * alpha, depth_normal, alpha).item() == pytest.approx(1 / 3.0)
    # A pixel with undefined n_d drops out of numerator and denominator.
    depth_normal[1, 1] = 0.0
    assert normal_consistency_loss(normal, depth_normal, alpha).item() == pytest.approx(1.0 / 2.5)


def test_step_edge_is_down_weighted_by_the_image_edge():
    distance = torch.ones(H, W, 1)
    distance[:, W // 2:] = 2.0  # a unit jump in d between two columns
    flat = torch.full((H, W, 3), 0.5)
    edged = flat.clone()
    edged[:, W // 2:] = 0.8  # an image edge of 0.3 at the same place
    without_edge = edge_aware_smoothness(distance, *edge_weights(flat))
    with_edge = edge_aware_smoothness(distance, *edge_weights(edged))
    assert without_edge.item() == pytest.approx(H * 1.0 / (H * (W - 1)))
    assert with_edge.item() == pytest.approx(without_edge.item() * math.exp(-10 * 0.3), rel=1e-5)
    weight_x, weight_y = edge_weights(edged)
    assert weight_x.shape == (H, W - 1) and weight_y.shape == (H - 1, W)
    assert torch.allclose(weight_y, torch.ones_like(weight_y))


def test_edge_weights_do_not_carry_gradient_to_the_image():
    rgb = torch.rand(H, W, 3, requires_grad=True)
    distance = torch.rand(H, W, 1, requires_grad=True)
    edge_aware_smoothness(distance, *edge_weights(rgb)).backward()
    assert rgb.grad is None and distance.grad.abs().sum() > 0


def test_gradients_finite_with_zero_alpha_everywhere():
    images = {name: torch.zeros(H, W, c, requires_grad=True) for name, c in
              [("rgb", 3), ("alpha", 1), ("normal", 3), ("depth_normal", 3), ("distance", 1)]}
    terms = dngc_losses(**images)
    total = sum(terms.values())
    total.backward()
    assert all(value.item() == 0.0 for value in terms.values())
    for tensor in images.values():
        assert tensor.grad is None or torch.isfinite(tensor.grad).all()


def test_gradients_finite_with_depth_discontinuities():
    generator = torch.Generator().manual_seed(3)
    distance = torch.rand(H, W, 1, generator=generator)
    distance[:, :5] += 1e4  # a huge jump (sky / building boundary)
    normal = torch.randn(H, W, 3, generator=generator)
    normal[0] = 0.0  # nothing drawn in the first row
    depth_normal = torch.randn(H, W, 3, generator=generator)
    depth_normal[:, 0] = 1e-30  # undefined, tiny but non-zero
    depth_normal[-1] = 0.0
    leaves = [t.requires_grad_() for t in (normal, depth_normal, distance)]
    terms = dngc_losses(torch.rand(H, W, 3, generator=generator), torch.rand(H, W, 1, generator=generator),
                        normal, depth_normal, distance)
    sum(terms.values()).backward()
    assert all(torch.isfinite(v) for v in terms.values())
    for leaf in leaves:
        assert torch.isfinite(leaf.grad).all()
    assert (normal.grad[0] == 0).all() and (depth_normal.grad[:, 0] == 0).all()


def test_dngc_terms_gradcheck_float64():
    generator = torch.Generator().manual_seed(4)
    h, w = 4, 5
    rgb = torch.rand(h, w, 3, generator=generator, dtype=torch.float64)
    alpha = torch.rand(h, w, 1, generator=generator, dtype=torch.float64)
    normal = torch.randn(h, w, 3, generator=generator, dtype=torch.float64, requires_grad=True)
    depth_normal = torch.randn(h, w, 3, generator=generator, dtype=torch.float64, requires_grad=True)
    distance = torch.rand(h, w, 1, generator=generator, dtype=torch.float64, requires_grad=True)

    def all_terms(n, nd, d):
        terms = dngc_losses(rgb, alpha, n, nd, d)
        return terms["nc"], terms["ns"], terms["ds"]

    assert torch.autograd.gradcheck(all_terms, (normal, depth_normal, distance), eps=1e-6, atol=1e-6)


def test_warmup_schedule():
    assert warmup_weight(0, 100, 1000) == 0.0
    assert warmup_weight(100, 100, 1000) == 0.0
    assert warmup_weight(350, 100, 1000) == pytest.approx(0.25)
    assert warmup_weight(1100, 100, 1000) == 1.0
    assert warmup_weight(10**6, 100, 1000) == 1.0
    assert warmup_weight(100, 100, 0) == 0.0 and warmup_weight(101, 100, 0) == 1.0


def test_dngc_component_outputs_and_weighting():
    loss = LOSSES.get("dngc")(start_step=10, warmup_steps=20).setup()
    assert loss.required_outputs(5) == set() and loss.required_outputs(10) == set()
    assert loss.required_outputs(11) == {"rgb", "alpha", "normal", "depth_normal", "distance"}
    generator = torch.Generator().manual_seed(5)
    images = {name: torch.rand(H, W, c, generator=generator) for name, c in
              [("rgb", 3), ("alpha", 1), ("normal", 3), ("depth_normal", 3), ("distance", 1)]}
    outputs = RenderOutputs(**images)
    assert loss(RenderOutputs(rgb=images["rgb"]), images["rgb"], step=3) == {}
    raw = dngc_losses(**images)
    terms = loss(outputs, images["rgb"], step=15)  # w = 0.25
    assert set(terms) == {"dngc_nc", "dngc_ns", "dngc_ds"}
    assert terms["dngc_nc"].item() == pytest.approx(0.25 * 0.05 * raw["nc"].item())
    assert terms["dngc_ds"].item() == pytest.approx(0.25 * 0.01 * raw["ds"].item())
    with pytest.raises(HicoError, match="depth_normal"):
        loss(RenderOutputs(rgb=images["rgb"], alpha=images["alpha"], normal=images["normal"],
                           distance=images["distance"]), images["rgb"], step=15)


def test_photometric_known_values_and_gradient():
    target = torch.rand(1, 20, 24, 3, generator=torch.Generator().manual_seed(6))
    loss = PhotometricLossConfig().setup()
    same = loss(RenderOutputs(rgb=target.clone()), target, step=0)
    assert same["rgb_l1"].item() == 0.0 and same["rgb_dssim"].item() == pytest.approx(0.0, abs=1e-6)
    shifted = (target * 0.8 + 0.1).requires_grad_()
    terms = loss(RenderOutputs(rgb=shifted), target, step=0)
    expected_l1 = (shifted - target).abs().mean().item()
    assert terms["rgb_l1"].item() == pytest.approx(0.8 * expected_l1)
    assert terms["rgb_dssim"].item() > 0
    sum(terms.values()).backward()
    assert torch.isfinite(shifted.grad).all() and shifted.grad.abs().sum() > 0
    with pytest.raises(HicoError, match="ssim_lambda"):
        PhotometricLossConfig(ssim_lambda=1.5).setup()


def test_loss_set_unions_outputs_and_terms():
    losses = Losses.setup({**default_losses(), "dngc": DNGCLossConfig(start_step=0, warmup_steps=0)})
    assert losses.required_outputs(1) == {"rgb", "alpha", "normal", "depth_normal", "distance"}
    assert Losses.setup(default_losses()).required_outputs(0) == {"rgb"}
    images = plane_render((0.0, 0.0, -1.0), 2.0)
    images = {k: v.float()[None].expand(2, *v.shape) for k, v in images.items()}  # two cameras
    terms = losses(RenderOutputs(**images), images["rgb"], step=1)
    assert set(terms) == {"rgb_l1", "rgb_dssim", "dngc_nc", "dngc_ns", "dngc_ds"}
    assert all(abs(value.item()) < 1e-5 for value in terms.values())


def _disc_plane(disc_tilt: float):
    """Flat discs with centres on the plane z = 3 + 0.3 x (camera = world frame), each disc's normal
    tilted by ``disc_tilt`` about y from the camera axis; disc_tilt = atan(0.3) lies them in the plane."""
    grid = torch.linspace(-1.2, 1.2, 25)
    x, y = torch.meshgrid(grid, grid, indexing="ij")
    means = torch.stack([x.ravel(), y.ravel(), 3 + 0.3 * x.ravel()], -1)
    # Rotation by -disc_tilt about y takes the disc axis z to (-sin, 0, cos) (flipped to face the camera).
    half = -disc_tilt / 2
    quats = torch.tensor([math.cos(half), 0.0, math.sin(half), 0.0]).expand(len(means), 4).contiguous()
    scales = torch.tensor([0.08, 0.08, 1e-4]).expand(len(means), 3).contiguous()
    return means, quats, scales


@pytest.mark.parametrize("disc_tilt, expect_consistent", [(math.atan(0.3), True), (-0.5, False)])
def test_dngc_on_rasterized_plane(disc_tilt, expect_consistent):
    """The rasterizer's n_r and n_d conventions agree with the loss: discs lying in their plane give
    L_nc ~ 0, discs tilted against it do not."""
    from hico_plugin.rasterizer import rasterize

    means, quats, scales = _disc_plane(disc_tilt)
    K_px = torch.tensor([[30.0, 0.0, 16.0], [0.0, 30.0, 16.0], [0.0, 0.0, 1.0]])
    out = rasterize(means, quats, scales, torch.full((len(means),), 0.9), torch.full((len(means), 3), 0.5),
                    torch.eye(4), K_px, 32, 32, outputs=("rgb", "alpha", "normal", "distance", "depth_normal"),
                    use_compile=False)
    nc = dngc_losses(out.rgb, out.alpha, out.normal, out.depth_normal, out.distance)["nc"].item()
    assert (nc < 1e-3) if expect_consistent else (nc > 0.3)


def test_losses_config_is_the_registry_and_scales_its_own_schedules():
    assert list(default_losses()) == [name for name, _ in LOSSES.registered()] == ["rgb", "dngc"]
    losses = Losses.setup(default_losses(), schedule_scale=0.1)
    dngc = losses.components["dngc"]
    assert (dngc.start_step, dngc.warmup_steps) == (1000, 1000)
    assert losses.metrics(1500) == {"dngc_weight": 0.5}
    assert Losses.setup(default_losses()).components["dngc"].start_step == 10_000


def test_a_disabled_loss_is_not_built_and_a_foreign_config_is_named():
    losses = Losses.setup({**default_losses(), "dngc": DNGCLossConfig(enabled=False)})
    assert list(losses.components) == ["rgb"] and losses.metrics(10**6) == {}
    with pytest.raises(HicoError, match=r"model\.losses\.environment: expected a loss config .*got EnvironmentConfig"):
        from hico_plugin.model.effects.environment import EnvironmentConfig

        Losses.setup({"environment": EnvironmentConfig()})


def test_every_registered_loss_is_offered_switched_off(monkeypatch):
    from hico_plugin.losses import LossConfig, with_every_loss

    class TestOnlyLoss(LossConfig):
        pass

    monkeypatch.setitem(LOSSES._entries, "test-only", TestOnlyLoss)  # registered for this test only
    offered = with_every_loss({"rgb": PhotometricLossConfig(ssim_lambda=0.3)})
    assert list(offered) == ["rgb", "dngc", "test-only"]
    assert offered["rgb"].ssim_lambda == 0.3 and offered["rgb"].enabled
    assert not offered["dngc"].enabled and not offered["test-only"].enabled
