"""The fused CPU SSIM kernel against pytorch-msssim: values, gradients w.r.t. pred, thread independence."""

from __future__ import annotations

import warnings

import pytest
import pytorch_msssim
import torch

from hico_plugin.losses.photometric import photometric_terms
from hico_plugin.metrics import image
from hico_plugin.metrics.ssim_fused import KERNEL, gaussian_window, ssim_fused
from helpers_native import require_kernel

# Relative tolerances: float32 and float64 rounding of two different summation orders.
TOL = {torch.float32: 1e-5, torch.float64: 1e-10}
SIZES = [(11, 11), (12, 30), (64, 48), (97, 203)]


@pytest.fixture(autouse=True)
def _kernel():
    require_kernel(KERNEL)


def reference_ssim(pred, target):
    """pytorch-msssim as metrics.image.ssim calls it: [B, H, W, C] -> [B]."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # its warning for a dimension shorter than the window
        return pytorch_msssim.ssim(pred.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2), data_range=1.0,
                                   size_average=False, win_size=11, win_sigma=1.5)


def value_and_grad(fn, pred, target):
    """fn(pred, target) and the gradient w.r.t. pred of its images weighted 1, 2, ... (so the per-image
    upstream gradient matters)."""
    pred = pred.detach().clone().requires_grad_()
    values = fn(pred, target)
    weights = torch.arange(1, values.numel() + 1, dtype=values.dtype).reshape(values.shape)
    (values * weights).sum().backward()
    return values.detach(), pred.grad


def assert_matches_reference(pred, target, tol):
    """Fused and pytorch-msssim agree: values to ``tol`` relative, gradients to ``tol`` of the larger of
    their largest entry and 1 / pixels-per-image (their natural scale: the gradient of a mean)."""
    batched = pred.dim() == 4
    value, grad = value_and_grad(ssim_fused, pred, target)
    ref_value, ref_grad = value_and_grad(
        lambda p, t: reference_ssim(p, t) if batched else reference_ssim(p[None], t[None])[0], pred, target)
    assert value.shape == ref_value.shape == pred.shape[:-3]
    torch.testing.assert_close(value, ref_value, rtol=tol, atol=tol)
    scale = max(ref_grad.abs().max().item(), 1.0 / pred.shape[-3:].numel())
    torch.testing.assert_close(grad, ref_grad, rtol=0.0, atol=tol * scale)


def random_pair(shape, dtype, seed):
    """A target and a noisy prediction of it, both in [0, 1]."""
    generator = torch.Generator().manual_seed(seed)
    target = torch.rand(shape, generator=generator, dtype=dtype)
    return (target + 0.2 * torch.randn(shape, generator=generator, dtype=dtype)).clamp(0, 1), target


def test_gradcheck_float64():
    pred, target = random_pair((2, 13, 17, 3), torch.float64, 0)
    assert torch.autograd.gradcheck(lambda p: ssim_fused(p, target), (pred.requires_grad_(),))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size", SIZES)
def test_matches_pytorch_msssim(dtype, size):
    pred, target = random_pair((2, *size, 3), dtype, 1)
    assert_matches_reference(pred, target, TOL[dtype])  # batched
    assert_matches_reference(pred[1], target[1], TOL[dtype])  # one image [H, W, C]
    independent = torch.rand((2, *size, 3), generator=torch.Generator().manual_seed(2), dtype=dtype)
    assert_matches_reference(independent, target, TOL[dtype])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size", SIZES)
def test_identical_images_give_one_and_no_gradient(dtype, size):
    image_ = random_pair((2, *size, 3), dtype, 3)[1]
    value, grad = value_and_grad(ssim_fused, image_, image_)
    torch.testing.assert_close(value, torch.ones(2, dtype=dtype), rtol=0.0, atol=TOL[dtype])
    assert grad.abs().max().item() < TOL[dtype] / image_[0].numel()
    assert_matches_reference(image_, image_, TOL[dtype])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size", SIZES)
def test_constant_images(dtype, size):
    pred = torch.stack([torch.full((*size, 3), 0.3, dtype=dtype), torch.full((*size, 3), 0.9, dtype=dtype)])
    target = torch.stack([torch.full((*size, 3), 0.7, dtype=dtype), torch.full((*size, 3), 0.2, dtype=dtype)])
    # In float32 both sides' sigmas are E[x^2] - mu^2 of equal numbers, rounding noise of ~1e-7 against
    # C2 = 9e-4: each is ~1e-4 off the exact (float64) answer, so they agree only to that.
    tol = 1e-3 if dtype == torch.float32 else TOL[dtype]
    assert_matches_reference(pred, target, tol)
    assert_matches_reference(pred[0], target[0], tol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size", [(8, 40), (40, 8), (5, 7)])
def test_smaller_than_window_skips_smoothing_like_pytorch_msssim(dtype, size):
    pred, target = random_pair((2, *size, 3), dtype, 4)
    with pytest.warns(UserWarning, match="Skipping Gaussian Smoothing"):
        ssim_fused(pred, target)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert_matches_reference(pred, target, TOL[dtype])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bitwise_independent_of_thread_count(dtype):
    pred, target = random_pair((2, 150, 77, 3), dtype, 5)  # several row blocks per channel
    threads = torch.get_num_threads()
    try:
        results = []
        for count in (1, 2):
            torch.set_num_threads(count)
            results.append(value_and_grad(ssim_fused, pred, target))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])


def test_refuses_a_target_that_needs_a_gradient():
    pred, target = random_pair((12, 12, 3), torch.float32, 6)
    with pytest.raises(ValueError, match="pred only"):
        ssim_fused(pred, target.requires_grad_())


def test_metrics_ssim_routes_to_the_kernel_on_cpu(monkeypatch):
    pred, target = random_pair((2, 40, 52, 3), torch.float32, 7)
    assert torch.equal(image.ssim(pred, target), ssim_fused(pred, target))
    assert torch.equal(image.ssim(pred[0], target[0]), ssim_fused(pred[0], target[0]))
    # A target that needs a gradient goes to pytorch-msssim, which gives it one.
    target_grad = target.clone().requires_grad_()
    image.ssim(pred, target_grad).sum().backward()
    assert target_grad.grad is not None and target_grad.grad.abs().sum() > 0
    monkeypatch.setattr(image, "ssim_fused_available", lambda: False)
    torch.testing.assert_close(image.ssim(pred, target), reference_ssim(pred, target), rtol=1e-5, atol=0.0)


def test_photometric_loss_uses_the_kernel():
    rgb, target = random_pair((2, 30, 41, 3), torch.float32, 8)
    fused_rgb, reference_rgb = rgb.clone().requires_grad_(), rgb.clone().requires_grad_()
    l1, dssim = photometric_terms(fused_rgb, target)
    assert torch.equal(dssim, 1.0 - ssim_fused(fused_rgb, target).mean())
    (l1 + dssim).backward()
    ((reference_rgb - target).abs().mean() + 1.0 - reference_ssim(reference_rgb, target).mean()).backward()
    scale = reference_rgb.grad.abs().max().item()
    torch.testing.assert_close(fused_rgb.grad, reference_rgb.grad, rtol=0.0, atol=1e-5 * scale)


def test_window_is_pytorch_msssims():
    from pytorch_msssim.ssim import _fspecial_gauss_1d

    assert torch.equal(gaussian_window(), _fspecial_gauss_1d(11, 1.5).flatten())
