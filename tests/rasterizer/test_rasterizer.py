"""The torch rasterizer against a dense brute-force reference, plus float64 gradchecks."""

import math

import pytest
import torch

from hico_plugin.rasterizer import rasterize

ALL = ("rgb", "alpha", "depth", "normal", "distance", "plane_depth", "depth_normal")


def rotmat(q):
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def reference(means, quats, scales, opacities, colors, viewmat, K, width, height, near=0.01,
              background=None):
    """Every pixel x every Gaussian, depth-sorted, written as directly as possible."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    rot = rotmat(quats)
    cov3 = rot @ torch.diag_embed(scales**2) @ rot.transpose(-1, -2)
    mc = means @ R.T + t
    x, y, z = mc.unbind(-1)
    covc = R @ cov3 @ R.T
    tx = z * torch.clamp(x / z, -(cx / fx + 0.3 * 0.5 * width / fx), (width - cx) / fx + 0.3 * 0.5 * width / fx)
    ty = z * torch.clamp(y / z, -(cy / fy + 0.3 * 0.5 * height / fy), (height - cy) / fy + 0.3 * 0.5 * height / fy)
    J = torch.zeros(len(means), 2, 3, dtype=means.dtype)
    J[:, 0, 0] = fx / z
    J[:, 0, 2] = -fx * tx / z**2
    J[:, 1, 1] = fy / z
    J[:, 1, 2] = -fy * ty / z**2
    cov2 = J @ covc @ J.transpose(-1, -2) + 0.3 * torch.eye(2, dtype=means.dtype)
    inv = torch.linalg.inv(cov2)
    mu = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)

    vs, us = torch.meshgrid(torch.arange(height, dtype=means.dtype) + 0.5,
                            torch.arange(width, dtype=means.dtype) + 0.5, indexing="ij")
    pix = torch.stack([us, vs], -1).reshape(-1, 1, 2)  # [P,1,2]
    d = pix - mu[None]  # [P,N,2]
    sigma = 0.5 * torch.einsum("pni,nij,pnj->pn", d, inv, d)
    alpha = torch.clamp(opacities[None] * torch.exp(-sigma), max=0.99)
    alpha = torch.where((alpha >= 1 / 255) & (z > near)[None], alpha, torch.zeros_like(alpha))
    order = torch.argsort(z)
    alpha = alpha[:, order]
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha], 1), 1)
    drawn = trans[:, 1:] > 1e-4
    w = torch.where(drawn, alpha * trans[:, :-1], torch.zeros_like(alpha))  # [P,N]

    # Geometry per Gaussian, by its definition.
    axis = rot[torch.arange(len(means)), :, scales.argmin(-1)]  # shortest axis (a column)
    n = axis @ R.T
    n = torch.where(((n * mc).sum(-1) > 0)[:, None], -n, n)
    dist = (n * mc).sum(-1).abs()
    comp = lambda f: (w @ f[order]).reshape(height, width, -1)  # noqa: E731
    A = comp(torch.ones_like(z)[:, None])
    rgb = comp(colors) + (1 - A) * (background if background is not None else 0)
    N_ = comp(n)
    D = comp(dist[:, None])
    Z = comp(z[:, None])
    has = A > 1e-6
    depth = torch.where(has, Z / torch.where(has, A, torch.ones_like(A)), torch.zeros_like(A))
    ray = torch.stack([(us - cx) / fx, (vs - cy) / fy, torch.ones_like(us)], -1)
    den = -(N_ * ray).sum(-1, keepdim=True)
    ok = has & (den > 1e-6 * A)
    pd = torch.where(ok, D / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(D))
    # depth normal: explicit per-pixel cross products of back-projected neighbours
    P = pd * ray
    dn = torch.zeros(height, width, 3, dtype=means.dtype)
    for v in range(1, height - 1):
        for u in range(1, width - 1):
            if min(pd[v, u + 1, 0], pd[v, u - 1, 0], pd[v - 1, u, 0], pd[v + 1, u, 0]) <= 0:
                continue
            c = torch.linalg.cross(P[v, u + 1] - P[v, u - 1], P[v - 1, u] - P[v + 1, u])
            c = c / c.norm()
            dn[v, u] = -c if (c * P[v, u]).sum() > 0 else c
    return dict(rgb=rgb, alpha=A, depth=depth, normal=N_, distance=D, plane_depth=pd,
                depth_normal=dn)


def random_scene(n, seed, dtype=torch.float64, spread=1.0):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) * spread
    means[:, 2] += 3.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=dtype) * 0.5 - 2.5)
    opacities = torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, scales, opacities, colors


def camera(width, height, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    angle = torch.randn(3, generator=g, dtype=dtype) * 0.1
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[:3, :3] = torch.linalg.matrix_exp(torch.tensor(
        [[0, -angle[2], angle[1]], [angle[2], 0, -angle[0]], [-angle[1], angle[0], 0]], dtype=dtype))
    viewmat[:3, 3] = torch.randn(3, generator=g, dtype=dtype) * 0.1
    K = torch.tensor([[0.9 * width, 0, 0.5 * width + 1.3], [0, 0.9 * width, 0.5 * height - 0.7],
                      [0, 0, 1]], dtype=dtype)
    return viewmat, K


# Both blending kernels of the torch backend are held to the same reference.
compositors = pytest.mark.parametrize("compositor", ["torch", "fused"])


@compositors
@pytest.mark.parametrize("seed,width,height,tile", [(0, 37, 29, 16), (1, 24, 20, 8), (2, 16, 16, 4)])
def test_all_outputs_match_dense_reference(seed, width, height, tile, compositor):
    scene = random_scene(60, seed)
    viewmat, K = camera(width, height, seed=seed)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    out = rasterize(*scene, viewmat, K, width, height, outputs=ALL, tile_size=tile, background=bg,
                    use_compile=False, compositor=compositor)
    ref = reference(*scene, viewmat, K, width, height, background=bg)
    for name in ALL:
        got = getattr(out, name)
        assert got.shape == ref[name].shape, name
        torch.testing.assert_close(got, ref[name], atol=1e-9, rtol=1e-7, msg=name)
    assert out.alpha.max() > 0.5  # the scene actually covers the image


@compositors
def test_float32_matches_reference_and_depth_option(compositor):
    scene = random_scene(200, 7)
    viewmat, K = camera(40, 33, seed=3)
    scene32 = [t.float() for t in scene]
    out = rasterize(*scene32, viewmat.float(), K.float(), 40, 33, outputs=ALL, use_compile=False,
                    compositor=compositor)
    ref = reference(*scene, viewmat, K, 40, 33)
    for name in ("rgb", "alpha", "depth", "normal", "distance"):
        torch.testing.assert_close(getattr(out, name).double(), ref[name], atol=2e-5, rtol=1e-4)
    # depth_normal from expected depth: a fronto-parallel plane of Gaussians gives n_d = (0,0,-1)
    g = torch.Generator().manual_seed(0)
    xy = torch.rand(3000, 2, generator=g) * 4 - 2
    means = torch.cat([xy, torch.full((3000, 1), 2.0)], 1)
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(3000, 1)
    scales = torch.tensor([[0.05, 0.05, 0.0]]).repeat(3000, 1)
    ones = torch.ones(3000)
    out = rasterize(means, quats, scales, ones, ones[:, None], torch.eye(4),
                    torch.tensor([[20.0, 0, 16], [0, 20, 16], [0, 0, 1]]), 32, 32,
                    outputs=("depth", "plane_depth", "depth_normal", "normal"),
                    depth_normal_from="depth", use_compile=False, compositor=compositor)
    inner = out.depth_normal[1:-1, 1:-1]
    torch.testing.assert_close(inner, torch.tensor([0.0, 0, -1]).expand_as(inner), atol=1e-4, rtol=0)
    torch.testing.assert_close(out.plane_depth[1:-1, 1:-1], torch.full((30, 30, 1), 2.0), atol=1e-4,
                               rtol=0)
    assert (out.depth_normal[0] == 0).all() and (out.depth_normal[:, -1] == 0).all()


def assert_gradients_match_reference(scene, viewmat, K, width, height, seed, compositor):
    """Gradients of every input under random cotangents on every output equal the reference's."""
    out = rasterize(*scene, viewmat, K, width, height, outputs=ALL, tile_size=8, use_compile=False,
                    compositor=compositor)
    ref = reference(*scene, viewmat, K, width, height)
    g = torch.Generator().manual_seed(seed)
    cots = {n: torch.randn(ref[n].shape, generator=g, dtype=torch.float64) for n in ALL}
    got = torch.autograd.grad(sum((getattr(out, n) * cots[n]).sum() for n in ALL), scene)
    want = torch.autograd.grad(sum((ref[n] * cots[n]).sum() for n in ALL), scene)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, atol=1e-8, rtol=1e-6)
    return ref


