"""Tile binning: the flat list of (tile, Gaussian) intersections sorted by (tile, depth)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class TileBins:
    """Intersections of C cameras' tiles with the Gaussians, flattened over cameras.

    Tiles are numbered camera-major, then row-major: ``tile = c * tiles_y * tiles_x + ty * tiles_x + tx``;
    Gaussians are numbered ``c * N + n`` (the flattened [C,N] projection).
    """

    gaussian_ids: Tensor  # [I] int64 flattened Gaussian of each intersection, by (tile, depth)
    tile_ids: Tensor  # [I] int64 tile of each intersection (non-decreasing)
    tile_offsets: Tensor  # [T+1] int64 first intersection of each tile (T = C * tiles_y * tiles_x)
    tiles_x: int
    tiles_y: int
    tile_size: int


def bin_gaussians(means2d: Tensor, extents: Tensor, depths: Tensor, radii: Tensor,
                  width: int, height: int, tile_size: int) -> TileBins:
    """means2d [C,N,2], extents [C,N,2] (bbox half-sizes, px), depths [C,N], radii [C,N] (0 = culled).

    Vectorised: each Gaussian's tile rectangle is enumerated with repeat_interleave, and a stable
    sort of depth-ordered intersections by tile gives the per-tile depth order.
    """
    num_cams, n = depths.shape
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    device = depths.device
    with torch.no_grad():
        u, v = means2d.detach().reshape(-1, 2).unbind(-1)
        ex, ey = extents.reshape(-1, 2).unbind(-1)
        # Pixels i with centre i+0.5 inside [u-ex, u+ex]; then their tiles, clipped to the image.
        x0 = torch.ceil(u - ex - 0.5).clamp(0, width - 1)
        x1 = torch.floor(u + ex - 0.5).clamp(0, width - 1)
        y0 = torch.ceil(v - ey - 0.5).clamp(0, height - 1)
        y1 = torch.floor(v + ey - 0.5).clamp(0, height - 1)
        tx0 = torch.div(x0, tile_size, rounding_mode="floor").long()
        tx1 = torch.div(x1, tile_size, rounding_mode="floor").long()
        ty0 = torch.div(y0, tile_size, rounding_mode="floor").long()
        ty1 = torch.div(y1, tile_size, rounding_mode="floor").long()
        drawn = (radii.reshape(-1) > 0) & (x0 <= x1) & (y0 <= y1)
        span_x = (tx1 - tx0 + 1).clamp_min(0)
        counts = torch.where(drawn, span_x * (ty1 - ty0 + 1), torch.zeros_like(span_x))

        # Enumerate in global depth order so that a stable sort by tile keeps depth order per tile.
        order = torch.argsort(depths.detach().reshape(-1), stable=True)
        order = order[counts[order] > 0]
        counts_sorted = counts[order]
        gaussian_ids = torch.repeat_interleave(order, counts_sorted)
        starts = torch.cumsum(counts_sorted, 0) - counts_sorted
        local = torch.arange(gaussian_ids.numel(), device=device) - torch.repeat_interleave(
            starts, counts_sorted)
        span = span_x[gaussian_ids]
        tx = tx0[gaussian_ids] + local % span
        ty = ty0[gaussian_ids] + torch.div(local, span, rounding_mode="floor")
        cam = torch.div(gaussian_ids, n, rounding_mode="floor")
        tile_ids = (cam * tiles_y + ty) * tiles_x + tx
        tile_ids, perm = torch.sort(tile_ids, stable=True)
        gaussian_ids = gaussian_ids[perm]
        num_tiles = num_cams * tiles_x * tiles_y
        tile_offsets = torch.zeros(num_tiles + 1, dtype=torch.int64, device=device)
        tile_offsets[1:] = torch.cumsum(torch.bincount(tile_ids, minlength=num_tiles), 0)
    return TileBins(gaussian_ids, tile_ids, tile_offsets, tiles_x, tiles_y, tile_size)
