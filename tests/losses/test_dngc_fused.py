"""The fused CPU DNGC kernel against the torch terms: values, gradients, hard inputs, thread independence,
and its selection by DNGCLossConfig.kernel."""

from __future__ import annotations

import pytest
import torch

from hico_plugin.errors import HicoError
from hico_plugin.losses import DNGCLossConfig, dngc_fused, dngc_losses
from hico_plugin.losses.dngc_fused import KERNEL, dngc_terms_fused
from hico_plugin.rasterizer.base import RenderOutputs
from helpers_native import require_kernel

# Relative tolerances: float32 and float64 rounding of different operation and summation orders.
TOL = {torch.float32: 2e-5, torch.float64: 1e-12}
NAMES = ("rgb", "alpha", "normal", "depth_normal", "distance")
CHANNELS = {"rgb": 3, "alpha": 1, "normal": 3, "depth_normal": 3, "distance": 1}
UPSTREAM = {"nc": 1.3, "ns": -0.7, "ds": 2.1}  # distinct upstream gradients, so each term's backward counts


@pytest.fixture(autouse=True)
def _kernel():
    require_kernel(KERNEL)


def random_images(shape, dtype=torch.float64, seed=0, undefined=0.0):
    """Render-like images of leading shape ``shape`` ([H, W] or [B, H, W]); a fraction ``undefined`` of the
    pixels has a zero n_r and another a zero n_d."""
    generator = torch.Generator().manual_seed(seed)
    images = {name: torch.randn(*shape, k, generator=generator, dtype=dtype) for name, k in CHANNELS.items()}
    images["rgb"] = images["rgb"].abs()
    images["alpha"] = torch.rand(*shape, 1, generator=generator, dtype=dtype)
    images["distance"] = images["distance"] * 3
    for name in ("normal", "depth_normal"):
        images[name][torch.rand(*shape, generator=generator) < undefined] = 0
    return images


def terms_and_grads(fn, images, beta=10.0):
    """fn's terms and the gradients w.r.t. normal, depth_normal, distance of sum_t UPSTREAM[t] * term t."""
    leaves = {name: t.detach().clone().requires_grad_(name not in ("rgb", "alpha")) for name, t in images.items()}
    terms = fn(*(leaves[name] for name in NAMES), beta)
    sum(UPSTREAM[name] * value for name, value in terms.items()).backward()
    return terms, [leaves[name].grad for name in ("normal", "depth_normal", "distance")]


def assert_matches_reference(images, beta=10.0):
    dtype = images["normal"].dtype
    fused_terms, fused_grads = terms_and_grads(dngc_terms_fused, images, beta)
    torch_terms, torch_grads = terms_and_grads(dngc_losses, images, beta)
    assert fused_terms.keys() == torch_terms.keys()
    for name, value in torch_terms.items():
        assert fused_terms[name].dtype == dtype and fused_terms[name].shape == ()
        torch.testing.assert_close(fused_terms[name], value, rtol=TOL[dtype], atol=TOL[dtype] * 1e-3,
                                   msg=lambda m, name=name: f"L_{name}: {m}")
    for name, fused, reference in zip(("normal", "depth_normal", "distance"), fused_grads, torch_grads):
        assert torch.isfinite(fused).all()
        scale = reference.abs().max().item() if reference.numel() else 0.0
        torch.testing.assert_close(fused, reference, rtol=TOL[dtype], atol=TOL[dtype] * scale,
                                   msg=lambda m, name=name: f"grad {name}: {m}")
    return fused_terms, fused_grads


def test_gradcheck_float64():
    images = random_images((2, 5, 6), seed=1)

    def all_terms(normal, depth_normal, distance):
        terms = dngc_terms_fused(images["rgb"], images["alpha"], normal, depth_normal, distance, 2.0)
        return terms["nc"], terms["ns"], terms["ds"]

    inputs = tuple(images[name].clone().requires_grad_() for name in ("normal", "depth_normal", "distance"))
    assert torch.autograd.gradcheck(all_terms, inputs, eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(12, 16), (3, 12, 16), (70, 41), (2, 45, 33)])
