"""The fused CPU compositor against the vectorised torch one, and what happens when it cannot be built."""

import pytest
import torch

from hico_plugin.errors import HicoError
from hico_plugin.rasterizer import RendererConfig, rasterize
from hico_plugin.rasterizer import fused as fused_module
from hico_plugin.rasterizer.composite import composite
from hico_plugin.rasterizer.fused import bin_gaussians_fused, composite_fused, fused_available
from hico_plugin.rasterizer.projection import project_gaussians
from hico_plugin.rasterizer.gsplat_backend import GsplatBackend
from hico_plugin.rasterizer.torch_backend import TorchBackend, _untile
from hico_plugin.rasterizer.tiling import TileBins, bin_gaussians

K = torch.tensor([[60.0, 0, 33], [0, 60, 25], [0, 0, 1]])


def projected_scene(n, seed, num_cams=2, dtype=torch.float32, spread=1.0, log_scale=-3.0):
    """n random Gaussians projected into num_cams cameras of 64x48 pixels; returns the projection
    and the opacities."""
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(n, 2, generator=g) * 2 - 1) * spread,
                       torch.rand(n, 1, generator=g) * 2 + 2], 1)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.5 + log_scale)
    opacities = torch.rand(n, generator=g)
    viewmats = torch.eye(4).repeat(num_cams, 1, 1)
    viewmats[:, 0, 3] = torch.linspace(-0.2, 0.2, num_cams)
    proj = project_gaussians(*(t.to(dtype) for t in (means, quats, scales, opacities, viewmats)),
                             K[None].repeat(num_cams, 1, 1).to(dtype), 64, 48)
    return proj, opacities.to(dtype)


def binned_scene(n, seed, tile_size, num_cams=2, dtype=torch.float32):
    """Flattened compositor inputs of n Gaussians in front of num_cams cameras, 64x48 pixels."""
    g = torch.Generator().manual_seed(seed + 1000)
    proj, opacities = projected_scene(n, seed, num_cams, dtype)
    bins = bin_gaussians(proj.means2d, proj.conics, proj.reach, proj.extents, proj.depths, proj.radii,
                         64, 48, tile_size)
    features = torch.rand(num_cams * n, 5, generator=g, dtype=dtype)
    return [proj.means2d.reshape(-1, 2), proj.conics.reshape(-1, 3),
            opacities.repeat(num_cams), features], bins


def outputs_and_grads(fn, inputs, bins, seed=0):
    leaves = [t.detach().clone().requires_grad_() for t in inputs]
    out, acc = fn(*leaves, bins)
    g = torch.Generator().manual_seed(seed)  # drawn in float64: the same cotangents for either dtype
    cot_out = torch.randn(out.shape, generator=g, dtype=torch.float64).to(out.dtype)
    cot_acc = torch.randn(acc.shape, generator=g, dtype=torch.float64).to(acc.dtype)
    ((out * cot_out).sum() + (acc * cot_acc).sum()).backward()
    return out, acc, [t.grad for t in leaves]


@pytest.mark.parametrize("tile_size", [4, 16])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_fused_matches_torch_compositor_with_random_cotangents(tile_size, dtype, tol):
    inputs, bins = binned_scene(600, seed=tile_size, tile_size=tile_size, dtype=dtype)
    assert fused_available(), fused_module.EXTENSION.error
    want = outputs_and_grads(composite, inputs, bins)
    got = outputs_and_grads(composite_fused, inputs, bins)
    assert want[1].max() > 0.99  # deep enough that pixels stop early
    torch.testing.assert_close(got[0], want[0], atol=tol, rtol=tol)
    torch.testing.assert_close(got[1], want[1], atol=tol, rtol=tol)
    for name, a, b in zip(("means2d", "conics", "opacities", "features"), got[2], want[2]):
        scale = b.abs().max()
        torch.testing.assert_close(a / scale, b / scale, atol=tol, rtol=0, msg=name)


