"""The gsplat backend on a CPU-only machine: its clear error, the projection conventions against gsplat's
pure-torch reference, and its channel wiring with gsplat's reference kernels standing in for CUDA."""

from __future__ import annotations

import importlib.util
import math
from types import SimpleNamespace

import pytest
import torch

from hico_plugin.errors import HicoError
from hico_plugin.rasterizer import gsplat_backend, project_gaussians, rasterize
from hico_plugin.rasterizer.projection import ALPHA_MIN

HAS_GSPLAT = importlib.util.find_spec("gsplat") is not None
needs_gsplat = pytest.mark.skipif(not HAS_GSPLAT, reason="gsplat is not installed (pip install -e \".[test]\")")


def look_at(eye: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """World->camera 4x4 (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    forward = torch.nn.functional.normalize(target - eye, dim=0)
    helper = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype)
    if abs(float(forward @ helper)) > 0.99:  # looking straight up / down
        helper = torch.tensor([0.0, 1.0, 0.0], dtype=eye.dtype)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, helper), dim=0)
    down = torch.linalg.cross(forward, right)
    rotation = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
    viewmat = torch.eye(4, dtype=eye.dtype)
    viewmat[:3, :3] = rotation
    viewmat[:3, 3] = -rotation @ eye
    return viewmat


def random_scene(n: int, num_cams: int, seed: int, dtype=torch.float64, spread: float = 1.5):
    generator = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=generator, dtype=dtype) - 0.5) * 2 * spread
    quats = torch.randn(n, 4, generator=generator, dtype=dtype)
    scales = torch.exp(torch.empty(n, 3, dtype=dtype).uniform_(-5.0, -1.0, generator=generator))
    eyes = torch.nn.functional.normalize(torch.randn(num_cams, 3, generator=generator, dtype=dtype), dim=1) * 2.5
    eyes[0] = torch.tensor([0.0, 0.0, 3.0], dtype=dtype)  # one camera looking straight down
    viewmats = torch.stack([look_at(eye, torch.zeros(3, dtype=dtype)) for eye in eyes])
    focal = 30.0 + 20.0 * torch.rand(num_cams, generator=generator, dtype=dtype)
    Ks = torch.zeros(num_cams, 3, 3, dtype=dtype)
    Ks[:, 0, 0], Ks[:, 1, 1] = focal, focal * 1.1
    Ks[:, 0, 2], Ks[:, 1, 2], Ks[:, 2, 2] = 21.0, 15.5, 1.0
    return means, quats, scales, viewmats, Ks


def test_gsplat_backend_raises_clear_error_here():
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA; the error path is for CPU-only machines")
    means, quats, scales, viewmats, Ks = random_scene(5, 1, seed=0, dtype=torch.float32)
    with pytest.raises(HicoError, match=r'pip install -e "\.\[cuda\]"'):
        rasterize(means, quats, scales, torch.ones(5), torch.rand(5, 3), viewmats[0], Ks[0], 40, 30,
                  backend="gsplat")


@needs_gsplat
def test_projection_matches_gsplat_reference():
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    width, height, near = 42, 31, 0.05
    means, quats, scales, viewmats, Ks = random_scene(400, 4, seed=1, spread=2.5)  # some behind cameras
    opacities = torch.ones(400, dtype=torch.float64)
    ours = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, near=near)
    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    radii_xy, means2d, depths, conics, _ = _fully_fused_projection(
        means, covars, viewmats, Ks, width, height, eps2d=0.3, near_plane=near)

    assert torch.allclose(ours.depths, depths, rtol=1e-12, atol=1e-12)
    theirs_visible = (radii_xy > 0).all(-1)
    ours_visible = ours.radii > 0
    both = ours_visible & theirs_visible
    assert both.sum() > 200 and (~theirs_visible).sum() > 50  # the scene exercises both sides
    assert torch.allclose(ours.means2d[both], means2d[both], rtol=1e-10, atol=1e-9)
    assert torch.allclose(ours.conics[both], conics[both], rtol=1e-9, atol=1e-12)

    # Radius: gsplat draws ceil(3.33 sigma) per axis; ours ceil(sqrt(2 ln(o / (1/255))) sigma) of the
    # larger axis -- 3.3290 sigma at opacity 1. Rescaled to gsplat's factor, ours gives gsplat's max.
    reach = math.sqrt(2.0 * math.log(1.0 / ALPHA_MIN))
    rescaled = torch.ceil(ours.extents.amax(-1) * (3.33 / reach)).to(torch.int32)
    assert torch.equal(rescaled[both], radii_xy.amax(-1)[both])
    assert ((radii_xy.amax(-1) - ours.radii)[both] <= 1).all()

    # Culling: ours is gsplat's set minus ellipses whose smaller extent misses the image by < 1 px.
    assert not (ours_visible & ~theirs_visible).any()
    only_theirs = theirs_visible & ~ours_visible
    u, v = means2d[only_theirs].unbind(-1)
    sx, sy = radii_xy[only_theirs].unbind(-1)
    assert ((u + sx > 0) & (u - sx < width) & (v + sy > 0) & (v - sy < height)).all()
    margin = torch.minimum(torch.minimum(u + sx, width - (u - sx)), torch.minimum(v + sy, height - (v - sy)))
    assert (margin <= 1.0 + 0.01 * torch.maximum(sx, sy)).all()


def _reference_ops():
    """gsplat's own pure-torch projection and tile intersection, and a dense brute-force compositor,
    behind the names of gsplat's CUDA entry points, so the backend's wiring runs on CPU."""
    from gsplat.cuda._torch_impl import (
        _fully_fused_projection, _isect_offset_encode, _isect_tiles, _quat_scale_to_covar_preci)

    state = {}

    def fully_fused_projection(means, covars, quats, scales, viewmats, Ks, width, height, *, eps2d,
                               near_plane, far_plane, opacities):
        covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_preci=False)
        radii, means2d, depths, conics, comp = _fully_fused_projection(
            means, covars, viewmats, Ks, width, height, eps2d=eps2d, near_plane=near_plane, far_plane=far_plane)
        state["depths"] = depths.detach()
        return radii, means2d, depths, conics, comp

    def rasterize_to_pixels(means2d, conics, colors, opacities, width, height, tile_size, isect_offsets,
                            flatten_ids):
        num_cams, n = opacities.shape
        drawn = torch.zeros(num_cams * n, dtype=torch.bool)
        drawn[flatten_ids.long()] = True
        ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
        images, alphas = [], []
        for cam in range(num_cams):  # a test reference: clarity over speed
            ids = drawn.view(num_cams, n)[cam].nonzero().squeeze(1)
            ids = ids[state["depths"][cam, ids].argsort()]
            dx = xs.reshape(-1, 1) - means2d[cam, ids, 0]
            dy = ys.reshape(-1, 1) - means2d[cam, ids, 1]
            a, b, c = conics[cam, ids].unbind(-1)
            sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
            alpha = torch.clamp_max(opacities[cam, ids] * torch.exp(-sigma), 0.99)
            alpha = torch.where((sigma >= 0) & (alpha >= 1 / 255), alpha, torch.zeros_like(alpha))
            log_t = torch.cumsum(torch.log1p(-alpha), dim=1)
            weight = torch.where(log_t > math.log(1e-4), alpha * torch.exp(log_t - torch.log1p(-alpha)),
                                 torch.zeros_like(alpha))
            images.append((weight @ colors[cam, ids]).reshape(height, width, -1))
            alphas.append(weight.sum(1).reshape(height, width, 1))
        return torch.stack(images), torch.stack(alphas)

    return SimpleNamespace(fully_fused_projection=fully_fused_projection, isect_tiles=_isect_tiles,
                           isect_offset_encode=_isect_offset_encode, rasterize_to_pixels=rasterize_to_pixels)


ALL_OUTPUTS = ("rgb", "alpha", "depth", "normal", "distance", "plane_depth", "depth_normal")


@needs_gsplat
@pytest.mark.parametrize("num_cams", [1, 2])
def test_gsplat_backend_wiring_matches_torch_backend(monkeypatch, num_cams):
    monkeypatch.setattr(gsplat_backend, "load_gsplat_ops", lambda device: _reference_ops())
    means, quats, scales, viewmats, Ks = random_scene(40, num_cams, seed=2, dtype=torch.float32, spread=0.6)
    scales = scales * 3.0
    quats[0] = 0.0  # zero quaternion = identity in both backends
    generator = torch.Generator().manual_seed(3)
    opacities = torch.rand(40, generator=generator) * 0.9 + 0.1
    colors = torch.rand(40, 3, generator=generator)
    background = torch.tensor([0.1, 0.2, 0.3])
    viewmat, K = (viewmats, Ks) if num_cams > 1 else (viewmats[0], Ks[0])
    kwargs = dict(outputs=ALL_OUTPUTS, background=background, near=0.05)

    means2d_leaf = means.clone().requires_grad_()
    ours = rasterize(means2d_leaf, quats, scales, opacities, colors, viewmat, K, 42, 31, backend="gsplat", **kwargs)
    reference = rasterize(means, quats, scales, opacities, colors, viewmat, K, 42, 31, backend="torch",
                          use_compile=False, **kwargs)
    for name in ALL_OUTPUTS:
        got, want = getattr(ours, name), getattr(reference, name)
        assert got.shape == want.shape, name
        assert torch.allclose(got, want, atol=2e-4, rtol=1e-4), (name, (got - want).abs().max())
    assert reference.alpha.max() > 0.5  # the comparison is not vacuous
    assert ours.radii.shape == reference.radii.shape and ours.means2d.shape == reference.means2d.shape

    # means2d is on the images' autograd path, so retain_grad collects screen-space gradients.
    ours.means2d.retain_grad()
    ours.rgb.sum().backward()
    assert ours.means2d.grad is not None and ours.means2d.grad.abs().sum() > 0

    only_alpha = rasterize(means, quats, scales, opacities, colors, viewmat, K, 42, 31, backend="gsplat",
                           outputs=("alpha",), near=0.05)
    assert only_alpha.rgb is None and torch.allclose(only_alpha.alpha, reference.alpha, atol=2e-4)
