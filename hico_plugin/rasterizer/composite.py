"""Front-to-back alpha compositing of binned Gaussians, in bounded-memory chunks of tiles.

Every (intersection, pixel-of-its-tile) pair is evaluated as one row of an [R, tile_size^2] block;
transmittance is a per-tile cumulative sum of log(1 - alpha) down the rows, so the early stop
(T < 1e-4) is a mask instead of a loop. The autograd Function keeps only its inputs and recomputes
each chunk in backward, so peak memory is one chunk's pairs, not image size x Gaussian count.
"""

from __future__ import annotations

import math
import os
import warnings
from typing import Callable

import torch
from torch import Tensor

from hico_plugin.rasterizer.projection import ALPHA_MIN
from hico_plugin.rasterizer.tiling import TileBins

ALPHA_MAX = 0.99
LOG_T_MIN = math.log(1e-4)  # a Gaussian is drawn only while the transmittance after it stays above
PAIRS_PER_CHUNK = 1 << 22  # ~4M pairs: a few hundred MB of float32 intermediates per chunk


def composite_chunk(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor,
                    gaussian_ids: Tensor, seg_ids: Tensor, seg_starts: Tensor,
                    pix_x: Tensor, pix_y: Tensor) -> tuple[Tensor, Tensor]:
    """Composite one chunk of S consecutive tiles holding R intersections.

    means2d [G,2], conics [G,3], opacities [G], features [G,D] (G flattened Gaussians);
    gaussian_ids [R]; seg_ids [R] tile of each row within the chunk (non-decreasing);
    seg_starts [S] first row of each tile; pix_x, pix_y [S,P] pixel-centre coordinates of each tile.
    Returns features [S,P,D] and alpha [S,P].
    """
    mean = means2d[gaussian_ids]
    conic = conics[gaussian_ids]
    dx = pix_x[seg_ids] - mean[:, 0:1]  # [R,P]
    dy = pix_y[seg_ids] - mean[:, 1:2]
    sigma = 0.5 * (conic[:, 0:1] * dx * dx + conic[:, 2:3] * dy * dy) + conic[:, 1:2] * dx * dy
    alpha = torch.clamp_max(opacities[gaussian_ids][:, None] * torch.exp(-sigma), ALPHA_MAX)
    alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    log_t = torch.log1p(-alpha)

    # Segmented cumsum: subtract the previous tile's total at each tile start, so the running sum
    # restarts near zero per tile (a plain prefix difference would lose float32 precision).
    num_segs = pix_x.shape[0]
    totals = log_t.new_zeros(num_segs, log_t.shape[1]).index_add(0, seg_ids, log_t)
    # Empty tiles share their start row with the next tile and add a zero total; trailing empty
    # tiles start past the last row and are dropped.
    inside = (seg_starts[1:] < log_t.shape[0])[:, None]
    reset = torch.zeros_like(log_t).index_put(
        (seg_starts[1:].clamp_max(log_t.shape[0] - 1),),
        torch.where(inside, totals[:-1], torch.zeros_like(totals[:-1])), accumulate=True)
    log_t_after = torch.cumsum(log_t - reset, 0)  # log T after each Gaussian, within its tile
    drawn = log_t_after > LOG_T_MIN
    weight = torch.where(drawn, alpha * torch.exp(log_t_after - log_t), torch.zeros_like(alpha))

    out = features.new_zeros(num_segs, weight.shape[1], features.shape[1])
    out = out.index_add(0, seg_ids, weight[:, :, None] * features[gaussian_ids][:, None, :])
    acc = weight.new_zeros(num_segs, weight.shape[1]).index_add(0, seg_ids, weight)
    return out, acc


_compiled: dict[str, Callable] = {}


def _chunk_fn(use_compile: bool) -> Callable:
    """composite_chunk, through torch.compile when asked and not disabled by HICO_NO_COMPILE=1."""
    if not use_compile or os.environ.get("HICO_NO_COMPILE") == "1" or "failed" in _compiled:
        return composite_chunk
    if "fn" not in _compiled:
        _compiled["fn"] = torch.compile(composite_chunk, dynamic=True)
    return _compiled["fn"]