@pytest.mark.parametrize("tile_size", [4, 8, 16])
@pytest.mark.parametrize("channels", [3, 4, 7, 8])
def test_fused_float32_vector_loops_match_torch_compositor(tile_size, channels):
    # float32 runs the kernel's vector loops (several pixels per instruction, a polynomial exp), one
    # build per channel count it specialises (5 channels, above, takes the general one). A tile of 4
    # pixels is narrower than a vector, so the lanes past the box run into the next pixel row.
    inputs, bins = binned_scene(500, seed=channels, tile_size=tile_size)
    inputs[3] = torch.rand(inputs[3].shape[0], channels, generator=torch.Generator().manual_seed(9))
    assert fused_available(), fused_module.EXTENSION.error
    want = outputs_and_grads(composite, inputs, bins)
    got = outputs_and_grads(composite_fused, inputs, bins)
    assert want[1].max() > 0.99  # deep enough that pixels stop early
    torch.testing.assert_close(got[0], want[0], atol=2e-4, rtol=2e-4)
    torch.testing.assert_close(got[1], want[1], atol=2e-4, rtol=2e-4)
    for name, a, b in zip(("means2d", "conics", "opacities", "features"), got[2], want[2]):
        scale = b.abs().max()
        torch.testing.assert_close(a / scale, b / scale, atol=2e-4, rtol=0, msg=name)


def test_fused_float32_keeps_an_inf_feature_and_a_nan_gradient_where_they_belong():
    # The vector loops multiply by a zero weight on lanes a row does not draw, unless the row's features
    # (forward) or the tile's colour gradients (backward) are not all finite. The float64 scalar loops
    # skip such pairs outright: their non-finite outputs and gradients are exactly where they belong.
    inputs, bins = binned_scene(300, seed=5, tile_size=16)
    inputs[3][7, 1] = float("inf")
    got = {}
    for dtype in (torch.float32, torch.float64):
        leaves = [t.detach().to(dtype).clone().requires_grad_() for t in inputs]
        out, acc = composite_fused(*leaves, bins)
        cotangent = torch.ones_like(out)
        cotangent[1, 100, 2] = float("nan")
        ((out * cotangent).sum() + acc.sum()).backward()
        got[dtype] = [out.isfinite(), *(leaf.grad.isfinite() for leaf in leaves)]
    assert not got[torch.float64][0].all() and got[torch.float64][0].float().mean() > 0.5
    assert not got[torch.float64][4].all()
    for a, b in zip(got[torch.float32], got[torch.float64]):
        assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_image_layout_is_the_tiles_cropped(dtype):
    # 7 x 5 tiles of 10 pixels cover 70x50: the 64x48 images crop a column and a row of tiles.
    inputs, bins = binned_scene(300, seed=4, tile_size=10, dtype=dtype)
    assert fused_available(), fused_module.EXTENSION.error
    by_tile = [t.detach().clone().requires_grad_() for t in inputs]
    by_image = [t.detach().clone().requires_grad_() for t in inputs]
    features, tile_alpha = composite_fused(*by_tile, bins)
    tiled = _untile(torch.cat([features, tile_alpha[..., None]], -1), 2, bins, 64, 48)
    image, alpha = composite_fused(*by_image, bins, image_size=(64, 48))
    assert image.shape == (2, 48, 64, 5) and alpha.shape == (2, 48, 64)
    assert torch.equal(image, tiled[..., :-1]) and torch.equal(alpha, tiled[..., -1])
    cotangent = torch.randn(tiled.shape, generator=torch.Generator().manual_seed(1), dtype=dtype)
    (tiled * cotangent).sum().backward()
    ((image * cotangent[..., :-1]).sum() + (alpha * cotangent[..., -1]).sum()).backward()
    for a, b in zip(by_image, by_tile):
        assert torch.equal(a.grad, b.grad)


def test_fused_gradcheck_float64():
    inputs, bins = binned_scene(12, seed=5, tile_size=16, num_cams=1, dtype=torch.float64)
    # Opacities away from the 0.99 clamp and the 1/255 cut keep the function smooth at eps.
    inputs[2] = 0.2 + 0.6 * inputs[2]
    leaves = [t.detach().clone().requires_grad_() for t in inputs]
    assert torch.autograd.gradcheck(lambda *x: composite_fused(*x, bins), leaves, eps=1e-6,
                                    atol=1e-6, rtol=1e-4)


