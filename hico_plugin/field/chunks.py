"""Anchors grouped into Morton-order chunks with conservative bounds, so a view's selection tests the chunks first
and then only the anchors of chunks it may see: a step costs what its view sees, not what the model holds (the
block culling of CityGS-X and Hierarchical 3DGS).

A chunk is rejected only when no anchor inside could pass ``lod_visible`` and ``frustum_visible`` (bounds: the
anchors' box, their largest extent, smallest level minus largest eps), so the selection is exactly the rule's over
the whole model. Bounds only grow when rows move (``expand``); a rebuild tightens them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from hico_plugin.cameras import Camera
from hico_plugin.field.octree import OctreeGrid

MORTON_BITS = 10
"""Bits per axis of the Morton code that orders the anchors (1024 cells a side of the octree cube)."""

# Relative slack of the chunk tests over float32 rounding of the per-anchor rule (a few ulp of 6e-8).
_SLACK = 1e-5


def morton_codes(positions: Tensor, grid: OctreeGrid, bits: int = MORTON_BITS) -> Tensor:
    """Interleaved-bit (Z-order) codes of positions [N,3] quantised in the octree's cube: [N] long."""
    cells = (1 << bits) - 1
    scaled = (positions.detach() - grid.origin_tensor(positions)) / grid.cube_size * cells
    quantised = scaled.clamp(0, cells).long()
    code = torch.zeros(positions.shape[0], dtype=torch.long, device=positions.device)
    for bit in range(bits):
        for axis in range(3):
            code |= ((quantised[:, axis] >> bit) & 1) << (3 * bit + axis)
    return code


def _reduce_rows_(target: Tensor, index: Tensor, source: Tensor, reduce: str) -> None:
    """target[index[i]] = reduce(target[index[i]], source[i]) over the rows of source [M, ...]."""
    if source.dim() > 1:
        index = index[:, None].expand_as(source)
    target.scatter_reduce_(0, index, source, reduce)


