"""Hard cases, input validation, the renderer config, batching and the compiled path."""

import math

import pytest
import torch

from hico_plugin.cameras import Camera
from hico_plugin.errors import HicoError
from hico_plugin.rasterizer import RASTERIZER_BACKENDS, RendererConfig, rasterize
from hico_plugin.rasterizer import api as api_module
from hico_plugin.rasterizer import torch_backend as torch_backend_module
from hico_plugin.rasterizer import composite as composite_module

ALL = ("rgb", "alpha", "depth", "normal", "distance", "plane_depth", "depth_normal")
K32 = torch.tensor([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])


def scene(n, seed=0, z=3.0, spread=1.0, log_scale=-2.5):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) * 2 - 1) * spread
    means[:, 2] += z
    return [means, torch.randn(n, 4, generator=g),
            torch.exp(torch.randn(n, 3, generator=g) * 0.3 + log_scale),
            torch.rand(n, generator=g), torch.rand(n, 3, generator=g)]


@pytest.fixture(params=["torch", "fused"])
def compositor(request):
    """Both blending kernels of the torch backend face every hard case."""
    return request.param


def render_and_backprop(params, viewmat=None, K=K32, width=32, height=24, outputs=ALL, **kw):
    """Render every output, backprop a random loss; return outputs and input gradients."""
    leaves = [p.detach().clone().requires_grad_() for p in params]
    viewmat = torch.eye(4) if viewmat is None else viewmat
    out = rasterize(*leaves, viewmat, K, width, height, outputs=outputs, use_compile=False, **kw)
    g = torch.Generator().manual_seed(0)
    loss = sum((img * torch.randn(img.shape, generator=g)).sum() for img in out.images().values())
    if loss.requires_grad:
        loss.backward()
    return out, [p.grad for p in leaves]


def assert_finite(out, grads):
    for name, img in out.images().items():
        assert torch.isfinite(img).all(), name
    for i, g in enumerate(grads):
        assert g is None or torch.isfinite(g).all(), f"gradient of input {i}"


@pytest.mark.parametrize("log_scale", [math.log(1e-7), math.log(1e-3), 0.0, math.log(1e4)])
def test_extreme_scales_finite(log_scale, compositor):
    params = scene(50, log_scale=log_scale)
    out, grads = render_and_backprop(params, compositor=compositor)
    assert_finite(out, grads)
    assert (out.alpha <= 1 + 1e-6).all() and (out.alpha >= 0).all()
    if log_scale > 5:  # huge Gaussians cover the whole image
        assert out.alpha.min() > 0.5


def test_flat_zero_quaternions_and_opacity_extremes(compositor):
    params = scene(40, seed=1)
    params[2][:, 2] = 0.0  # flat: one zero scale
    params[1][:10] = 0.0  # zero quaternions read as identity
    params[3][10:20] = 0.0
    params[3][20:30] = 1.0
    out, grads = render_and_backprop(params, compositor=compositor)
    assert_finite(out, grads)
    assert (out.radii[10:20] == 0).all()  # opacity 0 is never drawn
    assert (grads[1][:10] == 0).all()  # zero quaternion: no gradient, no blow-up
    # flat Gaussians are planes: their normal is their zero axis, the plane depth is positive
    drawn = out.alpha[..., 0] > 0.5
    assert drawn.any() and (out.plane_depth[drawn] > 0).all()


def test_behind_near_far_and_outside_frustum_are_culled(compositor):
    means = torch.tensor([[0.0, 0, -2], [0, 0, 0.005], [0, 0, 0.02], [100.0, 0, 1], [0, 0, 2e10],
                          [0.0, 0, 2]])
    n = len(means)
    params = [means, torch.randn(n, 4), torch.full((n, 3), 0.05), torch.full((n,), 0.9),
              torch.rand(n, 3)]
    out, grads = render_and_backprop(params, compositor=compositor)
    assert_finite(out, grads)
    assert out.radii.tolist()[:2] == [0, 0] and out.radii[3] == 0 and out.radii[4] == 0
    assert out.radii[2] > 0 and out.radii[5] > 0  # just past near: drawn (it fills the view)
    for i in (0, 1, 3, 4):
        assert (grads[0][i] == 0).all()