def test_fused_result_is_bitwise_independent_of_threads():
    inputs, bins = binned_scene(400, seed=2, tile_size=8)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = outputs_and_grads(composite_fused, inputs, bins)
        results = []
        for count in (max(2, threads), 3):  # 3: the Gaussians split into uneven id ranges for the sums
            torch.set_num_threads(count)
            results.append(outputs_and_grads(composite_fused, inputs, bins))
    finally:
        torch.set_num_threads(threads)
    # bitwise: a pixel is one thread's, and gradients are summed in intersection order
    for many in results:
        assert torch.equal(many[0], one[0]) and torch.equal(many[1], one[1])
        for a, b in zip(many[2], one[2]):
            assert torch.equal(a, b)


def test_unbuildable_fused_compositor(monkeypatch):
    """auto falls back to the torch compositor (and its tile size); an explicit 'fused' is one error."""
    monkeypatch.setattr(fused_module.EXTENSION, "module", None)
    monkeypatch.setattr(fused_module.EXTENSION, "error", "no C++ compiler")
    assert TorchBackend(compositor="auto").default_tile_size(torch.device("cpu")) == 4
    means = torch.tensor([[0.0, 0.0, 2.0]])
    args = (means, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1), torch.ones(1),
            torch.ones(1, 3), torch.eye(4), K, 64, 48)
    auto = rasterize(*args, use_compile=False)
    assert auto.rgb.max() > 0.9
    with pytest.raises(HicoError, match="compositor='fused' could not be built \\(no C\\+\\+ compiler\\)"):
        rasterize(*args, compositor="fused")


def test_default_tile_sizes():
    assert fused_available()
    cpu = torch.device("cpu")
    assert TorchBackend(compositor="auto").default_tile_size(cpu) == 16
    assert TorchBackend(compositor="torch").default_tile_size(cpu) == 4
    assert GsplatBackend().default_tile_size(cpu) == 16
    assert RendererConfig().compositor == "auto"


