"""The fused CPU projection kernel against the torch reference project_gaussians + gaussian_normals: gradcheck,
values and gradients, hard inputs, thread independence, the fallback, and its use by rasterize."""

from __future__ import annotations

import math

import pytest
import torch

from hico_plugin.rasterizer import rasterize
from hico_plugin.rasterizer import torch_backend
from hico_plugin.rasterizer.geometry import gaussian_normals
from hico_plugin.rasterizer.projection import FRUSTUM_MARGIN, project_gaussians
from hico_plugin.rasterizer.projection_fused import KERNEL, project_gaussians_fused
from helpers_native import require_kernel

# Relative to the magnitude of each Gaussian's values (see assert_close_per_gaussian): rounding of the reductions torch
# orders its own way, amplified by the cancellation in the 2-D covariance's determinant of thin Gaussians.
TOL = {torch.float32: 3e-5, torch.float64: 1e-12}
DIFFERENTIABLE = ("means_cam", "means2d", "conics", "depths", "normals", "distances")
WIDTH, HEIGHT = 40, 30


@pytest.fixture(autouse=True)
def _kernel():
    require_kernel(KERNEL)


def reference(means, quats, scales, opacities, viewmats, Ks, width, height, near=0.01, far=1e10, *, normals=False):
    projected = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, near, far)
    if normals:
        projected.normals, projected.distances = gaussian_normals(quats, scales, projected.means_cam, viewmats)
    return projected