def _run_chunk(use_compile: bool, *args: Tensor) -> tuple[Tensor, Tensor]:
    if use_compile:
        try:
            return _chunk_fn(True)(*args)
        except Exception as err:  # noqa: BLE001 - any compiler failure falls back to eager
            warnings.warn(f"torch.compile of the compositor failed, using eager mode: {err}")
            _compiled["failed"] = _compiled.pop("fn", None)
    return composite_chunk(*args)


def _chunks(bins: TileBins, pairs_per_chunk: int) -> list[tuple[int, int]]:
    """Consecutive tile ranges holding about ``pairs_per_chunk`` pairs each (a tile is never split)."""
    rows_per_chunk = max(1, pairs_per_chunk // bins.tile_size**2)
    offsets = bins.tile_offsets.tolist()
    num_tiles = len(offsets) - 1
    bounds, start = [], 0
    while start < num_tiles:
        end = int(torch.searchsorted(bins.tile_offsets, offsets[start] + rows_per_chunk,
                                     right=True)) - 1
        end = min(max(end, start + 1), num_tiles)
        bounds.append((start, end))
        start = end
    return bounds


def _chunk_inputs(bins: TileBins, start: int, end: int, dtype: torch.dtype
                  ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """gaussian_ids, seg_ids, seg_starts, pix_x, pix_y of tiles [start, end)."""
    ts = bins.tile_size
    offsets = bins.tile_offsets[start:end + 1]
    rows = slice(int(offsets[0]), int(offsets[-1]))
    tiles = torch.arange(start, end, device=offsets.device)
    in_cam = tiles % (bins.tiles_x * bins.tiles_y)
    local = torch.arange(ts * ts, device=offsets.device)
    pix_x = ((in_cam % bins.tiles_x) * ts)[:, None] + (local % ts)[None, :] + 0.5
    pix_y = (torch.div(in_cam, bins.tiles_x, rounding_mode="floor") * ts)[:, None] \
        + torch.div(local, ts, rounding_mode="floor")[None, :] + 0.5
    return (bins.gaussian_ids[rows], bins.tile_ids[rows] - start, offsets[:-1] - offsets[0],
            pix_x.to(dtype), pix_y.to(dtype))


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, bins, use_compile, pairs_per_chunk):
        num_tiles = bins.tile_offsets.numel() - 1
        pixels = bins.tile_size**2
        out = features.new_zeros(num_tiles, pixels, features.shape[1])
        acc = features.new_zeros(num_tiles, pixels)
        chunks = [c for c in _chunks(bins, pairs_per_chunk)
                  if bins.tile_offsets[c[1]] > bins.tile_offsets[c[0]]]
        for start, end in chunks:
            args = _chunk_inputs(bins, start, end, means2d.dtype)
            out[start:end], acc[start:end] = _run_chunk(
                use_compile, means2d, conics, opacities, features, *args)
        ctx.save_for_backward(means2d, conics, opacities, features)
        ctx.bins, ctx.chunks, ctx.use_compile = bins, chunks, use_compile
        return out, acc

    @staticmethod
    def backward(ctx, grad_out, grad_acc):
        inputs = [t.detach().requires_grad_(True) for t in ctx.saved_tensors]
        grads = [torch.zeros_like(t) for t in inputs]
        for start, end in ctx.chunks:
            args = _chunk_inputs(ctx.bins, start, end, inputs[0].dtype)
            with torch.enable_grad():
                out, acc = _run_chunk(ctx.use_compile, *inputs, *args)
                chunk_grads = torch.autograd.grad(
                    (out, acc), inputs, (grad_out[start:end], grad_acc[start:end]),
                    allow_unused=True)
            for total, g in zip(grads, chunk_grads):
                if g is not None:
                    total += g
        return (*grads, None, None, None)


def composite(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor,
              bins: TileBins, use_compile: bool = False,
              pairs_per_chunk: int = PAIRS_PER_CHUNK) -> tuple[Tensor, Tensor]:
    """Alpha-composite flattened Gaussians over the binned tiles.

    means2d [G,2], conics [G,3], opacities [G], features [G,D] -> features [T,P,D], alpha [T,P],
    with T tiles (camera-major) and P = tile_size^2 pixels per tile in row-major order.
    Differentiable w.r.t. means2d, conics, opacities and features.
    """
    return _Composite.apply(means2d, conics, opacities, features, bins, use_compile,
                            pairs_per_chunk)