@dataclass
class AnchorChunks:
    """order [N] long: anchor rows in Morton order, cut into chunks at starts [C+1]; chunk_of [N] long:
    each row's chunk; low / high [C,3]: the box of a chunk's positions; reach [C]: its largest anchor
    extent; level_min [C]: its smallest level; level_floor [C]: its smallest level - eps (the LOD rule's
    bound). A non-finite value widens its chunk's bounds to everything."""

    order: Tensor
    starts: Tensor
    chunk_of: Tensor
    low: Tensor
    high: Tensor
    reach: Tensor
    level_min: Tensor
    level_floor: Tensor

    @classmethod
    def build(cls, positions: Tensor, levels: Tensor, extra_level: Tensor, radii: Tensor, grid: OctreeGrid,
              chunk_size: int) -> "AnchorChunks":
        """Chunks of ``chunk_size`` consecutive anchors in Morton order (positions [N,3], levels [N],
        extra_level [N], radii [N])."""
        num, device = positions.shape[0], positions.device
        order = torch.argsort(morton_codes(positions, grid), stable=True)
        count = math.ceil(num / chunk_size)
        starts = (torch.arange(count + 1, device=device) * chunk_size).clamp_max(num)
        chunk_of = torch.empty(num, dtype=torch.long, device=device)
        chunk_of[order] = torch.arange(num, device=device) // chunk_size
        chunks = cls(order, starts, chunk_of, positions.new_empty(count, 3), positions.new_empty(count, 3),
                     positions.new_empty(count), levels.new_empty(count), positions.new_empty(count))
        chunks.refresh(positions, levels, extra_level, radii)
        return chunks

    def refresh(self, positions: Tensor, levels: Tensor, extra_level: Tensor, radii: Tensor) -> None:
        """Recompute every chunk's bounds from all anchors (the same grouping)."""
        self.low.fill_(math.inf)
        self.high.fill_(-math.inf)
        self.reach.fill_(0.0)
        self.level_min.fill_(torch.iinfo(self.level_min.dtype).max)
        self.level_floor.fill_(math.inf)
        _reduce_rows_(self.level_min, self.chunk_of, levels, "amin")
        floor = torch.nan_to_num(levels.to(extra_level) - extra_level, nan=-math.inf)
        _reduce_rows_(self.level_floor, self.chunk_of, floor, "amin")
        self._widen(self.chunk_of, positions, radii)

    def expand(self, rows: Tensor, positions: Tensor, radii: Tensor) -> None:
        """Grow the bounds of the chunks of ``rows`` [R] long to their new positions [R,3] and radii [R]."""
        self._widen(self.chunk_of.index_select(0, rows), positions, radii)

    def _widen(self, index: Tensor, positions: Tensor, radii: Tensor) -> None:
        positions = positions.detach()
        _reduce_rows_(self.low, index, torch.nan_to_num(positions, nan=-math.inf), "amin")
        _reduce_rows_(self.high, index, torch.nan_to_num(positions, nan=math.inf), "amax")
        _reduce_rows_(self.reach, index, torch.nan_to_num(radii.detach(), nan=math.inf), "amax")

    def candidates(self, camera: Camera, grid: OctreeGrid, active_levels: int, distance_scale: float,
                   near: float, margin: float) -> Tensor:
        """Rows of the chunks in which an anchor may pass the LOD rule and the frustum test: [M] long
        (in chunk order, not sorted)."""
        seen = self._lod_possible(camera.center.to(self.low), grid, active_levels, distance_scale)
        seen &= self._frustum_possible(camera, near, margin)
        chosen = seen.nonzero().squeeze(1)
        first = self.starts[chosen]
        lengths = self.starts[chosen + 1] - first
        # row j of the output is order[first[c] + (j - start of c's run in the output)]
        shift = torch.repeat_interleave(first - (torch.cumsum(lengths, 0) - lengths), lengths)
        return self.order[torch.arange(shift.numel(), device=shift.device) + shift]

    def _lod_possible(self, center: Tensor, grid: OctreeGrid, active_levels: int, distance_scale: float) -> Tensor:
        # lod_visible keeps level <= clamp(round(log_b(d_std / d) + eps), 0, active - 1): level 0 always,
        # otherwise level - eps <= log_b(d_std / d) + 1/2, largest at the box's nearest point.
        gap = torch.maximum(self.low - center, center - self.high).clamp_min(0)
        nearest = gap.norm(dim=1) * distance_scale * (1 - _SLACK)
        predicted = torch.log2(grid.d_std / nearest.clamp_min(1e-12)) / math.log2(grid.fork)
        unreachable = (self.level_min > 0) & (self.level_floor > predicted + 0.5 + _SLACK)
        return ~unreachable & (self.level_min <= active_levels - 1)

    def _frustum_possible(self, camera: Camera, near: float, margin: float) -> Tensor:
        # frustum_visible keeps an anchor in front (z > near) whose projection lies within the image
        # widened by margin and by its own reach r f / z; for z > 0 each side is a half-space of the
        # camera coordinates, a . p_cam + r f > 0, so of the world, n . p + a . t + r f > 0 with
        # n = R^T a, whose largest value over a box of centre c and half-size h is n . c + |n| . h.
        # Evaluated in float64 with a slack over the float32 rounding of the per-anchor test; a chunk is
        # only rejected by a comparison that holds (never by a NaN).
        rotation, translation = camera.viewmat[:3, :3].double(), camera.viewmat[:3, 3].double()
        K = camera.K.double()
        fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        focal, width, height = max(fx, fy), float(camera.width), float(camera.height)
        pad_w, pad_h = margin * width, margin * height
        planes = torch.tensor([[0.0, 0.0, 1.0], [fx, 0.0, cx + pad_w], [-fx, 0.0, width + pad_w - cx],
                               [0.0, fy, cy + pad_h], [0.0, -fy, height + pad_h - cy]],
                              dtype=torch.float64, device=rotation.device)  # [5,3]: in front, 4 sides
        normals = planes @ rotation  # rows n = R^T a
        centre, half = (self.high.double() + self.low.double()) / 2, (self.high.double() - self.low.double()) / 2
        best = centre @ normals.T + half @ normals.abs().T + planes @ translation  # [C,5]
        magnitude = (centre.abs() + half) @ normals.abs().T + planes.abs() @ translation.abs()
        reach = (self.reach.double() * focal)[:, None]
        magnitude = magnitude + reach
        possible = ~(best[:, 0] <= near - _SLACK * magnitude[:, 0])
        if near > 0:
            possible &= ~(best[:, 1:] + reach <= -_SLACK * magnitude[:, 1:]).any(1)
        return possible