def test_values_and_gradients_match_torch(dtype, shape):
    assert_matches_reference(random_images(shape, dtype, seed=2, undefined=0.1))


def _hard_cases():
    cases = {f"size {h}x{w}": random_images((h, w), seed=3, undefined=0.2)
             for h, w in [(1, 1), (1, 9), (9, 1), (2, 2), (0, 4)]}
    zero = random_images((10, 12), seed=4)
    zero["normal"][:, :5] = 0
    zero["depth_normal"][3:] = 0
    zero["normal"][0, 7] = 1e-30  # tiny but non-zero: still undefined
    cases["zero normals"] = zero
    no_weight = random_images((10, 12), seed=5, undefined=0.2)
    no_weight["alpha"].zero_()
    cases["all zero alpha"] = no_weight
    flat = random_images((10, 12), seed=6, undefined=0.1)
    flat["rgb"] = torch.full_like(flat["rgb"], 0.5)
    flat["normal"][:, :, :] = flat["normal"][:1, :1]  # equal neighbours: every |difference| at its kink
    flat["normal"][4:, 6:] = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    flat["depth_normal"] = flat["normal"].clone()
    flat["distance"] = torch.where(torch.arange(12) < 6, 2.0, 3.0).to(torch.float64).expand(10, 12)[..., None]
    cases["equal neighbours"] = flat
    huge = random_images((10, 12), seed=7)
    huge["distance"][:, :4] = 1e20
    cases["huge distances"] = huge
    wide = random_images((10, 12), seed=8)
    wide["rgb"] = wide["rgb"][..., :1].expand(10, 12, 4)  # any channel count, stride-0 channels
    cases["4-channel rgb"] = wide
    return cases


HARD = _hard_cases()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", list(HARD))
def test_hard_inputs_match_torch(case, dtype):
    terms, _ = assert_matches_reference({name: t.to(dtype) for name, t in HARD[case].items()})
    if case == "all zero alpha":
        assert terms["nc"].item() == 0.0
    if case in ("size 1x1", "size 0x4"):  # no differences (and no pixels): 0, not NaN
        assert terms["ns"].item() == terms["ds"].item() == 0.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_beta_zero_and_strided_slices_match_torch(dtype):
    generator = torch.Generator().manual_seed(9)
    render = torch.rand(3, 20, 17, 4, generator=generator, dtype=dtype)  # [C, H, W, rgb + alpha]
    geometry = torch.randn(3, 20, 17, 7, generator=generator, dtype=dtype)  # [C, H, W, n_r + d + n_d]
    geometry[1, 5:9, 3:6, :3] = 0

    def images(camera):
        return {"rgb": render[camera, ..., :3], "alpha": render[camera, ..., 3:], "normal": geometry[camera, ..., :3],
                "distance": geometry[camera, ..., 3:4], "depth_normal": geometry[camera, ..., 4:]}

    assert not any(t.is_contiguous() for t in images(1).values())
    assert_matches_reference(images(1), beta=0.0)
    assert_matches_reference(images(slice(None)), beta=0.0)


