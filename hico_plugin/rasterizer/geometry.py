"""Geometry channels: per-Gaussian normals / plane distances, and the per-pixel maps built from them.

Pixel convention (one for the whole package): pixel (u, v) has its centre at (u + 0.5, v + 0.5),
so its ray is r = ((u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy, 1) -- the same centres the rasterizer
evaluates Gaussians at. (The CityGS-X / PGSR CUDA code uses integer u, v, half a pixel off from its
own rasterizer; we keep the two consistent instead.)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from hico_plugin.rasterizer.projection import quat_to_rotmat

ALPHA_EPS = 1e-6  # below this accumulated alpha a pixel counts as empty (any drawn pixel has >= 1/255)
DENOM_EPS = 1e-6  # plane depth is undefined where the composited normal is (nearly) parallel to the ray
NORMAL_EPS = 1e-8  # a rendered or depth normal shorter than this is "undefined" (DNGC skips it)


def gaussian_normals(quats: Tensor, scales: Tensor, means_cam: Tensor, viewmats: Tensor
                     ) -> tuple[Tensor, Tensor]:
    """Camera-space normals and plane distances of Gaussians.

    quats [N,4], scales [N,3], means_cam [C,N,3], viewmats [C,4,4] -> normals [C,N,3], distances [C,N].
    The normal is the shortest axis, flipped to face the camera (n . mu_cam <= 0); the distance is
    |n . mu_cam|, the distance of the camera centre from the Gaussian's tangent plane.
    """
    rot = quat_to_rotmat(quats)  # [N,3,3], columns are the axes
    shortest = scales.detach().argmin(-1)  # [N]
    axis = torch.gather(rot, 2, shortest[:, None, None].expand(-1, 3, 1)).squeeze(-1)  # [N,3]
    normals = torch.einsum("cij,nj->cni", viewmats[:, :3, :3], axis)
    facing = (normals * means_cam).sum(-1, keepdim=True)
    normals = torch.where(facing > 0, -normals, normals)
    distances = (normals * means_cam).sum(-1).abs()
    return normals, distances


def pixel_rays(Ks: Tensor, width: int, height: int) -> Tensor:
    """Rays through pixel centres, z = 1: Ks [C,3,3] -> [C,H,W,3]."""
    u = torch.arange(width, dtype=Ks.dtype, device=Ks.device) + 0.5
    v = torch.arange(height, dtype=Ks.dtype, device=Ks.device) + 0.5
    fx, fy = Ks[:, 0, 0, None, None], Ks[:, 1, 1, None, None]
    cx, cy = Ks[:, 0, 2, None, None], Ks[:, 1, 2, None, None]
    rx = ((u[None, None, :] - cx) / fx).expand(-1, height, -1)
    ry = ((v[None, :, None] - cy) / fy).expand(-1, -1, width)
    return torch.stack([rx, ry, torch.ones_like(rx)], -1)


def safe_divide(num: Tensor, den: Tensor, valid: Tensor) -> Tensor:
    """num / den where valid, else 0 -- with finite gradients everywhere."""
    return torch.where(valid, num / torch.where(valid, den, torch.ones_like(den)), torch.zeros_like(num))


def expected_depth(z_sum: Tensor, alpha: Tensor) -> Tensor:
    """Composited camera z [C,H,W,1] normalised by alpha; 0 where nothing is drawn."""
    return safe_divide(z_sum, alpha, alpha > ALPHA_EPS)


def plane_depth(normal: Tensor, distance: Tensor, alpha: Tensor, Ks: Tensor) -> Tensor:
    """PGSR plane depth distance / -(normal . ray): normal [C,H,W,3], distance/alpha [C,H,W,1].

    The ratio cancels the alpha weighting; 0 where nothing is drawn or the plane is edge-on.
    """
    rays = pixel_rays(Ks, normal.shape[2], normal.shape[1])
    denom = -(normal * rays).sum(-1, keepdim=True)
    return safe_divide(distance, denom, (alpha > ALPHA_EPS) & (denom > DENOM_EPS * alpha))


def depth_to_normal(depth: Tensor, Ks: Tensor) -> Tensor:
    """Normals of a depth map by central differences: depth [C,H,W,1], Ks [C,3,3] -> [C,H,W,3].

    Each pixel is back-projected to P = depth * ray; n = normalise((P[u+1]-P[u-1]) x (P[v-1]-P[v+1])),
    which faces the camera (-z on a fronto-parallel plane), flipped if needed so that n . P <= 0.
    Zero on the 1-px border, where any of the four neighbours has no depth, and where the cross
    product vanishes.
    """
    num_cams, height, width, _ = depth.shape
    if height < 3 or width < 3:
        return depth.new_zeros(num_cams, height, width, 3)
    points = depth * pixel_rays(Ks, width, height)  # [C,H,W,3]
    along_u = points[:, 1:-1, 2:] - points[:, 1:-1, :-2]
    along_v = points[:, :-2, 1:-1] - points[:, 2:, 1:-1]
    cross = torch.linalg.cross(along_u, along_v, dim=-1)
    has_depth = depth[..., 0] > 0
    neighbours = (has_depth[:, 1:-1, 2:] & has_depth[:, 1:-1, :-2]
                  & has_depth[:, :-2, 1:-1] & has_depth[:, 2:, 1:-1])
    length = cross.norm(dim=-1, keepdim=True)
    valid = neighbours[..., None] & (length > 1e-12 * depth[:, 1:-1, 1:-1].detach().square())
    unit = safe_divide(cross, length, valid)
    centre = points[:, 1:-1, 1:-1]
    unit = torch.where((unit * centre).sum(-1, keepdim=True) > 0, -unit, unit)
    return F.pad(unit, (0, 0, 1, 1, 1, 1))
