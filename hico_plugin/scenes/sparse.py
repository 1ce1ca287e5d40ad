"""SfM-like sparse points: features on textured surfaces seen by at least two cameras."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class SparsePoints:
    """Points with colours and tracks, as an SfM reconstruction would hold them."""

    xyz: np.ndarray  # [N, 3] float64 world (with position noise)
    rgb: np.ndarray  # [N, 3] uint8, sampled from the source image
    # observations, grouped by point (the proposing view first within each point):
    obs_point: np.ndarray  # [M] point index
    obs_image: np.ndarray  # [M] view index
    obs_pixel: np.ndarray  # [M, 2] observed pixel (COLMAP: top-left pixel centre at (0.5, 0.5)),
    # with keypoint noise


def backproject(depth: np.ndarray, viewmat: np.ndarray, K: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """World points [n, 3] of integer ``pixels`` [n, 2] (col, row) with camera-z ``depth`` [H, W]."""
    z = depth[pixels[:, 1], pixels[:, 0]]
    x = (pixels[:, 0] + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (pixels[:, 1] + 0.5 - K[1, 2]) / K[1, 1] * z
    cam = np.stack([x, y, z], 1)
    return (cam - viewmat[:3, 3]) @ viewmat[:3, :3]


def project(points: np.ndarray, viewmats: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coords [C, N, 2] and camera z [C, N] of world points [N, 3] in every view."""
    cam = np.einsum("cij,nj->cni", viewmats[:, :3, :3], points) + viewmats[:, None, :3, 3]
    z = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([K[0, 0] * cam[..., 0] / z + K[0, 2], K[1, 1] * cam[..., 1] / z + K[1, 2]], -1)
    return uv, z


def visibility(points: np.ndarray, depths: np.ndarray, viewmats: np.ndarray, K: np.ndarray,
               tolerance: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Which views see each point unoccluded: a [C, N] bool mask (in the image, in front, and
    within ``tolerance`` x z of that view's depth map) and the pixel coords [C, N, 2]."""
    C, H, W = depths.shape
    uv, z = project(points, viewmats, K)
    col = np.floor(np.nan_to_num(uv[..., 0], nan=-1.0)).astype(np.int64)
    row = np.floor(np.nan_to_num(uv[..., 1], nan=-1.0)).astype(np.int64)
    inside = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
    surface = depths[np.arange(C)[:, None], np.clip(row, 0, H - 1), np.clip(col, 0, W - 1)]
    return inside & (surface > 0) & (np.abs(surface - z) <= tolerance * z), uv


def feature_points(
    images: np.ndarray,
    depths: np.ndarray,
    viewmats: np.ndarray,
    K: np.ndarray,
    count: int,
    position_noise: float,
    seed: int,
    max_track: int = 12,
    min_gradient: float = 0.0,
) -> SparsePoints:
    """Sample ~``count`` points like SfM would find them.

    images: [C, H, W, 3] uint8, depths: [C, H, W] camera z (0 = none), viewmats: [C, 4, 4].
    Each view proposes pixels with probability proportional to image gradient magnitude (features
    live on texture and edges, and none where the 1 px-blurred grey gradient is below ``min_gradient``
    levels per pixel); a proposal is kept when at least one other view sees its surface
    point unoccluded. Tracks list up to ``max_track`` observing views (the proposing view first);
    keypoints get 0.5 px noise and positions ``position_noise`` x distance noise."""
    rng = np.random.default_rng([seed, 5])
    C, H, W = depths.shape
    per_view = int(np.ceil(2.0 * count / C))
    sources, points = [], []
    for view in range(C):  # one proposal batch per camera
        grey = cv2.cvtColor(images[view], cv2.COLOR_RGB2GRAY).astype(np.float32)
        strength = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1)).ravel()
        blurred = cv2.GaussianBlur(grey, (0, 0), 1.0)
        # a 3x3 Sobel answers a ramp of slope s with 8 s
        contrast = np.hypot(cv2.Sobel(blurred, cv2.CV_32F, 1, 0), cv2.Sobel(blurred, cv2.CV_32F, 0, 1)).ravel() / 8
        strength = strength * (depths[view].ravel() > 0) * (contrast >= min_gradient)
        total = strength.sum()
        if total <= 0:
            continue
        take = min(per_view, int((strength > 0).sum()))
        flat = rng.choice(H * W, size=take, replace=False, p=strength / total)
        sources.append(np.full(take, view))
        points.append(backproject(depths[view], viewmats[view], K, np.stack([flat % W, flat // W], 1)))
    source = np.concatenate(sources)
    true_xyz = np.concatenate(points)
    seen, uv = visibility(true_xyz, depths, viewmats, K)
    seen[source, np.arange(len(source))] = True
    keep = np.flatnonzero(seen.sum(0) >= 2)
    if len(keep) > count:
        keep = np.sort(rng.choice(keep, size=count, replace=False))
    true_xyz, source, seen, uv = true_xyz[keep], source[keep], seen[:, keep], uv[:, keep]
    src_pixels = np.floor(uv[source, np.arange(len(keep))]).astype(np.int64)
    src_pixels = np.clip(src_pixels, 0, [W - 1, H - 1])
    pixel_rgb = images[source, src_pixels[:, 1], src_pixels[:, 0]]

    distance = np.linalg.norm(true_xyz - _centers(viewmats)[source], axis=1)
    xyz = true_xyz + rng.normal(0.0, 1.0, true_xyz.shape) * (position_noise * distance)[:, None]
    priority = rng.random(seen.shape) + 2.0 * (np.arange(C)[:, None] == source[None])  # source first
    priority = np.where(seen, priority, -1.0)
    ranked = np.argsort(-priority, axis=0)[:max_track].T  # [N, T] best views per point
    point = np.broadcast_to(np.arange(len(keep))[:, None], ranked.shape)
    observed = seen[ranked, point]  # [N, T]; a point seen by fewer than T views has padding
    obs_point, obs_image = point[observed], ranked[observed]
    obs_pixel = uv[obs_image, obs_point] + rng.normal(0.0, 0.5, (len(obs_point), 2))
    return SparsePoints(xyz=xyz, rgb=pixel_rgb.astype(np.uint8), obs_point=obs_point, obs_image=obs_image,
                        obs_pixel=obs_pixel)


def _centers(viewmats: np.ndarray) -> np.ndarray:
    return -np.einsum("cji,cj->ci", viewmats[:, :3, :3], viewmats[:, :3, 3])