def test_straddling_near_plane_is_finite(compositor):
    params = scene(30, seed=2, z=0.3, spread=0.4, log_scale=math.log(0.5))
    out, grads = render_and_backprop(params, near=0.2, compositor=compositor)
    assert_finite(out, grads)


def test_no_gaussians(compositor):
    empty = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)]
    bg = torch.tensor([0.1, 0.2, 0.3])
    out, grads = render_and_backprop(empty, background=bg, compositor=compositor)
    assert (out.rgb == bg).all() and (out.alpha == 0).all() and (out.depth == 0).all()
    assert out.means2d.shape == (0, 2) and out.radii.shape == (0,)
    assert_finite(out, grads)


def test_thousands_in_one_tile(compositor):
    g = torch.Generator().manual_seed(3)
    n = 4000
    means = torch.cat([torch.rand(n, 2, generator=g) * 0.02 - 0.01,
                       torch.rand(n, 1, generator=g) + 2], 1)
    params = [means, torch.randn(n, 4, generator=g), torch.full((n, 3), 0.002),
              torch.rand(n, generator=g) * 0.3, torch.rand(n, 3, generator=g)]
    out, grads = render_and_backprop(params, K=torch.tensor([[100.0, 0, 8], [0, 100, 8], [0, 0, 1]]),
                                     width=16, height=16, compositor=compositor)
    assert_finite(out, grads)
    assert out.alpha[8, 8] > 0.99
    # transmittance early stop: the far Gaussians behind a saturated pixel get no colour gradient
    far = means[:, 2] > 2.9
    assert (grads[4][far] == 0).all()


@pytest.mark.parametrize("width,height", [(1, 1), (17, 5), (33, 40)])
def test_odd_image_sizes(width, height, compositor):
    K = torch.tensor([[float(width), 0, width / 2], [0, float(width), height / 2], [0, 0, 1]])
    out, grads = render_and_backprop(scene(80, seed=4), K=K, width=width, height=height, compositor=compositor)
    assert_finite(out, grads)
    assert out.rgb.shape == (height, width, 3) and out.depth_normal.shape == (height, width, 3)
    assert out.alpha.max() > 0


def test_city_scale_coordinates_float32(compositor):
    offset = torch.tensor([1e5, -1e5, 50.0])
    params = scene(60, seed=5)
    near_out, _ = render_and_backprop(params, compositor=compositor)
    params[0] = params[0] + offset
    viewmat = torch.eye(4)
    viewmat[:3, 3] = -offset
    out, grads = render_and_backprop(params, viewmat=viewmat, compositor=compositor)
    assert_finite(out, grads)
    # float32 stores 1e5 to ~8 mm; the image may move by that much, not more
    assert (out.alpha - near_out.alpha).abs().mean() < 0.02
    covered = (out.alpha > 0.1) & (near_out.alpha > 0.1)
    assert covered.sum() > 50 and (out.depth - near_out.depth)[covered].abs().max() < 0.05


