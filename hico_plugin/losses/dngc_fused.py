"""Fused CPU DNGC terms: csrc/dngc_cpu.cpp, a plain C++ library built on first use (``hico_plugin.native``).

``dngc_terms_fused`` has the contract of ``dngc.dngc_losses`` (the torch reference, used wherever this
kernel is not) and computes the same L_nc, L_ns, L_ds (HiCo-GS Sec. 3.4) and gradients, to float rounding,
in one pass over the pixels each way instead of a chain of per-pixel torch ops and their autograd graph.
Inputs are read in place when their channels are adjacent (e.g. slices of a packed [C,H,W,7] render);
results are bitwise independent of the thread count.
"""

from __future__ import annotations

from ctypes import c_double, c_int, c_int64, c_void_p
from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from hico_plugin.native import DTYPE_SUFFIXES, NativeKernel, pointer, vector_flags
from hico_plugin.rasterizer.geometry import NORMAL_EPS

_IMAGES = [c_void_p] * 6 + [c_int64] * 4 + [c_double] * 2  # 5 images, their strides; B, H, W, C; beta, eps
# -fno-math-errno: GCC vectorises no loop with a sqrt that may set errno; it changes no result.
KERNEL = NativeKernel(
    "hico_dngc_cpu", Path(__file__).parent / "csrc" / "dngc_cpu.cpp", "fused CPU DNGC loss kernel",
    "the torch DNGC terms", flags=["-O3", "-fopenmp", "-fno-math-errno", *vector_flags()],
    functions={"hico_dngc_forward_{dtype}": ([*_IMAGES, c_void_p, c_int], None),
               "hico_dngc_backward_{dtype}": ([*_IMAGES, *[c_double] * 4, *[c_void_p] * 3, c_int], None)})
_CHANNELS = {"alpha": 1, "normal": 3, "depth_normal": 3, "distance": 1}  # rgb: any number >= 1


def dngc_fused_available() -> bool:
    """Whether the fused CPU DNGC kernel is built (building it on the first call)."""
    return KERNEL.available()


def dngc_fused_accepts(rgb: Tensor, alpha: Tensor, normal: Tensor, depth_normal: Tensor, distance: Tensor) -> bool:
    """Whether ``dngc_terms_fused`` takes these images: CPU, one dtype (float32 or float64), [H, W, K] or
    [B, H, W, K] of one leading shape, K = 1, 3, 3, 1 for alpha, normal, depth_normal, distance."""
    named = {"alpha": alpha, "normal": normal, "depth_normal": depth_normal, "distance": distance}
    return (rgb.dim() in (3, 4) and rgb.shape[-1] >= 1 and rgb.dtype in DTYPE_SUFFIXES and rgb.device.type == "cpu"
            and all(t.shape == rgb.shape[:-1] + (_CHANNELS[name],) and t.dtype == rgb.dtype
                    and t.device == rgb.device for name, t in named.items()))


def _strided(images: list[Tensor]) -> tuple[list[Tensor], Tensor]:
    """The [B,H,W,K] images as the kernel reads them (channels adjacent, any other strides) and their
    (batch, row, pixel) strides in elements, [5 * 3] int64."""
    images = [t if t.shape[-1] == 1 or t.stride(-1) == 1 else t.contiguous() for t in images]
    return images, torch.tensor([s for t in images for s in t.stride()[:3]], dtype=torch.int64)


def _call(direction: str, images: list[Tensor], strides: Tensor, beta: float, *rest) -> None:
    batch, height, width, channels = images[0].shape
    KERNEL.function(f"hico_dngc_{direction}_{{dtype}}", images[0].dtype)(
        *(c_void_p(t.data_ptr()) for t in images), pointer(strides), batch, height, width, channels,
        beta, NORMAL_EPS, *rest, torch.get_num_threads())


class _FusedDNGC(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rgb: Tensor, alpha: Tensor, normal: Tensor, depth_normal: Tensor, distance: Tensor,
                beta: float) -> tuple[Tensor, Tensor, Tensor]:
        images, strides = _strided([rgb, alpha, normal, depth_normal, distance])
        out = torch.empty(4, dtype=torch.float64)  # L_nc, L_ns, L_ds, the L_nc weight sum
        _call("forward", images, strides, beta, pointer(out))
        ctx.save_for_backward(*images, strides)
        ctx.beta, ctx.weight_sum = beta, out[3].item()
        return tuple(torch.tensor(value, dtype=normal.dtype) for value in out[:3].tolist())

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_nc: Tensor, grad_ns: Tensor, grad_ds: Tensor):
        *images, strides = ctx.saved_tensors
        grads = [torch.empty(images[0].shape[:3] + (k,), dtype=images[0].dtype) for k in (3, 3, 1)]
        _call("backward", images, strides, ctx.beta, grad_nc.item(), grad_ns.item(), grad_ds.item(),
              ctx.weight_sum, *map(pointer, grads))
        return None, None, *grads, None


def dngc_terms_fused(rgb: Tensor, alpha: Tensor, normal: Tensor, depth_normal: Tensor, distance: Tensor,
                     beta: float = 10.0) -> dict[str, Tensor]:
    """The unweighted DNGC terms {"nc": L_nc, "ns": L_ns, "ds": L_ds} as ``dngc_losses``, each [].

    rgb: [..., H, W, C] rendered image; alpha: [..., H, W, 1]; normal: [..., H, W, 3] n_r; depth_normal:
    [..., H, W, 3] n_d; distance: [..., H, W, 1] d; ``...`` empty or one batch dimension (the means run over
    it too); float32 or float64 CPU tensors of one dtype, any strides. Differentiable w.r.t. normal,
    depth_normal and distance (rgb and alpha are detached, as in the reference). Call
    ``dngc_fused_available()`` first.
    """
    images = (rgb.detach(), alpha.detach(), normal, depth_normal, distance)
    if not dngc_fused_accepts(*images):
        got = ", ".join(f"{tuple(t.shape)} {t.dtype} on {t.device}" for t in images)
        raise ValueError("dngc_terms_fused takes float32/float64 CPU images of one dtype: rgb [..., H, W, C], alpha "
                         f"[..., H, W, 1], normal and depth_normal [..., H, W, 3], distance [..., H, W, 1]; got {got}")
    batched = [t if t.dim() == 4 else t[None] for t in images]
    nc, ns, ds = _FusedDNGC.apply(*batched, float(beta))
    return {"nc": nc, "ns": ns, "ds": ds}
