"""The fused CPU depth-normal kernel against the torch chain depth_to_normal(plane_depth(...)): values, gradients,
hard inputs, thread independence, and its use by rasterize."""

from __future__ import annotations

import pytest
import torch

from hico_plugin.rasterizer import api, rasterize
from hico_plugin.rasterizer.depth_normal_fused import KERNEL, depth_normal_from_plane
from hico_plugin.rasterizer.geometry import ALPHA_EPS, depth_to_normal, pixel_rays, plane_depth
from helpers_native import require_kernel

# Relative to the largest magnitude of each compared tensor: rounding of reductions torch orders its own way.
TOL = {torch.float32: 1e-5, torch.float64: 1e-10}


@pytest.fixture(autouse=True)
def _kernel():
    require_kernel(KERNEL)


def reference(normal, distance, alpha, Ks):
    return depth_to_normal(plane_depth(normal, distance, alpha, Ks), Ks)


def planes(num_cams, height, width, dtype=torch.float64, seed=0):
    """Render-like maps (normal, distance, alpha, Ks) away from every threshold: composited normals (alpha times a
    unit normal within ~20 degrees of facing the camera), distances in [1, 3], alpha in [0.3, 1], and a different
    K per camera."""
    generator = torch.Generator().manual_seed(seed)
    alpha = torch.rand(num_cams, height, width, 1, generator=generator, dtype=dtype) * 0.7 + 0.3
    tilt = torch.randn(num_cams, height, width, 3, generator=generator, dtype=dtype) * 0.2
    unit = torch.nn.functional.normalize(tilt + torch.tensor([0.0, 0.0, -1.0], dtype=dtype), dim=-1)
    distance = torch.rand(num_cams, height, width, 1, generator=generator, dtype=dtype) * 2 + 1
    Ks, size = torch.zeros(num_cams, 3, 3, dtype=dtype), max(width, height)
    for c in range(num_cams):
        Ks[c] = torch.tensor([[(0.8 + 0.3 * c) * size, 0, 0.5 * width + c], [0, (0.9 + 0.2 * c) * size,
                              0.5 * height - 0.7 * c], [0, 0, 1]], dtype=dtype)
    return alpha * unit, distance, alpha, Ks


def value_and_grads(fn, normal, distance, alpha, Ks, seed=0):
    """fn's depth normal and the gradients w.r.t. normal and distance under a random upstream gradient (zeros
    where fn's result does not depend on them)."""
    leaves = [normal.detach().clone().requires_grad_(), distance.detach().clone().requires_grad_()]
    out = fn(*leaves, alpha, Ks)
    upstream = torch.randn(out.shape, generator=torch.Generator().manual_seed(seed), dtype=out.dtype)
    if out.requires_grad:  # the torch chain of an image under 3 px is a constant
        (out * upstream).sum().backward()
    return [out] + [t.grad if t.grad is not None else torch.zeros_like(t) for t in leaves]


def assert_close_to_max(got, want, dtype, name):
    """got == want within TOL[dtype] times want's largest magnitude, on the finite entries of want."""
    finite = torch.isfinite(want)
    assert torch.isfinite(got[finite]).all(), f"{name}: non-finite where the torch chain is finite"
    scale = want[finite].abs().max().item() if finite.any() else 0.0
    torch.testing.assert_close(got[finite], want[finite], rtol=0, atol=TOL[dtype] * scale, msg=name)


def assert_matches_reference(normal, distance, alpha, Ks):
    got = value_and_grads(depth_normal_from_plane, normal, distance, alpha, Ks)
    want = value_and_grads(reference, normal, distance, alpha, Ks)
    for name, a, b in zip(("depth_normal", "grad normal", "grad distance"), got, want):
        assert a.shape == b.shape and a.dtype == b.dtype, name
        assert_close_to_max(a, b, normal.dtype, name)
    return got


def test_gradcheck_float64():
    normal, distance, alpha, Ks = planes(2, 6, 7, seed=1)
    inputs = (normal.requires_grad_(), distance.requires_grad_())
    assert torch.autograd.gradcheck(lambda n, d: depth_normal_from_plane(n, d, alpha, Ks), inputs, eps=1e-6,
                                    atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(1, 12, 16), (3, 23, 41), (2, 40, 9)])