def test_camera_looking_straight_down(compositor):
    g = torch.Generator().manual_seed(6)
    n = 300
    means = torch.cat([torch.rand(n, 2, generator=g) * 4 - 2, torch.zeros(n, 1)], 1)  # ground z = 0
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    scales = torch.tensor([[0.3, 0.3, 0.0]]).repeat(n, 1)
    # camera 10 m above, looking along -z (world): camera axes x=(1,0,0), y=(0,-1,0), z=(0,0,-1)
    viewmat = torch.eye(4)
    viewmat[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
    viewmat[:3, 3] = torch.tensor([0.0, 0.0, 10.0])
    params = [means, quats, scales, torch.full((n,), 0.8), torch.rand(n, 3, generator=g)]
    out, grads = render_and_backprop(params, viewmat=viewmat, compositor=compositor)
    assert_finite(out, grads)
    solid = out.alpha[..., 0] > 0.99
    assert solid.sum() > 100
    torch.testing.assert_close(out.depth[solid], torch.full_like(out.depth[solid], 10.0))
    torch.testing.assert_close(out.plane_depth[solid], torch.full_like(out.depth[solid], 10.0),
                               atol=1e-3, rtol=0)
    unit = out.normal[solid] / out.normal[solid].norm(dim=-1, keepdim=True)
    torch.testing.assert_close(unit, torch.tensor([0.0, 0, -1]).expand_as(unit), atol=1e-4, rtol=0)


def test_batched_cameras_match_single_and_means2d_grad():
    params = [p.requires_grad_() for p in scene(100, seed=7)]
    v1 = torch.eye(4)
    v2 = torch.eye(4)
    v2[:3, 3] = torch.tensor([0.3, -0.1, 0.2])
    both = rasterize(*params, torch.stack([v1, v2]), torch.stack([K32, K32]), 32, 24, outputs=ALL,
                     use_compile=False)
    assert both.rgb.shape == (2, 24, 32, 3) and both.means2d.shape == (2, 100, 2)
    assert both.radii.shape == (2, 100)
    for i, v in enumerate((v1, v2)):
        one = rasterize(*params, v, K32, 32, 24, outputs=ALL, use_compile=False)
        for name in ALL:
            torch.testing.assert_close(getattr(both, name)[i], getattr(one, name), msg=name)
    both.means2d.retain_grad()
    both.rgb.sum().backward()
    assert both.means2d.grad.shape == (2, 100, 2) and both.means2d.grad.abs().sum() > 0


def test_rgb_alone_composites_only_colour_channels(monkeypatch):
    seen = []
    real = torch_backend_module.composite

    def spy(means2d, conics, opacities, features, bins, **kw):
        seen.append(features.shape[-1])
        return real(means2d, conics, opacities, features, bins, **kw)

    def no_geometry(*args, **kw):
        raise AssertionError("rgb alone must not compute per-Gaussian normals")

    monkeypatch.setattr(torch_backend_module, "composite", spy)
    params = scene(20)
    colors5 = torch.rand(20, 5)
    monkeypatch.setattr(api_module, "gaussian_normals", no_geometry)
    torch_only = dict(use_compile=False, compositor="torch")
    out = rasterize(*params[:4], colors5, torch.eye(4), K32, 32, 24, **torch_only)
    assert out.alpha is None and out.depth is None and out.rgb.shape == (24, 32, 5)
    monkeypatch.undo()
    monkeypatch.setattr(torch_backend_module, "composite", spy)
    rasterize(*params[:4], colors5, torch.eye(4), K32, 32, 24, outputs=("alpha",), **torch_only)
    rasterize(*params[:4], colors5, torch.eye(4), K32, 32, 24, outputs=("rgb", "depth"), **torch_only)
    rasterize(*params[:4], colors5, torch.eye(4), K32, 32, 24, outputs=ALL, **torch_only)
    assert seen == [5, 0, 6, 5 + 3 + 1 + 1]


@pytest.mark.parametrize("change,match", [
    (lambda a: a.update(means=torch.zeros(5, 2)), "means must have shape"),
    (lambda a: a.update(quats=torch.zeros(4, 4)), "quats must have shape"),
    (lambda a: a.update(opacities=torch.zeros(5, 1)), "opacities must have shape"),
    (lambda a: a.update(colors=torch.zeros(5, 3, dtype=torch.float64)), "share one dtype"),
    (lambda a: a.update(viewmat=torch.eye(3)), "viewmat must be"),
    (lambda a: a.update(K=torch.eye(3)[None]), "K must be"),
    (lambda a: a.update(outputs=("rgb", "colour")), "unknown outputs"),
    (lambda a: a.update(background=torch.zeros(4)), "background must have shape"),
    (lambda a: a.update(width=0), "width and height"),
    (lambda a: a.update(near=2.0, far=1.0), "near < far"),
    (lambda a: a.update(depth_normal_from="normal"), "depth_normal_from"),
    (lambda a: a.update(backend="vulkan"), "unknown rasterizer backend 'vulkan'"),
    (lambda a: a.update(compositor="cuda"), "compositor must be one of"),
    (lambda a: a.update(means=torch.zeros(5, 3, dtype=torch.int64)), "floating-point"),
])
def test_bad_input_is_one_clear_error(change, match):
    args = dict(means=torch.zeros(5, 3), quats=torch.zeros(5, 4), scales=torch.zeros(5, 3),
                opacities=torch.zeros(5), colors=torch.zeros(5, 3), viewmat=torch.eye(4), K=K32,
                width=8, height=8)
    change(args)
    kw = {k: args.pop(k) for k in list(args) if k not in
          ("means", "quats", "scales", "opacities", "colors", "viewmat", "K", "width", "height")}
    with pytest.raises(HicoError, match=match):
        rasterize(*args.values(), **kw)


def test_renderer_config_builds_a_camera_renderer():
    assert "torch" in RASTERIZER_BACKENDS
    renderer = RendererConfig(use_compile=False).setup()
    cam = Camera(viewmat=torch.eye(4), K=K32, width=32, height=24)
    out = renderer(*scene(30), cam, outputs=("rgb", "alpha"))
    assert out.rgb.shape == (24, 32, 3) and out.alpha.shape == (24, 32, 1)
    with pytest.raises(HicoError, match="rasterizer backend"):
        RendererConfig(backend="nope").setup()
    with pytest.raises(HicoError, match="renderer.compositor must be one of"):
        RendererConfig(compositor="nope").setup()


def test_compiled_compositor_matches_eager():
    params = scene(150, seed=8)
    leaves = [[p.detach().clone().requires_grad_() for p in params] for _ in range(2)]
    outs = []
    for use_compile, ps in zip((False, True), leaves):
        out = rasterize(*ps, torch.eye(4), K32, 32, 24, outputs=("rgb", "alpha", "plane_depth"),
                        use_compile=use_compile, compositor="torch", tile_size=16)
        (out.rgb.square().sum() + out.plane_depth.sum()).backward()
        outs.append(out)
    assert not composite_module.KERNELS.failed
    for name in ("rgb", "alpha", "plane_depth"):
        torch.testing.assert_close(getattr(outs[1], name), getattr(outs[0], name), atol=1e-5, rtol=1e-5)
    for a, b in zip(leaves[0], leaves[1]):
        torch.testing.assert_close(b.grad, a.grad, atol=1e-4, rtol=1e-4)


def test_chunking_does_not_change_the_image():
    params = scene(200, seed=9)
    viewmat = torch.eye(4)
    from hico_plugin.rasterizer.composite import composite
    from hico_plugin.rasterizer.projection import project_gaussians
    from hico_plugin.rasterizer.tiling import bin_gaussians
    proj = project_gaussians(params[0], params[1], params[2], params[3], viewmat[None], K32[None],
                             32, 24)
    bins = bin_gaussians(proj.means2d, proj.conics, proj.reach, proj.extents, proj.depths,
                         proj.radii, 32, 24, 16)
    args = (proj.means2d.reshape(-1, 2), proj.conics.reshape(-1, 3), params[3], params[4], bins)
    whole = composite(*args)
    tiny = composite(*args, pairs_per_chunk=1)  # one tile per chunk
    for a, b in zip(whole, tiny):
        torch.testing.assert_close(a, b)