@pytest.mark.parametrize("tile_size", [1, 4, 16, 64])
@pytest.mark.parametrize("spread,log_scale", [(1.0, -3.0), (0.3, -1.0), (1e4, -3.0), (1.0, -12.0)])
def test_fused_binning_equals_torch_binning(tile_size, spread, log_scale):
    """Same intersections in the same (tile, depth) order: dense, huge, far off-image, sub-pixel."""
    assert fused_available()
    proj, _ = projected_scene(500, seed=tile_size, num_cams=3, spread=spread, log_scale=log_scale)
    args = (proj.means2d, proj.conics, proj.reach, proj.extents, proj.depths, proj.radii, 64, 48,
            tile_size)
    want, got = bin_gaussians(*args), bin_gaussians_fused(*args)
    for name in ("gaussian_ids", "tile_ids", "tile_offsets"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name
    assert (got.tiles_x, got.tiles_y, got.tile_size) == (want.tiles_x, want.tiles_y, want.tile_size)
    if spread == 1.0 and log_scale == -3.0:
        assert want.gaussian_ids.numel() > 500  # the case is not vacuous


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_binning_keeps_torch_order_on_depth_ties(dtype):
    """Equal depths (and -0 beside +0, NaN) keep index order within a tile, as a stable argsort does."""
    proj, _ = projected_scene(400, seed=5, num_cams=2)
    depths = (proj.depths * 2).round() / 2  # a handful of distinct depths: ties everywhere
    depths[0, :7] = torch.tensor([0.0, -0.0, 0.0, -0.0, float("nan"), float("nan"), -1.0])
    args = [t.to(dtype) if t.is_floating_point() else t for t in
            (proj.means2d, proj.conics, proj.reach, proj.extents, depths.to(proj.depths), proj.radii)]
    want, got = bin_gaussians(*args, 64, 48, 16), bin_gaussians_fused(*args, 64, 48, 16)
    assert want.gaussian_ids.numel() > 400
    for name in ("gaussian_ids", "tile_ids", "tile_offsets"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name


def test_fused_binning_is_independent_of_threads():
    """The counting sort by tile splits the hits among the threads (and a Gaussian's tiles past the
    four the counting pass keeps are found again): any thread count gives the torch binning's order."""
    proj, _ = projected_scene(3000, seed=3, num_cams=2)
    args = (proj.means2d, proj.conics, proj.reach, proj.extents, proj.depths, proj.radii, 64, 48, 4)
    want = bin_gaussians(*args)
    assert want.gaussian_ids.numel() > 3 * 4096  # enough hits for three threads to share the sort
    assert torch.bincount(want.gaussian_ids).max() > 4
    threads = torch.get_num_threads()
    try:
        for count in (1, 2, 3):
            torch.set_num_threads(count)
            got = bin_gaussians_fused(*args)
            for name in ("gaussian_ids", "tile_ids", "tile_offsets"):
                assert torch.equal(getattr(got, name), getattr(want, name)), (count, name)
    finally:
        torch.set_num_threads(threads)


def test_fused_binning_of_nothing():
    proj, _ = projected_scene(0, seed=0, num_cams=2)
    bins = bin_gaussians_fused(proj.means2d, proj.conics, proj.reach, proj.extents, proj.depths,
                               proj.radii, 64, 48, 16)
    assert bins.gaussian_ids.numel() == 0 and bins.tile_offsets.shape == (2 * 4 * 3 + 1,)
    assert (bins.tile_offsets == 0).all()


def test_build_dir_is_private_to_version_torch_sources_headers_and_flags(monkeypatch, tmp_path):
    """The key is the bytes of both sources and the header beside them, not their folder: a copy keeps it,
    an edit of any of the three (or other flags) gets a new one."""
    import shutil

    kernel = fused_module.EXTENSION
    name = kernel.build_dir().name
    assert name.startswith("hico_composite_cpu-0.") and torch.__version__.replace("+", "-") in name
    copy = tmp_path / "csrc"
    shutil.copytree(kernel.sources[0].parent, copy)
    monkeypatch.setattr(kernel, "sources", tuple(copy / source.name for source in kernel.sources))
    assert kernel.build_dir().name == name
    names = {name}
    for edited in ("composite_cpu.cpp", "binning_cpu.cpp", "binning_cpu.h"):
        (copy / edited).write_bytes((copy / edited).read_bytes() + b"\n")
        names.add(kernel.build_dir().name)
    monkeypatch.setattr(kernel, "flags", ["-O2"])
    names.add(kernel.build_dir().name)
    assert len(names) == 5


def test_stale_build_lock_is_removed_and_a_render_finishes(tmp_path):
    """A builder killed mid-build leaves torch's lock file behind; the next render removes it (with a
    warning) instead of waiting forever. The built folder is copied so ninja has nothing to redo."""
    import os
    import shutil
    import subprocess
    import sys

    assert fused_available(), fused_module.EXTENSION.error
    built = fused_module.EXTENSION.build_dir()
    kernel_dir = tmp_path / "kernels" / built.name
    shutil.copytree(built, kernel_dir, ignore=shutil.ignore_patterns("lock", "hico-build.lock"))
    (kernel_dir / "lock").write_text("")  # the leftover of a killed build
    script = (
        "import torch\n"
        "from hico_plugin.rasterizer import rasterize\n"
        "out = rasterize(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1),"
        " torch.ones(1), torch.ones(1, 3), torch.eye(4), torch.tensor([[60.0, 0, 33], [0, 60, 25], [0, 0, 1]]),"
        " 64, 48, compositor='fused', use_compile=False)\n"
        "print('rendered', float(out.rgb.max()))\n"
    )
    env = {**os.environ, "HICO_CACHE_DIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stderr
    assert "rendered" in done.stdout and "removing the stale kernel build lock" in done.stderr
    assert not (kernel_dir / "lock").exists()


def test_hung_kernel_build_is_killed_and_a_render_finishes(tmp_path):
    """A compiler that never returns: the first-use build is killed after $HICO_KERNEL_BUILD_TIMEOUT
    (compiler included), one line says so, and the render finishes with the torch compositor."""
    import os
    import stat
    import subprocess
    import sys
    import time
    from pathlib import Path

    pid_file = tmp_path / "compiler.pid"
    compiler = tmp_path / "hung-c++"
    compiler.write_text(f"#!/bin/sh\necho $$ > {pid_file}\nexec sleep 600\n")
    compiler.chmod(compiler.stat().st_mode | stat.S_IEXEC)
    script = (
        "import torch\n"
        "from hico_plugin.rasterizer import rasterize\n"
        "out = rasterize(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1),"
        " torch.ones(1), torch.ones(1, 3), torch.eye(4), torch.tensor([[60.0, 0, 33], [0, 60, 25], [0, 0, 1]]),"
        " 64, 48, use_compile=False)\n"
        "print('rendered', float(out.rgb.max()))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "HICO_NO_FUSED"}
    env.update(HICO_CACHE_DIR=str(tmp_path), CXX=str(compiler), HICO_KERNEL_BUILD_TIMEOUT="4")
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env,
                          check=False)
    assert done.returncode == 0, done.stderr
    assert "rendered" in done.stdout and float(done.stdout.split()[-1]) > 0.9
    fallback = [line for line in done.stderr.splitlines() if "could not be built" in line]
    assert len(fallback) == 1 and "did not finish within 4 s" in fallback[0], done.stderr
    assert time.monotonic() - start < 60
    assert pid_file.is_file()  # the compiler did start, so it was the build that hung ...
    status = Path(f"/proc/{int(pid_file.read_text())}/status")
    deadline = time.monotonic() + 10  # ... and it was killed with the build (gone, or a zombie)
    while status.is_file() and "State:\tZ" not in status.read_text() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not status.is_file() or "State:\tZ" in status.read_text()
    left = {path.name for path in (tmp_path / "kernels").rglob("*")}
    assert "lock" not in left and "hico-built" not in left


def _conic(cov):
    return torch.linalg.inv(torch.tensor(cov, dtype=torch.float64))[[0, 0, 1], [0, 1, 1]]


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_fused_bounding_boxes_keep_every_pixel_of_hard_conics(dtype, tol):
    # The fused kernel visits only each row's ellipse bounding box; one 16x16 tile holding every row,
    # against the torch compositor, which tests every (pixel, row) pair.
    rows = [  # (mean, conic (a, b, c), opacity)
        ((7.5, 7.5), _conic([[50.0, 49.9], [49.9, 50.0]]), 0.9),  # needle along the diagonal
        ((3.0, 12.0), _conic([[400.0, 0.0], [0.0, 0.05]]), 0.8),  # thin, longer than the tile
        ((8.0, 8.0), torch.tensor([1.0, 2.0, 1.0]), 0.7),  # indefinite conic: unbounded set
        ((8.0, 8.0), torch.tensor([-1.0, 0.0, -1.0]), 0.7),  # negative definite
        ((15.5, 0.5), _conic([[0.3, 0.0], [0.0, 0.3]]), 0.99),  # tiny, on a pixel centre at the corner
        ((16.0, 16.0), _conic([[0.31, 0.0], [0.0, 0.31]]), 0.6),  # just outside the tile's last pixel
        ((float("nan"), 4.0), _conic([[2.0, 0.0], [0.0, 2.0]]), 0.9),  # not finite
        ((4.0, 4.0), torch.tensor([float("inf"), 0.0, 1.0]), 0.9),
        ((1e20, -1e20), _conic([[2.0, 0.0], [0.0, 2.0]]), 0.9),  # far outside
        ((5.0, 9.0), _conic([[9.0, 3.0], [3.0, 4.0]]), 0.0),  # zero opacity
        ((10.2, 5.7), _conic([[6.0, -2.0], [-2.0, 3.0]]), 1.0),  # clamped at alpha_max
        ((2.5, 2.5), _conic([[1e-4, 0.0], [0.0, 1e-4]]), 0.5),  # smaller than a pixel
    ]
    means2d = torch.tensor([m for m, _, _ in rows], dtype=dtype)
    conics = torch.stack([c.to(dtype) for _, c, _ in rows])
    opacities = torch.tensor([o for _, _, o in rows], dtype=dtype)
    features = torch.rand(len(rows), 4, generator=torch.Generator().manual_seed(3), dtype=dtype)
    count = len(rows)
    bins = TileBins(torch.arange(count), torch.zeros(count, dtype=torch.long), torch.tensor([0, count]), 1, 1, 16)
    assert fused_available(), fused_module.EXTENSION.error
    want = outputs_and_grads(composite, [means2d, conics, opacities, features], bins)
    got = outputs_and_grads(composite_fused, [means2d, conics, opacities, features], bins)
    assert (want[1] > 0).sum() > 100  # the rows do cover the tile
    torch.testing.assert_close(got[0], want[0], atol=tol, rtol=tol)
    torch.testing.assert_close(got[1], want[1], atol=tol, rtol=tol)
    for name, a, b in zip(("means2d", "conics", "opacities", "features"), got[2], want[2]):
        finite = torch.isfinite(b)
        assert torch.equal(finite, torch.isfinite(a)), name
        scale = b[finite].abs().max()
        torch.testing.assert_close(a[finite] / scale, b[finite] / scale, atol=tol, rtol=0, msg=name)


def test_fused_float32_falloff_stepped_by_scanline_keeps_the_exp_accuracy():
    # float32 steps each row's exp(-sigma) from one scanline to the next with two products wherever the
    # box is tall and its sigma bounded; one Gaussian alone in each 16x16 tile, so every pixel's alpha is
    # opacity * exp(-sigma) and the float64 torch compositor gives it exactly. Tile-sized, tilted, small
    # and clamped Gaussians step; the needle's box corners lie beyond sigma 60 and take the direct exp.
    covs = [[[9.0, 0.0], [0.0, 9.0]], [[36.0, 0.0], [0.0, 36.0]], [[20.0, 12.0], [12.0, 15.0]],
            [[2.25, 0.0], [0.0, 2.25]], [[14.0, -9.0], [-9.0, 8.0]], [[50.0, 49.9], [49.9, 50.0]]]
    opacities = torch.tensor([0.9, 0.6, 0.99, 0.3, 1.0, 0.8], dtype=torch.float64)
    count = len(covs)
    local = torch.tensor([[7.5, 8.0], [8.3, 7.1], [6.0, 9.5], [4.2, 11.7], [8.0, 8.0], [7.5, 7.5]],
                         dtype=torch.float64)
    means2d = local + torch.stack([torch.arange(count) * 16.0, torch.zeros(count)], 1).to(torch.float64)
    conics = torch.stack([_conic(c) for c in covs])
    features = torch.rand(count, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    bins = TileBins(torch.arange(count), torch.arange(count), torch.arange(count + 1), count, 1, 16)
    inputs = [means2d, conics, opacities, features]
    want = outputs_and_grads(composite, inputs, bins)
    got = outputs_and_grads(composite_fused, [t.float() for t in inputs], bins)
    assert (want[1] > 0.05).sum() > 600  # the Gaussians fill most of their tiles
    # stepped (tiles 0-4): within 1e-5 of the exact alpha; the needle's direct exp is off by up to 2e-5
    # there, the float32 rounding of its large, cancelling sigma terms
    torch.testing.assert_close(got[1][:5].double(), want[1][:5], atol=1e-7, rtol=1e-5)
    torch.testing.assert_close(got[1].double(), want[1], atol=1e-7, rtol=2e-5)
    torch.testing.assert_close(got[0].double(), want[0], atol=1e-7, rtol=2e-5)
    for name, a, b in zip(("means2d", "conics", "opacities", "features"), got[2], want[2]):
        scale = b.abs().max()
        torch.testing.assert_close(a.double() / scale, b / scale, atol=2e-5, rtol=0, msg=name)
