"""The anchor octree: level count and voxel sizes from the cameras, per-level voxelisation, weed-out.

Grid convention (Octree-GS's, the base method of paper Sec. 3.1): level 0 is the coarsest, ``v_l = voxel_size /
fork**l``; ``x`` maps to ``k = round((x - origin) / v_l)`` and the anchor sits on ``origin + k * v_l``, the centre
of the voxel ``[k - 1/2, k + 1/2) * v_l``. So the paper's ``g_i^l = round((p_i - o) / v_l)`` gives every anchor
its own ``k``, and its containing level-(l-1) cell is ``floor(k / 2)`` (the parent-rule choice: context.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.nearest import knn


@dataclass(frozen=True)
class OctreeGrid:
    """Everything needed to map positions to cells and levels; saved with the field's state.

    origin [3]: the cube's minimum corner (grid index 0 at every level); cube_size: its edge (``bbox = origin +
    [0, cube_size]``); voxel_size: level-0 (coarsest) voxel size, ``v_l = voxel_size / fork**l``; num_levels;
    fork: branching factor b per axis (2 = octree); d_std: the standard distance of the LOD rule (paper Eq. 1),
    level 0's; init_level: the last level active from the start (progressive schedule).
    """

    origin: tuple[float, float, float]
    cube_size: float
    voxel_size: float
    num_levels: int
    fork: int
    d_std: float
    init_level: int

    @property
    def bbox(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(min corner, max corner) of the octree's cube."""
        return self.origin, tuple(x + self.cube_size for x in self.origin)

    def origin_tensor(self, like: Tensor) -> Tensor:
        return torch.tensor(self.origin, dtype=like.dtype, device=like.device)

    def grid_index(self, positions: Tensor, levels: Tensor) -> Tensor:
        """Grid index of each position at the given level: positions [N,3], levels [N] -> [N,3] long."""
        sizes = self.voxel_size / float(self.fork) ** levels.to(positions.dtype)
        return torch.round((positions - self.origin_tensor(positions)) / sizes[:, None]).long()

    def grid_position(self, index: Tensor, levels: Tensor, dtype: torch.dtype = torch.float32) -> Tensor:
        """Inverse of ``grid_index``: index [N,3] long, levels [N] -> positions [N,3]."""
        sizes = self.voxel_size / float(self.fork) ** levels.to(dtype)
        return index.to(dtype) * sizes[:, None] + torch.tensor(self.origin, dtype=dtype, device=index.device)

    def cells_per_axis(self, level: int) -> int:
        """Grid indices at ``level`` run from 0 to this value inclusive (grid points of the cube)."""
        return int(round(self.cube_size / (self.voxel_size / self.fork**level)))

    def as_dict(self) -> dict:
        return {
            "origin": list(self.origin), "cube_size": self.cube_size, "voxel_size": self.voxel_size,
            "num_levels": self.num_levels, "fork": self.fork, "d_std": self.d_std,
            "init_level": self.init_level,
        }

    @classmethod
    def from_dict(cls, data: dict) -> "OctreeGrid":
        return cls(origin=tuple(float(x) for x in data["origin"]), cube_size=float(data["cube_size"]),
                   voxel_size=float(data["voxel_size"]), num_levels=int(data["num_levels"]),
                   fork=int(data["fork"]), d_std=float(data["d_std"]), init_level=int(data["init_level"]))


def _quantile(values: Tensor, q: float) -> Tensor:
    """torch.quantile refuses more than 2**24 elements; subsample evenly beyond that."""
    limit = 1 << 24
    if values.numel() > limit:
        values = values.flatten()[:: math.ceil(values.numel() / limit)]
    return torch.quantile(values.flatten().float(), q)


MAX_SEED_POINTS = 2_000_000  # sparse points beyond this are subsampled evenly (memory of the per-level unique)


def anchor_seed_points(points: Tensor, max_points: int = MAX_SEED_POINTS) -> Tensor:
    """The sparse points [P,3] the octree is built from: float32, duplicates removed, evenly strided
    down to ``max_points``."""
    points = torch.unique(points.float(), dim=0)
    return points[:: math.ceil(points.shape[0] / max_points)] if points.shape[0] > max_points else points


def level_count(dist_min: float, dist_max: float, fork: int = 2) -> int:
    """The octree's level count for a camera-to-point distance range (Octree-GS): one level per
    halving (``fork``: per b-fold step) of the distance, round(log_b(dist_max / dist_min)) + 1."""
    if not dist_max > 0:
        return 1
    dist_min = max(dist_min, dist_max * 1e-6)
    return max(1, int(round(math.log2(dist_max / dist_min) / math.log2(fork))) + 1)