def cameras(num_cams, dtype):
    """num_cams world->camera matrices turning about y and x and moving, with different intrinsics."""
    viewmats = torch.eye(4, dtype=torch.float64).repeat(num_cams, 1, 1)
    Ks = torch.zeros(num_cams, 3, 3, dtype=torch.float64)
    for c in range(num_cams):
        ay, ax = 0.25 * c, -0.15 * c
        rot_y = torch.tensor([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
        rot_x = torch.tensor([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
        viewmats[c, :3, :3] = (rot_x @ rot_y).double()
        viewmats[c, :3, 3] = torch.tensor([0.2 * c, -0.1 * c, 0.3 * c])
        Ks[c] = torch.tensor([[33.0 + 5 * c, 0, 19.3 + c], [0, 35.0 + 3 * c, 14.1 - c], [0, 0, 1]])
    return viewmats.to(dtype), Ks.to(dtype)


def random_gaussians(n, dtype, seed):
    """n Gaussians around the cameras: most in view, some beside the widened frustum, some behind."""
    generator = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=generator, dtype=torch.float64) * 2 - 1) * torch.tensor([3.0, 2.5, 3.0])
    means[:, 2] += 2.5
    quats = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    scales = torch.exp(torch.randn(n, 3, generator=generator, dtype=torch.float64) * 0.7 - 2.5)
    opacities = torch.rand(n, generator=generator, dtype=torch.float64)
    return [t.to(dtype) for t in (means, quats, scales, opacities)]


def values_and_grads(fn, means, quats, scales, opacities, viewmats, Ks, normals=True, outputs=DIFFERENTIABLE, **kw):
    """fn's projection and the gradients w.r.t. means, quats and scales under random cotangents of the
    differentiable ``outputs`` (normals and distances only with ``normals``)."""
    leaves = [t.detach().clone().requires_grad_() for t in (means, quats, scales)]
    projected = fn(*leaves, opacities, viewmats, Ks, WIDTH, HEIGHT, normals=normals, **kw)
    generator = torch.Generator().manual_seed(0)
    loss = 0
    for name in [name for name in outputs if normals or name not in ("normals", "distances")]:
        value = getattr(projected, name)
        loss = loss + (value * torch.randn(value.shape, generator=generator, dtype=value.dtype)).sum()
    loss.backward()
    return projected, [torch.zeros_like(leaf) if leaf.grad is None else leaf.grad for leaf in leaves]


def assert_close_per_gaussian(got, want, dtype, name, tol=None):
    """got == want within TOL[dtype] times the largest magnitude of want's entries of the same Gaussian (and
    camera) -- or 1e-3 of the largest overall, so that one huge gradient does not hide the others' errors --, or
    of all of want for a scalar per Gaussian (depths, distances, reach); exactly where want is all zero."""
    if want.numel():
        scalar = name in ("depths", "distances", "reach")
        rows = want.abs().max() if scalar else want.abs().amax(-1, keepdim=True)
        scale = rows.clamp_min(max(1e-3 * want.abs().max().item(), torch.finfo(dtype).tiny))
        torch.testing.assert_close(got / scale, want / scale, rtol=0, atol=TOL[dtype] if tol is None else tol,
                                   msg=name)


def assert_matches_reference(*inputs, normals=True, outputs=DIFFERENTIABLE, tol=None, **kw):
    dtype = inputs[0].dtype
    got, got_grads = values_and_grads(project_gaussians_fused, *inputs, normals=normals, outputs=outputs, **kw)
    want, want_grads = values_and_grads(reference, *inputs, normals=normals, outputs=outputs, **kw)
    for name in DIFFERENTIABLE[:4 + 2 * normals] + ("reach", "extents"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.shape == b.shape and a.dtype == b.dtype, name
        assert_close_per_gaussian(a, b, dtype, name, tol)
    if not normals:
        assert got.normals is None and got.distances is None
    assert got.radii.dtype == torch.int32 and not got.extents.requires_grad
    # A radius is a ceil: float32 rounding may move the rare extent sitting at an integer by one pixel.
    differ = got.radii != want.radii
    assert not differ.any() if dtype == torch.float64 else (got.radii - want.radii).abs().max() <= 1
    assert differ.float().mean() < 1e-3
    for name, a, b in zip(("means", "quats", "scales"), got_grads, want_grads):
        assert torch.isfinite(a).all(), f"grad {name}: not finite"
        assert_close_per_gaussian(a, b, dtype, f"grad {name}", tol)
    return got, got_grads


def small_case():
    """Seven float64 Gaussians seen by two cameras (near plane 0.2) away from every kink: inside the frustum,
    beyond the widened frustum in x and in y (clamped Jacobian), between the camera and the near plane, behind
    the camera, and straddling the near plane (centre just past it, a metre wide)."""
    means = torch.tensor([[0.1, -0.2, 2.0], [-0.3, 0.1, 3.0], [5.0, 0.2, 1.5], [0.1, -4.0, 2.0], [0.05, 0.0, 0.1],
                          [0.2, 0.1, -1.0], [0.0, 0.05, 0.3]], dtype=torch.float64)
    generator = torch.Generator().manual_seed(3)
    quats = torch.randn(7, 4, generator=generator, dtype=torch.float64)
    scales = torch.tensor([[0.1, 0.2, 0.05], [0.3, 0.1, 0.2], [0.2, 0.15, 0.1], [0.12, 0.05, 0.3],
                           [0.2, 0.3, 0.1], [0.1, 0.2, 0.3], [0.5, 0.4, 0.3]], dtype=torch.float64)
    return means, quats, scales, torch.full((7,), 0.7, dtype=torch.float64), *cameras(2, torch.float64)


@pytest.mark.parametrize("normals", [False, True])
def test_gradcheck_float64(normals):
    means, quats, scales, opacities, viewmats, Ks = small_case()
    want = reference(means, quats, scales, opacities, viewmats, Ks, WIDTH, HEIGHT, near=0.2, normals=True)
    ratios = want.means_cam[..., :2] / want.means_cam[..., 2:]
    assert (ratios.abs() > 1.5).any() and (want.depths < 0.2).sum() >= 2  # clamped and culled Gaussians
    assert (want.distances > 1e-3).all()  # no Gaussian's plane near the camera centre (|.| and the flip)

    def f(means, quats, scales):
        projected = project_gaussians_fused(means, quats, scales, opacities, viewmats, Ks, WIDTH, HEIGHT, near=0.2,
                                            normals=normals)
        return tuple(getattr(projected, name) for name in ("means_cam", "means2d", "conics", "normals",
                                                           "distances")[:3 + 2 * normals])

    inputs = [t.clone().requires_grad_() for t in (means, quats, scales)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("normals", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_values_and_gradients_match_torch(dtype, normals):
    inputs = (*random_gaussians(3000, dtype, seed=1), *cameras(3, dtype))
    got, _ = assert_matches_reference(*inputs, normals=normals)
    drawn = got.radii > 0
    assert drawn.sum() > 3000 and (~drawn).sum() > 1000  # many drawn and many culled
    assert (got.depths < 0.01).sum() > 300  # behind the near plane in some camera


@pytest.mark.parametrize("outputs", [("means2d",), ("conics",), ("distances",), ("normals", "depths")])
def test_gradients_of_some_outputs_match_torch(outputs):
    """The outputs a loss does not use have no cotangent (None), whose terms the kernel skips."""
    assert_matches_reference(*random_gaussians(500, torch.float64, seed=2), *cameras(2, torch.float64),
                             outputs=outputs)


def hard_case(dtype):
    """Gaussians one camera (identity viewmat) sees at the edges of the maths, with the near plane 0.01."""
    Ks = torch.tensor([[[33.0, 0, 19.3], [0, 35.0, 14.1], [0, 0, 1]]], dtype=dtype)
    fx, cx = Ks[:, 0, 0, None], Ks[:, 0, 2, None]
    lim_x_pos = ((WIDTH - cx) / fx + FRUSTUM_MARGIN * (0.5 * WIDTH / fx)).item()  # the reference's expression
    rows = [  # mean, quaternion, scales, opacity
        ((0.1, 0.2, 3.0), (0.0, 0.0, 0.0, 0.0), (0.1, 0.2, 0.05), 0.8),  # zero quaternion: identity, no gradient
        ((0.2, 0.1, 2.0), (0.3, 0.1, -0.5, 0.2), (0.0, 0.0, 0.0), 0.9),  # zero scales
        ((-0.2, 0.1, 2.0), (0.3, 0.1, -0.5, 0.2), (1e-8, 1e-8, 1e-8), 0.9),
        ((0.0, 0.3, 2.5), (0.9, 0.1, 0.2, 0.3), (0.2, 0.1, 0.0), 0.7),  # flat: one zero scale
        ((0.1, 0.1, -2.0), (0.5, 0.5, 0.1, 0.2), (0.1, 0.1, 0.2), 0.9),  # behind the camera
        ((0.0, 0.0, 0.01), (0.5, 0.5, 0.1, 0.2), (0.1, 0.1, 0.2), 0.9),  # at the near plane: culled
        ((0.0, 0.0, 0.0), (0.5, 0.5, 0.1, 0.2), (0.1, 0.1, 0.2), 0.9),  # at the camera centre
        ((0.001, 0.0, 0.02), (0.5, 0.5, 0.1, 0.2), (0.1, 0.1, 0.2), 0.9),  # just past the near plane
        ((0.0, 0.02, 0.3), (0.2, 0.7, 0.1, 0.2), (0.5, 0.6, 0.4), 0.9),  # straddling the near plane
        ((100.0, 0.0, 1.0), (0.2, 0.7, 0.1, 0.2), (0.1, 0.2, 0.3), 0.9),  # far outside the frustum
        ((0.3, -0.2, 2.0), (0.2, 0.7, 0.1, 0.2), (0.1, 0.2, 0.3), 0.0),  # opacity 0: radius 0
        ((0.3, 0.2, 2.0), (0.2, 0.7, 0.1, 0.2), (0.1, 0.2, 0.3), 1 / 255),  # opacity at the cut
        ((lim_x_pos, 0.1, 1.0), (0.2, 0.7, 0.1, 0.2), (0.1, 0.2, 0.3), 0.9),  # x / z at the clamp: half the gradient
        ((0.2, 0.1, 2.0), (0.2, 0.7, 0.1, 0.2), (0.1, 0.1, 0.3), 0.9),  # tied shortest axes: the first
        ((0.0, 0.0, 2.0), (1.0, 0.0, 0.0, 0.0), (0.01, 0.2, 0.2), 0.9),  # plane through the camera: distance 0
        ((0.1, 0.1, 2e10), (0.2, 0.7, 0.1, 0.2), (0.1, 0.2, 0.3), 0.9),  # beyond the far plane
        ((0.1, 0.1, 2.0), (1e-13, 0.0, 1e-13, 0.0), (0.1, 0.2, 0.3), 0.9),  # norm under 1e-12: identity
        ((0.1, -0.1, 2.0), (1e-11, 0.0, 1e-11, 0.0), (0.1, 0.2, 0.3), 0.9),  # norm over 1e-12: normalised
    ]
    means, quats, scales, opacities = (torch.tensor([row[i] for row in rows], dtype=dtype) for i in range(4))
    return means, quats, scales, opacities, torch.eye(4, dtype=dtype)[None], Ks


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hard_inputs_match_torch(dtype):
    got, (_, grad_quats, _) = assert_matches_reference(*hard_case(dtype))
    assert got.radii[0, [4, 5, 6, 9, 10, 11, 15]].eq(0).all()  # behind, at near, outside, faint, far
    assert got.radii[0, [0, 1, 2, 3, 7, 8, 12, 13, 14, 16, 17]].gt(0).all()
    assert grad_quats[0].eq(0).all() and grad_quats[16].eq(0).all()  # read as the identity: no gradient
    assert grad_quats[17].abs().max() > 1e3  # a tiny quaternion that is normalised has a large gradient
    assert got.distances[0, 14] == 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_city_scale_coordinates(dtype):
    """Gaussians 1e5 units from the origin, a camera near them: the camera coordinates are computed in float64."""
    offset = torch.tensor([1e5, -1e5, 50.0], dtype=torch.float64)
    means, quats, scales, opacities = random_gaussians(500, torch.float64, seed=4)
    viewmats, Ks = cameras(2, torch.float64)
    viewmats[:, :3, 3] -= (viewmats[:, :3, :3] @ offset)
    inputs = [t.to(dtype) for t in (means + offset, quats, scales, opacities, viewmats, Ks)]
    # In float64 the world coordinates (|offset| = 1.4e5) carry |offset| x eps = 3e-11 of rounding into
    # camera coordinates of about 1, and the torch reference's matrix product (a BLAS that fuses
    # multiply-adds, as on AVX-512 CPUs) rounds them differently from the kernel's loop (1.5e-11 apart
    # on such a CPU): a few of those roundings, not TOL's 1e-12, bound the difference.
    rounding = 4 * float(offset.norm()) * torch.finfo(torch.float64).eps
    got, _ = assert_matches_reference(*inputs, tol=None if dtype == torch.float32 else rounding)
    assert got.radii.gt(0).sum() > 300
    local = project_gaussians_fused(*(t.to(dtype) for t in (means, quats, scales, opacities, *cameras(2, dtype))),
                                    WIDTH, HEIGHT)
    # float32 stores 1e5 (and the translation) to ~4 mm: that much, not more, moves the camera coordinates
    tolerance = 0.01 if dtype == torch.float32 else 1e-9
    assert (got.means_cam - local.means_cam).abs().max() < tolerance


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bitwise_independent_of_thread_count(dtype):
    inputs = (*random_gaussians(4001, dtype, seed=5), *cameras(3, dtype))
    threads = torch.get_num_threads()
    try:
        results = []
        for count in (1, 2):
            torch.set_num_threads(count)
            projected, grads = values_and_grads(project_gaussians_fused, *inputs)
            results.append([getattr(projected, name) for name in DIFFERENTIABLE + ("extents", "radii")] + grads)
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(*results))


def test_refuses_inputs_it_does_not_take():
    means, quats, scales, opacities, viewmats, Ks = small_case()
    with pytest.raises(ValueError, match="float32/float64 CPU"):
        project_gaussians_fused(means.float(), quats, scales, opacities, viewmats, Ks, WIDTH, HEIGHT)
    with pytest.raises(ValueError, match="without a gradient"):
        project_gaussians_fused(means, quats, scales, opacities, viewmats.requires_grad_(), Ks, WIDTH, HEIGHT)


def render(dtype, scene, outputs, **kw):
    """rasterize with the fused compositor; the rendered images and the gradients of means, quats, scales
    under random cotangents."""
    means, quats, scales, opacities, colors, viewmats, Ks = scene
    leaves = [t.clone().requires_grad_() for t in (means, quats, scales)]
    out = rasterize(*leaves, opacities, colors, viewmats, Ks, WIDTH, HEIGHT, outputs=outputs, compositor="fused",
                    use_compile=False, **kw)
    generator = torch.Generator().manual_seed(7)
    images = out.images()
    sum((image * torch.randn(image.shape, generator=generator, dtype=dtype)).sum() for image in images.values()
        ).backward()
    return images, [leaf.grad for leaf in leaves]


def render_scene(dtype):
    means, quats, scales, opacities = random_gaussians(300, dtype, seed=6)
    colors = torch.rand(300, 3, generator=torch.Generator().manual_seed(8), dtype=dtype)
    return means, quats, scales * 2, opacities, colors, *cameras(2, dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rasterize_with_the_fused_projection_matches_the_torch_projection(dtype, monkeypatch):
    outputs = ("rgb", "depth", "normal", "plane_depth", "depth_normal")
    calls = []
    monkeypatch.setattr(torch_backend, "project_gaussians_fused", lambda *a, **kw: calls.append(kw) or
                        project_gaussians_fused(*a, **kw))
    scene = render_scene(dtype)
    got = render(dtype, scene, outputs)
    assert calls == [{"normals": True}]
    monkeypatch.setattr(torch_backend, "projection_fused_available", lambda: False)
    want = render(dtype, scene, outputs)
    assert len(calls) == 1
    assert want[0]["depth"].gt(0).float().mean() > 0.5  # the scene covers most of the images
    # The maps inherit the projection's rounding, and float32 depth normals amplify it.
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    for name in outputs:
        scale = want[0][name].abs().max()
        torch.testing.assert_close(got[0][name] / scale, want[0][name] / scale, rtol=0, atol=tol, msg=name)
    for name, a, b in zip(("means", "quats", "scales"), got[1], want[1]):
        scale = b.abs().max()
        torch.testing.assert_close(a / scale, b / scale, rtol=0, atol=tol, msg=f"grad {name}")


def test_the_torch_projection_when_the_kernel_cannot_be_built_or_the_camera_needs_a_gradient(monkeypatch):
    calls = []
    real = torch_backend.project_gaussians
    monkeypatch.setattr(torch_backend, "project_gaussians", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(KERNEL, "module", None)  # as when the build failed
    monkeypatch.setattr(KERNEL, "error", "RuntimeError: no compiler")
    scene = render_scene(torch.float64)
    images, grads = render(torch.float64, scene, ("rgb", "normal"))
    assert len(calls) == 1 and images["rgb"].abs().sum() > 0 and all(torch.isfinite(g).all() for g in grads)
    monkeypatch.undo()
    monkeypatch.setattr(torch_backend, "project_gaussians", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(torch_backend, "project_gaussians_fused", None)  # must not be called
    *gaussians, viewmats, Ks = scene
    images, _ = render(torch.float64, (*gaussians, viewmats.clone().requires_grad_(), Ks), ("rgb",))
    assert len(calls) == 2
