"""The fused CPU kernels: csrc/composite_cpu.cpp (the compositor) and csrc/binning_cpu.cpp (the tile binning), one
torch extension built on first use (``hico_plugin.native``; needs a C++ compiler, as torch.compile on CPU does);
without it the renderer uses the torch compositor, saying so.

``composite_fused`` has ``composite.composite``'s contract (the reference and fallback) in one pass per pixel with
early termination, so deep tiles cost what is visible, not what is binned; ``bin_gaussians_fused`` returns exactly
what ``tiling.bin_gaussians`` does without the tensors of every candidate (Gaussian, tile) pair.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from hico_plugin.native import NativeKernel
from hico_plugin.rasterizer.composite import ALPHA_MAX, LOG_T_MIN
from hico_plugin.rasterizer.projection import ALPHA_MIN
from hico_plugin.rasterizer.tiling import TileBins

T_MIN = float(torch.tensor(LOG_T_MIN, dtype=torch.float64).exp())  # the torch version's cut, 1e-4

_CSRC = Path(__file__).parent / "csrc"
EXTENSION = NativeKernel("hico_composite_cpu", [_CSRC / "composite_cpu.cpp", _CSRC / "binning_cpu.cpp"],
                         "fused CPU compositor", "the torch one (slower)", loader="torch")


def fused_available() -> bool:
    """Whether the fused CPU compositor is built (building it on the first call)."""
    return EXTENSION.available()


class _FusedComposite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, bins, image_size):
        ext = EXTENSION.get()
        grid = (bins.tiles_x, bins.tiles_x * bins.tiles_y, bins.tile_size)
        inputs = [t.contiguous() for t in (means2d, conics, opacities, features)]
        out, acc, final_t, n_drawn, records = ext.forward(*inputs, bins.gaussian_ids, bins.tile_offsets,
                                                          *grid, ALPHA_MIN, ALPHA_MAX, T_MIN, *image_size)
        # records: each Gaussian's footprint (cut-off, box half-sizes) and inputs packed in one row, which
        # the backward reads instead of recomputing
        ctx.save_for_backward(*inputs, final_t, n_drawn, records)
        ctx.bins, ctx.grid, ctx.image_size = bins, grid, image_size
        return out, acc

    @staticmethod
    def backward(ctx, grad_out, grad_acc):
        means2d, conics, opacities, features, final_t, n_drawn, records = ctx.saved_tensors
        bins = ctx.bins
        grads = EXTENSION.get().backward(
            means2d, conics, opacities, features, bins.gaussian_ids, bins.tile_offsets, *ctx.grid,
            ALPHA_MIN, ALPHA_MAX, final_t, n_drawn, records, grad_out.contiguous(), grad_acc.contiguous(),
            *ctx.image_size)
        return (*grads, None, None)


def bin_gaussians_fused(means2d: Tensor, conics: Tensor, reach: Tensor, extents: Tensor,
                        depths: Tensor, radii: Tensor, width: int, height: int,
                        tile_size: int) -> TileBins:
    """The arguments and result of ``tiling.bin_gaussians`` (CPU tensors). Call ``fused_available()``
    first."""
    num_cams, n = depths.shape
    with torch.no_grad():
        gaussian_ids, tile_ids, tile_offsets = EXTENSION.get().bin(
            means2d.detach().reshape(-1, 2).contiguous(), conics.detach().reshape(-1, 3).contiguous(),
            reach.detach().contiguous(), extents.detach().reshape(-1, 2).contiguous(),
            radii.reshape(-1).to(torch.int32).contiguous(), depths.detach().reshape(-1).contiguous(),
            num_cams, n, width, height, tile_size)
    return TileBins(gaussian_ids, tile_ids, tile_offsets, -(-width // tile_size),
                    -(-height // tile_size), tile_size)


def composite_fused(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor,
                    bins: TileBins, image_size: tuple[int, int] | None = None) -> tuple[Tensor, Tensor]:
    """means2d [G,2], conics [G,3], opacities [G], features [G,D] -> features [T,P,D], alpha [T,P]
    (T tiles camera-major, P = tile_size^2 pixels row-major); with ``image_size`` = (width, height),
    the cameras' images instead: features [C,H,W,D], alpha [C,H,W] (the tiles laid out as images and
    cropped, written in place). CPU tensors, float32 or float64. Differentiable w.r.t. the four
    inputs. Call ``fused_available()`` first."""
    return _FusedComposite.apply(means2d, conics, opacities, features, bins, tuple(image_size or (0, 0)))
