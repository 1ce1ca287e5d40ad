"""Fused CPU depth normal of a plane-depth render: csrc/depth_normal_cpu.cpp, a plain C++ library built on first
use (``hico_plugin.native``).

``depth_normal_from_plane`` computes what ``depth_to_normal(plane_depth(normal, distance, alpha, Ks), Ks)``
(geometry.py, the torch reference, used wherever this kernel is not) computes, values and gradients to float
rounding with every masking rule, in two passes over the pixels each way instead of a chain of per-pixel
torch ops and their autograd graph. Results are bitwise independent of the thread count.
"""

from __future__ import annotations

from ctypes import c_double, c_int, c_int64, c_void_p
from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from hico_plugin.native import DTYPE_SUFFIXES, NativeKernel, pointer, vector_flags
from hico_plugin.rasterizer.geometry import ALPHA_EPS, DENOM_EPS

_SHAPE = [c_int64] * 3 + [c_double] * 2  # C, H, W, ALPHA_EPS, DENOM_EPS
# -fno-math-errno and -fno-trapping-math let GCC vectorise the square root and the masked divisions; neither
# changes a result.
KERNEL = NativeKernel(
    "hico_depth_normal_cpu", Path(__file__).parent / "csrc" / "depth_normal_cpu.cpp",
    "fused CPU depth-normal kernel", "the torch depth normals",
    flags=["-O3", "-fopenmp", "-fno-math-errno", "-fno-trapping-math", *vector_flags()],
    functions={"hico_depth_normal_forward_{dtype}": ([*[c_void_p] * 4, *_SHAPE, c_void_p, c_void_p, c_int], None),
               "hico_depth_normal_backward_{dtype}": ([*[c_void_p] * 5, *_SHAPE, *[c_void_p] * 3, c_int], None)})
_SCRATCH_PLANES = 6  # the backward's scratch: dL/da, dL/db per pixel, one zero pixel at both row ends


def depth_normal_fused_available() -> bool:
    """Whether the fused CPU depth-normal kernel is built (building it on the first call)."""
    return KERNEL.available()


def depth_normal_fused_accepts(normal: Tensor, distance: Tensor, alpha: Tensor, Ks: Tensor) -> bool:
    """Whether ``depth_normal_from_plane`` takes these tensors: CPU, one dtype (float32 or float64), the shapes
    of its contract, and Ks without a gradient (the kernel differentiates w.r.t. normal and distance only)."""
    num_cams, height, width = normal.shape[:3] if normal.dim() == 4 else (-1, -1, -1)
    shapes = [(normal, (num_cams, height, width, 3)), (distance, (num_cams, height, width, 1)),
              (alpha, (num_cams, height, width, 1)), (Ks, (num_cams, 3, 3))]
    return (normal.dtype in DTYPE_SUFFIXES and not Ks.requires_grad
            and all(tuple(t.shape) == shape and t.dtype == normal.dtype and t.device.type == "cpu"
                    for t, shape in shapes))


class _FusedDepthNormal(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal: Tensor, distance: Tensor, alpha: Tensor, Ks: Tensor) -> Tensor:
        num_cams, height, width, _ = normal.shape
        depth, out = normal.new_empty(num_cams, height, width), torch.empty_like(normal)
        KERNEL.function("hico_depth_normal_forward_{dtype}", normal.dtype)(
            pointer(normal), pointer(distance), pointer(alpha), pointer(Ks), num_cams, height, width, ALPHA_EPS,
            DENOM_EPS, pointer(depth), pointer(out), torch.get_num_threads())
        ctx.save_for_backward(normal, alpha, Ks, depth)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor) -> tuple[Tensor, Tensor, None, None]:
        normal, alpha, Ks, depth = ctx.saved_tensors
        num_cams, height, width, _ = normal.shape
        grad_out = grad_out.contiguous()  # held through the call
        scratch = normal.new_empty(num_cams * height * _SCRATCH_PLANES * (width + 2))
        grad_normal, grad_distance = torch.empty_like(normal), torch.empty_like(alpha)
        KERNEL.function("hico_depth_normal_backward_{dtype}", normal.dtype)(
            pointer(normal), pointer(alpha), pointer(Ks), pointer(depth), pointer(grad_out), num_cams, height,
            width, ALPHA_EPS, DENOM_EPS, pointer(scratch), pointer(grad_normal), pointer(grad_distance),
            torch.get_num_threads())
        return grad_normal, grad_distance, None, None


def depth_normal_from_plane(normal: Tensor, distance: Tensor, alpha: Tensor, Ks: Tensor) -> Tensor:
    """The depth normal n_d of the plane depth, as ``depth_to_normal(plane_depth(normal, distance, alpha, Ks), Ks)``.

    normal [C,H,W,3] n_r, distance [C,H,W,1] d, alpha [C,H,W,1] (composited, not normalised), Ks [C,3,3] ->
    [C,H,W,3], unit where defined, else 0 (and 0 on the 1-px border). float32 or float64 CPU tensors of one
    dtype, any strides. Differentiable w.r.t. normal and distance; alpha only enters the masks and Ks must not
    need a gradient (see ``depth_normal_fused_accepts``). Call ``depth_normal_fused_available()`` first.
    """
    if not depth_normal_fused_accepts(normal, distance, alpha, Ks):
        got = ", ".join(f"{tuple(t.shape)} {t.dtype} on {t.device}" for t in (normal, distance, alpha, Ks))
        raise ValueError("depth_normal_from_plane takes float32/float64 CPU tensors of one dtype: normal [C,H,W,3], "
                         f"distance and alpha [C,H,W,1], Ks [C,3,3] without a gradient; got {got}")
    return _FusedDepthNormal.apply(normal.contiguous(), distance.contiguous(), alpha.detach().contiguous(),
                                   Ks.contiguous())
