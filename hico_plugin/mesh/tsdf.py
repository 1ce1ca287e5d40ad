"""TSDF fusion of depth + colour maps into a triangle mesh (Open3D's hashed voxel-block TSDF), and the
multi-view depth consistency filter applied before it.

Depths are camera z (OpenCV axes) in the cameras' world units; 0 (or non-finite) = no surface.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from hico_plugin.cameras import Cameras
from hico_plugin.errors import HicoError
from hico_plugin.mesh.mesh import TriangleMesh


def import_open3d():
    """The open3d module, or a HicoError saying how to install the optional extra."""
    try:
        import open3d
    except ImportError as error:
        # Installed but unloadable is usually a missing system library (the CPU wheel links libusb-1.0).
        raise HicoError(f"mesh extraction needs Open3D: pip install 'hico_plugin[mesh]' (open3d>=0.18); "
                        f"importing it failed with: {error}") from None
    return open3d


def _to_pixels(in_camera: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """in_camera: [..., P, 3] camera-space points; K: [..., 3, 3] -> ([..., P, 2] pixels, [..., P] z)."""
    z = in_camera[..., 2]
    safe_z = torch.where(z.abs() > 1e-12, z, torch.ones_like(z))
    focal, principal = torch.diagonal(K[..., :2, :2], dim1=-2, dim2=-1), K[..., :2, 2]
    return in_camera[..., :2] / safe_z[..., None] * focal[..., None, :] + principal[..., None, :], z


def _from_pixels(pixels: Tensor, depth: Tensor, K: Tensor) -> Tensor:
    """pixels: [..., P, 2], depth: [..., P] camera z, K: [..., 3, 3] -> [..., P, 3] camera-space points."""
    focal, principal = torch.diagonal(K[..., :2, :2], dim1=-2, dim2=-1), K[..., :2, 2]
    xy = (pixels - principal[..., None, :]) / focal[..., None, :]
    return torch.cat([xy, torch.ones_like(depth)[..., None]], dim=-1) * depth[..., None]


def nearest_views(cameras: Cameras, num_neighbours: int) -> Tensor:
    """[C, k] ids of each camera's ``k`` nearest other cameras by centre distance (k <= C - 1)."""
    centres = cameras.centers.to(torch.float64)
    distances = torch.cdist(centres, centres)
    distances.fill_diagonal_(math.inf)
    k = min(num_neighbours, len(cameras) - 1)
    return distances.topk(k, dim=1, largest=False).indices


