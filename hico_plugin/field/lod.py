"""Per-camera anchor selection: LOD level (paper Eq. 1), progressive level activation, frustum culling."""

from __future__ import annotations

import torch
from torch import Tensor

from hico_plugin.cameras import Camera
from hico_plugin.field.octree import OctreeGrid, lod_levels_from_distance


def progressive_interval_ends(grid: OctreeGrid, coarse_steps: float, coarse_factor: float) -> list[float]:
    """Steps at which levels init_level+1, init_level+2, ... switch on (Octree-GS's progressive training).

    n = num_levels - 1 - init_level intervals whose lengths shrink geometrically by 1/coarse_factor
    and sum to ``coarse_steps``; empty when no level is held back.
    """
    n = grid.num_levels - 1 - grid.init_level
    if n <= 0 or coarse_steps <= 0:
        return []
    q = 1.0 / coarse_factor
    first = coarse_steps * (1 - q) / (1 - q**n) if q != 1.0 else coarse_steps / n
    ends, total = [], 0.0
    for i in range(n):
        total += first * q**i
        ends.append(total)
    ends[-1] = float(coarse_steps)  # exact despite float round-off
    return ends


def active_level_count(grid: OctreeGrid, step: int | None, interval_ends: list[float]) -> int:
    """Number of levels usable at ``step`` (levels 0 .. count-1); ``step=None`` (eval) = all levels."""
    if step is None or not interval_ends:
        return grid.num_levels
    passed = sum(1 for end in interval_ends if end < step)  # searchsorted(ends, step, side="left")
    return min(grid.num_levels, passed + 1 + grid.init_level)


def lod_visible(positions: Tensor, levels: Tensor, extra_level: Tensor, camera_center: Tensor,
                grid: OctreeGrid, active_levels: int, distance_scale: float = 1.0) -> Tensor:
    """Anchors whose level l_i <= predicted level (paper Eq. 1): [N] bool.

    positions [N,3], levels [N], extra_level [N] (eps_i), camera_center [3], distance_scale
    multiplies every distance (1 = Eq. 1). The distance is
    ``||p_i - c||`` as in the paper's Eq. 1 (the base code adds a half-voxel shift to p first; the
    paper does not, and anchors here sit on their grid points, so no shift is applied).
    """
    dist = _row_norm(positions - camera_center) * distance_scale
    predicted = lod_levels_from_distance(dist, grid, extra_level, max_level=active_levels - 1)
    return levels <= predicted


def frustum_visible(positions: Tensor, radii: Tensor, camera: Camera, near: float, margin: float) -> Tensor:
    """Anchors whose extent may reach the widened image: [N] bool.

    positions [N,3], radii [N] world-space extent of each anchor's Gaussians (e.g. 3 x largest
    offset scale). An anchor is kept if z > near and its centre projects within the image widened by
    ``margin`` x (width, height) on each side plus its own projected radius.
    """
    viewmat = camera.viewmat.to(positions)
    K = camera.K.to(positions)
    # elementwise, not a matrix product: an anchor's result must not depend on which others are tested
    cam = (positions[:, 0:1] * viewmat[:3, 0] + positions[:, 1:2] * viewmat[:3, 1]
           + positions[:, 2:3] * viewmat[:3, 2] + viewmat[:3, 3])
    z = cam[:, 2]
    in_front = z > near
    z_safe = torch.where(in_front, z, torch.ones_like(z))
    u = K[0, 0] * cam[:, 0] / z_safe + K[0, 2]
    v = K[1, 1] * cam[:, 1] / z_safe + K[1, 2]
    reach = radii * torch.maximum(K[0, 0], K[1, 1]) / z_safe
    pad_u = margin * camera.width + reach
    pad_v = margin * camera.height + reach
    inside = (u > -pad_u) & (u < camera.width + pad_u) & (v > -pad_v) & (v < camera.height + pad_v)
    return in_front & inside



def _row_norm(vectors: Tensor) -> Tensor:
    """Euclidean norm of each row of [N,3], elementwise, so a row's value is the same in any batch."""
    x, y, z = vectors.unbind(-1)
    return torch.sqrt(x * x + y * y + z * z)