@compositors
def test_random_cotangents_match_reference_gradients(compositor):
    scene = [t.requires_grad_() for t in random_scene(40, 11)]
    viewmat, K = camera(23, 19, seed=5)
    assert_gradients_match_reference(scene, viewmat, K, 23, 19, seed=1, compositor=compositor)


@compositors
def test_gradients_behind_opaque_layers_match_reference(compositor):
    """Deep, nearly opaque stacks: most tile rows lie behind the transmittance cut, where the backward
    pass skips them; every gradient must still equal the dense reference's."""
    means, quats, scales, opacities, colors = random_scene(150, 4, spread=0.4)
    scene = [t.requires_grad_() for t in (means, quats, scales * 10.0, 0.9 + 0.1 * opacities, colors)]
    viewmat, K = camera(21, 17, seed=2)
    ref = assert_gradients_match_reference(scene, viewmat, K, 21, 17, seed=3, compositor=compositor)
    # ~150 Gaussians of alpha >= 0.9 over every pixel: the cut comes after a few of them.
    assert ref["alpha"].min() > 0.998


def tiny_scene(seed):
    """Four Gaussians in a 10x9 image with 4-px tiles: overlapping, multi-tile, away from kinks."""
    g = torch.Generator().manual_seed(seed)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.2, 0.1, 2.5], [-0.3, 0.2, 3.0], [0.1, -0.3, 2.2]],
                         dtype=torch.float64) + 0.01 * torch.randn(4, 3, generator=g, dtype=torch.float64)
    quats = torch.randn(4, 4, generator=g, dtype=torch.float64)
    scales = torch.tensor([[0.3, 0.2, 0.05], [0.25, 0.1, 0.3], [0.2, 0.4, 0.1], [0.1, 0.15, 0.3]],
                          dtype=torch.float64)
    opacities = torch.tensor([0.7, 0.5, 0.9, 0.6], dtype=torch.float64)
    colors = torch.rand(4, 3, generator=g, dtype=torch.float64)
    K = torch.tensor([[8.0, 0, 5.1], [0, 8.0, 4.4], [0, 0, 1]], dtype=torch.float64)
    return (means, quats, scales, opacities, colors), torch.eye(4, dtype=torch.float64), K