def distance_range(points: Tensor, camera_centers: Tensor, dist_ratio: float = 0.999,
                   chunk_elements: int = 1 << 24) -> tuple[float, float]:
    """(dist_min, dist_max) of the camera-to-point distances, robust to outliers (Octree-GS's
    ``set_level``); the one figure the level count, the LOD effect's finding and the mesh depth use.

    points [P,3], camera_centers [C,3]. Per camera, the (1-r) and r quantiles of its distances to
    all points are collected; dist_max is the r-quantile of that list, dist_min its (1-r)-quantile.
    """
    per_camera = []
    rows = max(1, chunk_elements // max(1, points.shape[0]))
    for start in range(0, camera_centers.shape[0], rows):
        dist = torch.cdist(camera_centers[start:start + rows].float(), points.float())  # [c, P]
        qs = torch.tensor([1.0 - dist_ratio, dist_ratio], dtype=dist.dtype)
        if dist.shape[1] > (1 << 24):
            dist = dist[:, :: math.ceil(dist.shape[1] / (1 << 24))]
        per_camera.append(torch.quantile(dist, qs, dim=1).T.reshape(-1))
    collected = torch.cat(per_camera)
    return float(_quantile(collected, 1.0 - dist_ratio)), float(_quantile(collected, dist_ratio))


def knn_log_scale(positions: Tensor, k: int = 3) -> Tensor:
    """log(sqrt(mean squared distance to the k nearest other anchors)): [N] (the 3DGS / Octree-GS
    initial scale, their ``distCUDA2``).

    Coincident anchors (a coarse grid point is also a fine one) give distance 0, clamped to 1e-7 in
    squared distance as the base method does.
    """
    n = positions.shape[0]
    if n < 2:
        return torch.zeros(n, dtype=positions.dtype, device=positions.device)
    dist, _ = knn(positions.detach().cpu().double().numpy(), k)  # [N, min(k, N - 1)], self left out
    mean_sq = torch.from_numpy((dist**2).mean(axis=1)).clamp_min(1e-7)
    return torch.log(torch.sqrt(mean_sq)).to(positions.dtype).to(positions.device)


def lod_levels_from_distance(distances: Tensor, grid: OctreeGrid, extra_level: Tensor | float = 0.0,
                             max_level: int | None = None) -> Tensor:
    """Paper Eq. 1: round(log_b(d_std / distance) + eps), clamped to [0, max_level]: [N] long.

    distances [N] (or any shape), extra_level broadcastable (the learnable eps_i).
    """
    max_level = grid.num_levels - 1 if max_level is None else max_level
    pred = torch.log2(grid.d_std / distances.clamp_min(1e-12)) / math.log2(grid.fork) + extra_level
    return torch.round(pred).clamp(0, max_level).long()


def visibility_fraction(positions: Tensor, levels: Tensor, camera_centers: Tensor, grid: OctreeGrid,
                        chunk_elements: int = 1 << 24) -> Tensor:
    """Fraction of cameras from which each anchor's level is LOD-visible (no eps): [N] (Octree-GS's
    weed-out of anchors no training camera would draw).

    positions [N,3], levels [N], camera_centers [C,3]. Chunked over anchors so N x C never
    materialises at once.
    """
    out = positions.new_empty(positions.shape[0])
    rows = max(1, chunk_elements // max(1, camera_centers.shape[0]))
    for start in range(0, positions.shape[0], rows):
        dist = torch.cdist(positions[start:start + rows], camera_centers.to(positions))  # [n, C]
        visible = levels[start:start + rows, None] <= lod_levels_from_distance(dist, grid)
        out[start:start + rows] = visible.float().mean(1)
    return out


def enclosing_cube(points: Tensor, extend: float) -> tuple[Tensor, float]:
    """(origin [3], edge) of an axis-aligned cube centred on the points' box, ``extend`` x its longest
    side. The base method multiplies the scalar coordinate min / max by 1.1, which shrinks the region
    when the minimum is positive and can cut points off; this cube always encloses every point.
    """
    lo, hi = points.min(0).values, points.max(0).values
    edge = float((hi - lo).max()) * extend
    edge = edge if edge > 0 else 1.0  # a single point: any cube around it works
    return (lo + hi) / 2 - edge / 2, edge


def voxelize(points: Tensor, grid: OctreeGrid) -> tuple[Tensor, Tensor]:
    """Unique grid points of every level: points [P,3] -> (positions [N,3], levels [N] long).

    One ``unique`` per level over ``round((P - o) / v_l)``; levels are not de-duplicated against each
    other (a coarse anchor and a fine anchor may coincide, as in the base method).
    """
    positions, levels = [], []
    for level in range(grid.num_levels):  # <= ~12 levels; each pass is fully vectorised
        level_ids = torch.full((points.shape[0],), level, dtype=torch.long, device=points.device)
        cells = torch.unique(grid.grid_index(points, level_ids), dim=0)
        cell_levels = torch.full((cells.shape[0],), level, dtype=torch.long, device=points.device)
        positions.append(grid.grid_position(cells, cell_levels, points.dtype))
        levels.append(cell_levels)
    return torch.cat(positions), torch.cat(levels)


@dataclass
class OctreeBuildConfig:
    """How the anchor octree is built from the sparse points and the training cameras (Octree-GS)."""

    fork: int = 2
    """Branching factor b per axis (2 = octree)."""
    num_levels: int = -1
    """Number of levels; -1 = round(log_b(dist_max / dist_min)) + 1 from the camera distances."""
    init_level: int = -1
    """Last level active at the start of the progressive schedule; -1 = num_levels // 2."""
    dist_ratio: float = 0.999
    """Quantile that makes the camera-distance range robust to outliers."""
    default_voxel_size: float = -1.0
    """Target voxel size near the middle level (the base method's ``default_voxel_size``, scene units);
    -1 = the median nearest-neighbour distance of the points (Scaffold-GS's adaptive rule)."""
    cube_extend: float = 1.1
    """The enclosing cube is this factor x the points' longest box side."""
    visible_threshold: float = 0.01
    """Weed-out: keep anchors LOD-visible from more than this fraction of the training cameras;
    negative = the mean visibility."""
    max_points: int = MAX_SEED_POINTS
    """Sparse points beyond this are subsampled evenly (memory bound for the per-level unique)."""


def build_octree(points: Tensor, camera_centers: Tensor, config: OctreeBuildConfig,
                 distances: tuple[float, float] | None = None) -> tuple[Tensor, Tensor, OctreeGrid]:
    """Anchors of the octree: points [P,3], camera_centers [C,3] -> (positions [N,3], levels [N], grid).
    ``distances``: the ``distance_range`` of these points and cameras when already measured."""
    if points.dim() != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise HicoError(f"field: sparse points must be a non-empty [P, 3] array, got {list(points.shape)}")
    if camera_centers.shape[0] == 0:
        raise HicoError("field: at least one training camera is needed to build the octree")
    if not torch.isfinite(points).all():
        raise HicoError("field: sparse points contain NaN or Inf coordinates")
    points = anchor_seed_points(points, config.max_points)
    fork = config.fork
    dist_min, dist_max = distances or distance_range(points, camera_centers.float(), config.dist_ratio)
    num_levels = config.num_levels if config.num_levels > 0 else level_count(dist_min, dist_max, fork)
    init_level = config.init_level if config.init_level >= 0 else num_levels // 2
    init_level = min(init_level, num_levels - 1)

    origin, cube_size = enclosing_cube(points, config.cube_extend)
    target = config.default_voxel_size
    if target <= 0:
        spacing = knn(points.double().numpy(), 1)[0][:, 0]  # [P] (empty for a single point)
        target = float(torch.from_numpy(spacing).median()) if spacing.size else 0.0
        target = target if target > 0 else cube_size / 1024
    base_layer = int(round(math.log2(cube_size / target))) - num_levels // 2 + 1
    grid = OctreeGrid(origin=tuple(float(x) for x in origin), cube_size=cube_size,
                      voxel_size=cube_size / float(fork) ** base_layer, num_levels=num_levels, fork=fork,
                      d_std=dist_max, init_level=init_level)

    positions, levels = voxelize(points, grid)
    visibility = visibility_fraction(positions, levels, camera_centers.float(), grid)
    threshold = config.visible_threshold if config.visible_threshold >= 0 else float(visibility.mean())
    keep = visibility > threshold
    if not keep.any():
        raise HicoError(
            f"field: no anchor is visible from more than {threshold:.3g} of the training cameras; "
            "lower field.octree.visible_threshold or check the camera poses")
    return positions[keep], levels[keep], grid
