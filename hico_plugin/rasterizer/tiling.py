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


def bin_gaussians(means2d: Tensor, conics: Tensor, reach: Tensor, extents: Tensor,
                  depths: Tensor, radii: Tensor, width: int, height: int, tile_size: int) -> TileBins:
    """means2d [C,N,2], conics [C,N,3], reach [N] (Mahalanobis radius of the 1/255 cut),
    extents [C,N,2] (bbox half-sizes, px), depths [C,N], radii [C,N] (0 = culled).

    Vectorised: each Gaussian's tile rectangle is enumerated with repeat_interleave, tiles its
    ellipse misses are dropped, and a stable sort of depth-ordered intersections by tile gives the
    per-tile depth order.
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
        hit = _ellipse_meets_tile(means2d.detach().reshape(-1, 2)[gaussian_ids],
                                  conics.detach().reshape(-1, 3)[gaussian_ids],
                                  reach.repeat(num_cams)[gaussian_ids], tx, ty, tile_size)
        gaussian_ids, tx, ty = gaussian_ids[hit], tx[hit], ty[hit]
        cam = torch.div(gaussian_ids, n, rounding_mode="floor")
        tile_ids = (cam * tiles_y + ty) * tiles_x + tx
        tile_ids, perm = torch.sort(tile_ids, stable=True)
        gaussian_ids = gaussian_ids[perm]
        num_tiles = num_cams * tiles_x * tiles_y
        tile_offsets = torch.zeros(num_tiles + 1, dtype=torch.int64, device=device)
        tile_offsets[1:] = torch.cumsum(torch.bincount(tile_ids, minlength=num_tiles), 0)
    return TileBins(gaussian_ids, tile_ids, tile_offsets, tiles_x, tiles_y, tile_size)


def _ellipse_meets_tile(mean: Tensor, conic: Tensor, reach: Tensor, tx: Tensor, ty: Tensor,
                        tile_size: int) -> Tensor:
    """Whether the ellipse (x-m)^T conic (x-m) <= reach^2 reaches the pixel centres of tile (tx,ty).

    mean [I,2], conic [I,3], reach [I], tx/ty [I]. The quadratic's minimum over the rectangle of
    pixel centres is 0 with the centre inside, else it lies on an edge: on each edge the 1-D
    minimiser is clamped to the edge's span.
    """
    a, b, c = conic.unbind(-1)
    x0 = tx * tile_size + 0.5 - mean[:, 0]
    x1 = x0 + (tile_size - 1)
    y0 = ty * tile_size + 0.5 - mean[:, 1]
    y1 = y0 + (tile_size - 1)
    inside = (x0 <= 0) & (x1 >= 0) & (y0 <= 0) & (y1 >= 0)

    def quad(dx, dy):
        return a * dx * dx + 2 * b * dx * dy + c * dy * dy

    best = torch.full_like(a, float("inf"))
    for x in (x0, x1):  # vertical edges: minimise over y at fixed x
        best = torch.minimum(best, quad(x, torch.minimum(torch.maximum(-b * x / c, y0), y1)))
    for y in (y0, y1):  # horizontal edges
        best = torch.minimum(best, quad(torch.minimum(torch.maximum(-b * y / a, x0), x1), y))
    return inside | (best <= reach * reach)