@compositors
def test_gradcheck_every_input_and_output(compositor):
    """One float64 gradcheck over all inputs (viewmat too) and random projections of every output."""
    (means, quats, scales, opacities, colors), viewmat, K = tiny_scene(0)
    viewmat[:3, 3] = torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    sizes = {"rgb": 3, "normal": 3, "depth_normal": 3}
    weights = {n: torch.randn(9 * 10 * sizes.get(n, 1), 2, generator=g, dtype=torch.float64)
               for n in ALL}

    def f(means, quats, scales, opacities, colors, viewmat):
        out = rasterize(means, quats, scales, opacities, colors, viewmat, K, 10, 9, outputs=ALL,
                        tile_size=4, backend="torch", use_compile=False, compositor=compositor)
        # Two random projections per output: every output checked at 14 backward passes.
        return torch.cat([getattr(out, n).reshape(-1) @ weights[n] for n in ALL])

    inputs = [t.clone().requires_grad_() for t in (means, quats, scales, opacities, colors, viewmat)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_means2d_gradient_is_retained():
    scene = [t.float().requires_grad_() for t in random_scene(30, 2)]
    viewmat, K = camera(20, 20, dtype=torch.float32)
    out = rasterize(*scene, viewmat, K, 20, 20, use_compile=False)
    out.means2d.retain_grad()
    out.rgb.sum().backward()
    assert out.means2d.grad is not None and out.means2d.grad.shape == (30, 2)
    drawn = out.radii > 0
    assert out.means2d.grad[drawn].abs().sum(-1).gt(0).any()
    assert (out.means2d.grad[~drawn] == 0).all()
    assert math.isfinite(out.means2d.grad.sum().item())