def test_values_and_gradients_match_torch(dtype, shape):
    out, _, _ = assert_matches_reference(*(t.to(dtype) for t in planes(*shape, seed=2)))
    inner = out[:, 1:-1, 1:-1]
    torch.testing.assert_close(inner.norm(dim=-1), torch.ones_like(inner[..., 0]))  # defined everywhere inside


def _hard_cases():
    cases = {f"size {h}x{w}": planes(2, h, w, seed=3) for h, w in [(1, 1), (2, 2), (3, 3), (1, 9), (9, 1), (2, 7),
                                                                    (7, 2), (3, 4)]}
    normal, distance, alpha, Ks = planes(2, 14, 17, seed=4)
    alpha[0, 2:6, 3:9] = 0  # nothing drawn, normals still set
    normal[1, 8:, :5] = alpha[1, 8:, :5] = 0  # nothing drawn
    alpha[1, 1::3, 9::2, 0] = torch.tensor([0.0, ALPHA_EPS / 2, ALPHA_EPS, 2 * ALPHA_EPS], dtype=torch.float64)
    cases["empty pixels and alpha at ALPHA_EPS"] = (normal, distance, alpha, Ks)

    normal, distance, alpha, Ks = planes(2, 14, 17, seed=5)
    rays = pixel_rays(Ks, 17, 14)
    edge_on = torch.linalg.cross(rays, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).expand_as(rays), dim=-1)
    normal[:, 3:7] = edge_on[:, 3:7] * alpha[:, 3:7]  # n . r = 0: the plane contains the ray
    normal[0, 9:, 2:8] = torch.tensor([0.1, 0.0, 1.0], dtype=torch.float64) * alpha[0, 9:, 2:8]  # facing away
    normal[1, 9:, 2:8] = 0  # zero normals
    normal[1, 10, 12] *= 1e-7  # -(n . r) below DENOM_EPS * alpha
    cases["edge-on, back-facing and zero normals"] = (normal, distance, alpha, Ks)

    normal, distance, alpha, Ks = planes(2, 14, 17, seed=6)
    alpha[:, 5, 5] = alpha[:, 9, 3:12:2] = 0  # single holes among pixels with depth
    distance[0, 2:4, 10:14] = -1  # negative plane depth: no depth
    distance[1, :, 8] = 0  # a column of zero depth
    cases["pixels without depth next to pixels with depth"] = (normal, distance, alpha, Ks)

    normal, distance, alpha, Ks = planes(2, 14, 17, seed=7)
    distance[0, :, :6] = 1e20
    distance[1] = 1e20
    cases["huge distances"] = (normal, distance, alpha, Ks)

    normal, distance, alpha, Ks = planes(1, 12, 12, seed=8)
    normal[..., 2] = -alpha[..., 0]  # fronto-parallel plane, depth 2 (a vanishing depth difference, exactly)
    normal[..., :2] = 0
    distance = 2 * torch.ones_like(distance)
    cases["fronto-parallel plane"] = (normal, distance, alpha, Ks)
    return cases


HARD = _hard_cases()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", list(HARD))
def test_hard_inputs_match_torch(case, dtype):
    out, grad_normal, grad_distance = assert_matches_reference(*(t.to(dtype) for t in HARD[case]))
    if min(out.shape[1:3]) < 3:
        assert not out.any() and not grad_normal.any() and not grad_distance.any()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_non_finite_inputs_give_no_nan_where_torch_is_finite(dtype):
    normal, distance, alpha, Ks = (t.to(dtype) for t in planes(2, 14, 17, seed=9))
    normal[0, 3, 4, 1] = float("nan")
    normal[1, 7, 7] = float("inf")
    distance[0, 8, 10] = float("nan")
    distance[1, 2, 12] = float("inf")
    alpha[0, 10, 3] = float("nan")
    got = value_and_grads(depth_normal_from_plane, normal, distance, alpha, Ks)
    want = value_and_grads(reference, normal, distance, alpha, Ks)
    for name, a, b in zip(("depth_normal", "grad normal", "grad distance"), got, want):
        assert_close_to_max(a, b, dtype, name)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_non_contiguous_slices_of_a_packed_render(dtype):
    normal, distance, alpha, Ks = (t.to(dtype) for t in planes(3, 15, 19, seed=10))
    extra = torch.rand(3, 15, 19, 3, generator=torch.Generator().manual_seed(0), dtype=dtype)
    upstream = torch.randn(3, 15, 19, 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    results = []
    for fn in (depth_normal_from_plane, reference):
        packed = torch.cat([normal, extra, distance], -1).requires_grad_()  # [C,H,W,7], as a render's channels
        normal_view, _, distance_view = packed.split([3, 3, 1], -1)
        assert not normal_view.is_contiguous() and not distance_view.is_contiguous()
        out = fn(normal_view, distance_view, alpha[..., 0, None].expand_as(distance), Ks)
        (out * upstream).sum().backward()
        results.append((out, packed.grad))
    for name, a, b in zip(("depth_normal", "grad packed"), *results):
        assert_close_to_max(a, b, dtype, name)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bitwise_independent_of_thread_count(dtype):
    maps = [t.to(dtype) for t in planes(3, 61, 47, seed=11)]
    maps[2][0, 20:30, 10:20] = 0  # some undefined pixels
    threads = torch.get_num_threads()
    try:
        results = []
        for count in (1, 2):
            torch.set_num_threads(count)
            results.append(value_and_grads(depth_normal_from_plane, *maps))
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(*results))