def multiview_depth_filter(depths: Tensor, cameras: Cameras, num_neighbours: int = 8, min_consistent: int = 2,
                           max_reprojection_px: float = 1.0, max_relative_depth: float = 0.01) -> Tensor:
    """Which pixels have a depth that neighbour views confirm (geometric consistency as in MVS fusion).

    depths: [C, H, W] camera z (0 = none) for ``cameras`` (all of size W x H); returns [C, H, W] bool. A pixel
    agrees with neighbour j when its point lands inside j on a valid depth whose own point, projected back, is
    within ``max_reprojection_px`` pixels of the start and ``max_relative_depth`` of its depth; it is kept when at
    least ``min_consistent`` of its ``num_neighbours`` nearest views agree.
    """
    num_views, height, width = depths.shape
    if num_views < 2:
        raise HicoError(f"depth filter: needs at least 2 views, got {num_views}; turn the filter off")
    if bool((cameras.widths != width).any() or (cameras.heights != height).any()):
        raise HicoError("depth filter: every view must have the depth maps' size "
                        f"{width}x{height}; cameras have other sizes")
    depths = depths.to(torch.float64)
    viewmats, Ks = cameras.viewmats.to(depths), cameras.Ks.to(depths)
    valid = torch.isfinite(depths) & (depths > 0)
    depths = torch.where(valid, depths, torch.zeros_like(depths))
    neighbours = nearest_views(cameras, num_neighbours)
    rots, trans = viewmats[:, :3, :3], viewmats[:, :3, 3]
    ys, xs = torch.meshgrid(torch.arange(height, dtype=depths.dtype) + 0.5,
                            torch.arange(width, dtype=depths.dtype) + 0.5, indexing="ij")
    start = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)  # [P, 2] pixel centres of every view
    keep = torch.zeros_like(valid)
    for i in range(num_views):  # views, not pixels: each step is vectorised over all pixels and neighbours
        ids = neighbours[i]
        world = (_from_pixels(start, depths[i].reshape(-1), Ks[i]) - trans[i]) @ rots[i]  # R^T (x - t): [P, 3]
        pixels_j, z_j = _to_pixels(torch.einsum("kab,pb->kpa", rots[ids], world) + trans[ids, None], Ks[ids])
        cols, rows = pixels_j[..., 0].floor().long(), pixels_j[..., 1].floor().long()  # [k, P]
        inside = (z_j > 0) & (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
        cols, rows = cols.clamp(0, width - 1), rows.clamp(0, height - 1)
        depth_j = depths[ids[:, None], rows, cols]
        # The neighbour's own surface point at that pixel, back in world and then in view i.
        hit_j = _from_pixels(torch.stack([cols, rows], dim=-1) + 0.5, depth_j, Ks[ids])
        world_j = torch.einsum("kpa,kab->kpb", hit_j - trans[ids, None], rots[ids])
        back, back_z = _to_pixels(world_j @ rots[i].T + trans[i], Ks[i])
        error_px = (back - start).norm(dim=-1)
        depth_i = depths[i].reshape(1, -1)
        relative = (back_z - depth_i).abs() / depth_i.clamp_min(1e-12)
        agree = inside & (depth_j > 0) & (error_px < max_reprojection_px) & (relative < max_relative_depth)
        keep[i] = valid[i] & (agree.sum(dim=0) >= min_consistent).reshape(height, width)
    return keep


def fuse_tsdf(depths: Sequence[Tensor], colors: Sequence[Tensor], cameras: Cameras, voxel_size: float,
              sdf_trunc: float, max_depth: float, min_weight: float = 1.0) -> TriangleMesh:
    """Fuse depth maps into a sparse (hashed voxel-block) TSDF volume and extract its marching-cubes
    mesh (same frame as ``cameras``; no cleaning). Voxels seen by fewer than ``min_weight`` views are
    left out of the surface.

    depths: C x [H, W] camera z (0 / non-finite = no surface; > ``max_depth`` is ignored);
    colors: C x [H, W, 3] uint8; voxel_size, sdf_trunc, max_depth in the cameras' world units.
    """
    for name, value in (("voxel_size", voxel_size), ("sdf_trunc", sdf_trunc), ("max_depth", max_depth)):
        if not (value > 0 and math.isfinite(value)):
            raise HicoError(f"mesh: {name} must be a positive finite distance, got {value}")
    if not (len(depths) == len(colors) == len(cameras)) or len(cameras) == 0:
        raise HicoError(f"mesh: got {len(depths)} depth maps and {len(colors)} colour maps for {len(cameras)} cameras")
    frames = []
    for i, (depth, color) in enumerate(zip(depths, colors)):
        camera = cameras[i]
        if depth.shape != (camera.height, camera.width) or color.shape != (camera.height, camera.width, 3):
            raise HicoError(f"mesh: view {i}: expected depth [{camera.height}, {camera.width}] and colour "
                            f"[{camera.height}, {camera.width}, 3], got {tuple(depth.shape)} and {tuple(color.shape)}")
        depth = depth.detach().cpu().float()
        usable = torch.isfinite(depth) & (depth > 0) & (depth <= max_depth)
        frames.append((torch.where(usable, depth, torch.zeros_like(depth)), color, int(usable.sum())))
    if sum(count for _, _, count in frames) == 0:
        raise HicoError(f"mesh: no pixel in any of the {len(cameras)} depth maps has a depth in (0, "
                        f"max_depth={max_depth:.4g}]: the depths are empty or all too far (raise max_depth?)")
    o3d = import_open3d()
    o3c = o3d.core
    # Open3D's hashed voxel-block TSDF, the maintained successor of ScalableTSDFVolume: with Open3D 0.20
    # (CPU and CUDA wheels alike) the legacy volume extracted an empty mesh even for a flat wall in front
    # of the camera. The block map grows as needed.
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=(1, 1, 3), voxel_size=float(voxel_size), block_resolution=8, block_count=50_000,
        device=o3c.Device("CPU:0"))
    trunc_multiplier = float(sdf_trunc) / float(voxel_size)
    for i, (depth, color, count) in enumerate(frames):  # Open3D integrates one frame at a time
        if count == 0:
            continue
        camera = cameras[i]
        K = camera.K.double().cpu().clone()
        K[:2, 2] -= 0.5  # Open3D puts pixel centres at integer coordinates; ours sit at +0.5.
        intrinsic = o3c.Tensor(K.numpy())
        extrinsic = o3c.Tensor(camera.viewmat.double().cpu().numpy())
        depth_image = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth.numpy())))
        color_image = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(
            color.detach().cpu().numpy().astype(np.float32) / 255.0)))
        try:
            blocks = grid.compute_unique_block_coordinates(depth_image, intrinsic, extrinsic, 1.0, float(max_depth),
                                                           trunc_voxel_multiplier=trunc_multiplier)
        except RuntimeError as err:
            if "No block is touched" in str(err):  # too few valid pixels in this view to touch a block
                continue
            raise
        grid.integrate(blocks, depth_image, color_image, intrinsic, intrinsic, extrinsic, 1.0, float(max_depth),
                       trunc_voxel_multiplier=trunc_multiplier)
    if grid.hashmap().size() == 0:
        return TriangleMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    mesh = grid.extract_triangle_mesh(weight_threshold=float(min_weight)).to_legacy()
    vertex_colors = np.asarray(mesh.vertex_colors)
    return TriangleMesh(
        np.asarray(mesh.vertices), np.asarray(mesh.triangles),
        np.clip(np.rint(vertex_colors * 255), 0, 255).astype(np.uint8) if len(vertex_colors) else None)
