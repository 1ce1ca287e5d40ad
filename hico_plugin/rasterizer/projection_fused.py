"""Fused CPU projection of Gaussians: csrc/projection_cpu.cpp, a plain C++ library built on first use
(``hico_plugin.native``).

``project_gaussians_fused`` computes what ``projection.project_gaussians`` (the torch reference, used wherever
this kernel is not) computes, optionally with ``geometry.gaussian_normals``: values and gradients to float
rounding, in one pass per (Gaussian, camera) each way instead of a few hundred torch ops and their autograd graph
(backward recomputes from the inputs). Results are bitwise independent of the thread count.
"""

from __future__ import annotations

from ctypes import c_double, c_int, c_int64, c_void_p
from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from hico_plugin.native import DTYPE_SUFFIXES, NativeKernel, pointer, vector_flags
from hico_plugin.rasterizer.base import FAR, NEAR
from hico_plugin.rasterizer.projection import (
    COV2D_BLUR, DET_MIN, FRUSTUM_MARGIN, QUAT_NORM_MIN, Projection, opacity_reach)

# C, N, width, height, near, far, COV2D_BLUR, FRUSTUM_MARGIN, DET_MIN, QUAT_NORM_MIN
_SETTINGS = [c_int64] * 2 + [c_double] * 8
# -fno-math-errno and -fno-trapping-math let GCC inline the square roots; neither changes a result.
KERNEL = NativeKernel(
    "hico_projection_cpu", Path(__file__).parent / "csrc" / "projection_cpu.cpp", "fused CPU projection kernel",
    "the torch projection", flags=["-O3", "-fopenmp", "-fno-math-errno", "-fno-trapping-math", *vector_flags()],
    functions={"hico_projection_forward_{dtype}": ([*[c_void_p] * 6, *_SETTINGS, *[c_void_p] * 7, c_int], None),
               "hico_projection_backward_{dtype}": ([*[c_void_p] * 5, *_SETTINGS, *[c_void_p] * 8, c_int], None)})


def projection_fused_available() -> bool:
    """Whether the fused CPU projection kernel is built (building it on the first call)."""
    return KERNEL.available()


def projection_fused_accepts(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmats: Tensor,
                             Ks: Tensor) -> bool:
    """Whether ``project_gaussians_fused`` takes these tensors: CPU, one dtype (float32 or float64), the shapes of
    its contract, and viewmats and Ks without a gradient (the kernel differentiates w.r.t. means, quats and
    scales; the opacities only set the drawn extent, which has no gradient)."""
    n = means.shape[0] if means.dim() == 2 else -1
    num_cams = viewmats.shape[0] if viewmats.dim() == 3 else -1
    shapes = [(means, (n, 3)), (quats, (n, 4)), (scales, (n, 3)), (opacities, (n,)), (viewmats, (num_cams, 4, 4)),
              (Ks, (num_cams, 3, 3))]
    return (means.dtype in DTYPE_SUFFIXES and not viewmats.requires_grad and not Ks.requires_grad
            and all(tuple(t.shape) == shape and t.dtype == means.dtype and t.device.type == "cpu"
                    for t, shape in shapes))


def _optional_pointer(tensor: Tensor | None) -> c_void_p:
    """A contiguous tensor's address, or a null pointer for a zero cotangent (None)."""
    return c_void_p(None) if tensor is None else pointer(tensor)


class _FusedProjection(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, reach, viewmats, Ks, settings, with_normals):
        num_cams, n = viewmats.shape[0], means.shape[0]
        means_cam, conics = means.new_empty(num_cams, n, 3), means.new_empty(num_cams, n, 3)
        means2d, extents = means.new_empty(num_cams, n, 2), means.new_empty(num_cams, n, 2)
        radii = means.new_empty(num_cams, n, dtype=torch.int32)
        normals = means.new_empty(num_cams, n, 3) if with_normals else None
        distances = means.new_empty(num_cams, n) if with_normals else None
        KERNEL.function("hico_projection_forward_{dtype}", means.dtype)(
            pointer(means), pointer(quats), pointer(scales), pointer(reach), pointer(viewmats), pointer(Ks),
            num_cams, n, *settings, pointer(means_cam), pointer(means2d), pointer(conics), pointer(extents),
            pointer(radii), _optional_pointer(normals), _optional_pointer(distances), torch.get_num_threads())
        ctx.save_for_backward(means, quats, scales, viewmats, Ks)
        ctx.settings = settings
        ctx.mark_non_differentiable(extents)
        ctx.set_materialize_grads(False)  # an unused output's cotangent stays None: the kernel skips its terms
        return means_cam, means2d, conics, extents, radii, normals, distances

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_means_cam, grad_means2d, grad_conics, _extents, _radii, grad_normals, grad_distances):
        means, quats, scales, viewmats, Ks = ctx.saved_tensors
        cotangents = [None if g is None else g.contiguous()  # held through the call
                      for g in (grad_means_cam, grad_means2d, grad_conics, grad_normals, grad_distances)]
        grad_means, grad_quats, grad_scales = torch.empty_like(means), torch.empty_like(quats), torch.empty_like(scales)
        KERNEL.function("hico_projection_backward_{dtype}", means.dtype)(
            pointer(means), pointer(quats), pointer(scales), pointer(viewmats), pointer(Ks), viewmats.shape[0],
            means.shape[0], *ctx.settings, *map(_optional_pointer, cotangents), pointer(grad_means),
            pointer(grad_quats), pointer(grad_scales), torch.get_num_threads())
        return grad_means, grad_quats, grad_scales, None, None, None, None, None


def project_gaussians_fused(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmats: Tensor,
                            Ks: Tensor, width: int, height: int, near: float = NEAR, far: float = FAR, *,
                            normals: bool = False) -> Projection:
    """``project_gaussians`` (same arguments, same ``Projection``), with ``normals``: its ``normals`` [C,N,3] and
    ``distances`` [C,N] as ``geometry.gaussian_normals(quats, scales, means_cam, viewmats)``.

    float32 or float64 CPU tensors of one dtype, any strides; differentiable w.r.t. means, quats and scales.
    viewmats and Ks must not need a gradient (see ``projection_fused_accepts``). ``depths`` is a view of
    ``means_cam``. Call ``projection_fused_available()`` first.
    """
    if not projection_fused_accepts(means, quats, scales, opacities, viewmats, Ks):
        got = ", ".join(f"{tuple(t.shape)} {t.dtype} on {t.device}"
                        for t in (means, quats, scales, opacities, viewmats, Ks))
        raise ValueError("project_gaussians_fused takes float32/float64 CPU tensors of one dtype: means [N,3], "
                         "quats [N,4], scales [N,3], opacities [N], viewmats [C,4,4] and Ks [C,3,3] without a "
                         f"gradient; got {got}")
    reach = opacity_reach(opacities).contiguous()
    settings = (float(width), float(height), float(near), float(far), COV2D_BLUR, FRUSTUM_MARGIN, DET_MIN,
                QUAT_NORM_MIN)
    means_cam, means2d, conics, extents, radii, normal, distance = _FusedProjection.apply(
        means.contiguous(), quats.contiguous(), scales.contiguous(), reach, viewmats.contiguous(), Ks.contiguous(),
        settings, normals)
    return Projection(means_cam, means2d, conics, means_cam[..., 2], reach, extents, radii, normal, distance)