def test_refuses_inputs_it_does_not_take():
    normal, distance, alpha, Ks = planes(2, 5, 6)
    with pytest.raises(ValueError, match="float32/float64 CPU"):
        depth_normal_from_plane(normal.float(), distance, alpha, Ks)
    with pytest.raises(ValueError, match="without a gradient"):
        depth_normal_from_plane(normal, distance, alpha, Ks.requires_grad_())


def render_scene(dtype):
    """60 Gaussians in front of two cameras of 37x29 pixels with different intrinsics."""
    generator = torch.Generator().manual_seed(12)
    means = (torch.rand(60, 3, generator=generator, dtype=dtype) * 2 - 1)
    means[:, 2] += 3.0
    scene = [means, torch.randn(60, 4, generator=generator, dtype=dtype),
             torch.exp(torch.randn(60, 3, generator=generator, dtype=dtype) * 0.5 - 2.0),
             torch.rand(60, generator=generator, dtype=dtype), torch.rand(60, 3, generator=generator, dtype=dtype)]
    viewmats = torch.eye(4, dtype=dtype).repeat(2, 1, 1)
    viewmats[1, 0, 3] = 0.2
    Ks = torch.tensor([[[33.0, 0, 19.3], [0, 33, 14.1], [0, 0, 1]], [[40.0, 0, 17], [0, 38, 15.2], [0, 0, 1]]],
                      dtype=dtype)
    return scene, viewmats, Ks


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rasterize_uses_the_kernel_with_the_fused_compositor(dtype, monkeypatch):
    calls = []
    monkeypatch.setattr(api, "depth_normal_from_plane", lambda *maps: calls.append(1) or depth_normal_from_plane(*maps))
    scene, viewmats, Ks = render_scene(dtype)
    upstream = torch.randn(2, 29, 37, 3, generator=torch.Generator().manual_seed(13), dtype=dtype)
    results = {}
    for compositor in ("fused", "torch"):
        leaves = [t.clone().requires_grad_() for t in scene[:3]]
        out = rasterize(*leaves, *scene[3:], viewmats, Ks, 37, 29, outputs=("depth_normal", "plane_depth"),
                        compositor=compositor, use_compile=False)
        (out.depth_normal * upstream).sum().backward()
        results[compositor] = [out.depth_normal] + [t.grad for t in leaves]
        assert len(calls) == 1  # the fused compositor's render ran the kernel, the torch one the torch chain
    assert results["torch"][0].abs().sum(-1).gt(0).sum() > 500  # the scene draws many depth normals
    for name, a, b in zip(("depth_normal", "means", "quats", "scales"), results["fused"], results["torch"]):
        # The two compositors' maps differ by rounding, and float32 depth normals amplify it.
        scale = b.abs().max()
        torch.testing.assert_close(a / scale, b / scale, rtol=0, atol=1e-4 if dtype == torch.float32 else 1e-12,
                                   msg=name)


def test_rasterize_keeps_the_torch_chain_when_K_needs_a_gradient(monkeypatch):
    monkeypatch.setattr(api, "depth_normal_from_plane", None)  # must not be called
    scene, viewmats, Ks = render_scene(torch.float64)
    out = rasterize(*scene, viewmats, Ks.requires_grad_(), 37, 29, outputs=("depth_normal",), compositor="fused",
                    use_compile=False)
    out.depth_normal.sum().backward()
    assert Ks.grad is not None