def test_float32_edge_weights_are_exp_to_a_few_ulp():
    """The kernel's own float32 exp, through dL_ds/dd of one row whose distance alternates 0, 1, 0, ...:
    -+(e_{j-1} + e_j) / N at pixel j, against float64 exp of the same float32 arguments -beta |dI|."""
    width, beta = 4002, 10.0
    rgb = torch.zeros(1, width, 1)
    rgb[0, 1::2, 0] = torch.linspace(0.0, 7.8, width // 2)  # arguments 0 ... -78: e / N stays a normal float
    distance = (torch.arange(width) % 2).float().reshape(1, width, 1).requires_grad_()
    zeros = torch.zeros(1, width, 3)  # undefined normals: only L_ds has a gradient
    dngc_terms_fused(rgb, zeros[..., :1], zeros, zeros, distance, beta)["ds"].backward()
    e = torch.exp(((-beta) * (rgb[0, 1:, 0] - rgb[0, :-1, 0]).abs()).double())
    sign = torch.where(torch.arange(1, width - 1) % 2 == 0, -1.0, 1.0).double()
    expected = sign * (e[:-1] + e[1:]) / (width - 1)
    torch.testing.assert_close(distance.grad[0, 1:-1, 0].double(), expected, rtol=6e-7, atol=0.0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bitwise_independent_of_thread_count(dtype):
    images = random_images((2, 150, 77), dtype, seed=10, undefined=0.05)  # several row blocks per image
    threads = torch.get_num_threads()
    try:
        results = []
        for count in (1, 2):
            torch.set_num_threads(count)
            results.append(terms_and_grads(dngc_terms_fused, images))
    finally:
        torch.set_num_threads(threads)
    (terms_1, grads_1), (terms_2, grads_2) = results
    assert all(torch.equal(terms_1[name], terms_2[name]) for name in terms_1)
    assert all(torch.equal(a, b) for a, b in zip(grads_1, grads_2))


def test_refuses_images_it_does_not_take():
    images = random_images((6, 7), torch.float32, seed=11)
    with pytest.raises(ValueError, match="float32/float64 CPU"):
        dngc_terms_fused(*(images[name] for name in NAMES[:-1]), images["normal"])  # 3-channel distance
    with pytest.raises(ValueError, match="float32/float64 CPU"):
        dngc_terms_fused(images["rgb"].double(), *(images[name] for name in NAMES[1:]))


def test_loss_kernel_fused_and_torch_give_the_same_terms():
    images = random_images((2, 24, 31), torch.float32, seed=12, undefined=0.1)
    outputs = RenderOutputs(**images)
    losses = {kernel: DNGCLossConfig(start_step=0, warmup_steps=0, kernel=kernel).setup()
              for kernel in ("auto", "fused", "torch")}
    terms = {kernel: loss(outputs, images["rgb"], step=1) for kernel, loss in losses.items()}
    assert set(terms["fused"]) == set(terms["torch"]) == {"dngc_nc", "dngc_ns", "dngc_ds"}
    for name, value in terms["torch"].items():
        assert torch.equal(terms["auto"][name], terms["fused"][name])
        torch.testing.assert_close(terms["fused"][name], value, rtol=TOL[torch.float32], atol=0.0)
    raw = dngc_terms_fused(*(images[name] for name in NAMES))
    assert torch.equal(terms["fused"]["dngc_nc"], 0.05 * raw["nc"])  # the kernel's own value: it ran
    # Images the kernel does not take (mixed dtypes) go to torch, also with kernel="fused".
    mixed = RenderOutputs(**{**images, "rgb": images["rgb"].double()})
    reference = dngc_losses(*(mixed.images()[name] for name in NAMES))
    assert torch.equal(losses["fused"](mixed, images["rgb"], step=1)["dngc_ds"], 0.01 * reference["ds"])


def test_setup_refuses_a_bad_kernel(monkeypatch):
    with pytest.raises(HicoError, match=r"losses\.dngc\.kernel must be one of \['auto', 'fused', 'torch'\]"):
        DNGCLossConfig(kernel="cuda").setup()
    monkeypatch.setattr(dngc_fused, "dngc_fused_available", lambda: False)
    monkeypatch.setattr(dngc_fused.KERNEL, "error", "RuntimeError: no compiler")
    with pytest.raises(HicoError, match=r"losses\.dngc\.kernel='fused'.*no compiler"):
        DNGCLossConfig(kernel="fused").setup()
    DNGCLossConfig(kernel="auto").setup()  # auto falls back to torch instead
