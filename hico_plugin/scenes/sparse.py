"""SfM-like sparse points: features on textured surfaces seen by at least two cameras."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

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


class FeatureSampler:
    """Sample ~``count`` points as SfM would, one view at a time, holding one image and a chunk of depth maps.

    ``propose`` as each view is rendered, ``finish`` once all are; viewmats: [C, 4, 4]. Pixels are proposed in
    proportion to image gradient magnitude (none where the 1 px-blurred grey gradient is below ``min_gradient``
    levels per pixel) and kept when another view sees their surface point unoccluded; tracks list up to
    ``max_track`` views (proposer first); keypoints get 0.5 px noise, positions ``position_noise`` x distance
    noise."""

    def __init__(self, viewmats: np.ndarray, K: np.ndarray, count: int, position_noise: float, seed: int,
                 max_track: int = 12, min_gradient: float = 0.0, chunk_elements: int = 1 << 18):
        self.viewmats, self.K, self.count = viewmats, K, count
        self.position_noise, self.max_track, self.min_gradient = position_noise, max_track, min_gradient
        # per chunk of views in finish: (view, point) pairs plus depth pixels, (view, point) draws
        self.chunk_elements = chunk_elements
        self.pixels = 0  # of a depth map, known from the first proposal
        self.rng = np.random.default_rng([seed, 5])
        self.per_view = int(np.ceil(2.0 * count / len(viewmats)))
        self.sources: list[np.ndarray] = []
        self.points: list[np.ndarray] = []

    def propose(self, view: int, image: np.ndarray, depth: np.ndarray) -> None:
        """Proposals of ``view`` (called in view order): image [H, W, 3] uint8, depth [H, W] camera z
        (0 = none)."""
        H, W = depth.shape
        self.pixels = H * W
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32)
        strength = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1)).ravel()
        blurred = cv2.GaussianBlur(grey, (0, 0), 1.0)
        # a 3x3 Sobel answers a ramp of slope s with 8 s
        contrast = np.hypot(cv2.Sobel(blurred, cv2.CV_32F, 1, 0), cv2.Sobel(blurred, cv2.CV_32F, 0, 1)).ravel() / 8
        strength = strength * (depth.ravel() > 0) * (contrast >= self.min_gradient)
        total = strength.sum()
        if total <= 0:
            return
        take = min(self.per_view, int((strength > 0).sum()))
        flat = self.rng.choice(H * W, size=take, replace=False, p=strength / total)
        self.sources.append(np.full(take, view))
        self.points.append(backproject(depth, self.viewmats[view], self.K, np.stack([flat % W, flat // W], 1)))

    def finish(self, depths_of: Callable[[np.ndarray], np.ndarray],
               image_of: Callable[[int], np.ndarray]) -> SparsePoints:
        """The points, with ``depths_of(views [n])`` -> depth maps [n, H, W] and ``image_of(view)`` ->
        image [H, W, 3] uint8 of the views already proposed from."""
        rng, viewmats, C = self.rng, self.viewmats, len(self.viewmats)
        source = np.concatenate(self.sources)
        true_xyz = np.concatenate(self.points)
        # (view, point) pairs where the view sees the point (its source always does), view-major
        obs_view, obs_point, obs_uv = self._observations(source, true_xyz, depths_of)
        keep = np.flatnonzero(np.bincount(obs_point, minlength=len(source)) >= 2)
        if len(keep) > self.count:
            keep = np.sort(rng.choice(keep, size=self.count, replace=False))
        kept = np.isin(obs_point, keep)
        obs_view, obs_point, obs_uv = obs_view[kept], np.searchsorted(keep, obs_point[kept]), obs_uv[kept]
        true_xyz, source = true_xyz[keep], source[keep]
        pixel_rgb = self._source_colours(obs_view, obs_point, obs_uv, source, image_of)

        distance = np.linalg.norm(true_xyz - _centers(viewmats)[source], axis=1)
        xyz = true_xyz + rng.normal(0.0, 1.0, true_xyz.shape) * (self.position_noise * distance)[:, None]
        # a random priority per (view, point), the source's raised above the rest: a point's track is its
        # max_track highest observing views; drawn a few views at a time, the numbers one [C, N] draw gives
        priority = np.empty(len(obs_view))
        rows = max(1, self.chunk_elements // max(1, len(keep)))
        bounds = np.searchsorted(obs_view, np.arange(0, C + rows, rows))
        for lo, first, last in zip(range(0, C, rows), bounds[:-1], bounds[1:]):
            draws = rng.random((min(rows, C - lo), len(keep)))
            priority[first:last] = draws[obs_view[first:last] - lo, obs_point[first:last]]
        priority += 2.0 * (obs_view == source[obs_point])
        order = np.lexsort((-priority, obs_point))  # by point, then by priority, highest first
        starts = np.searchsorted(obs_point[order], obs_point[order], side="left")
        order = order[np.arange(len(order)) - starts < self.max_track]
        obs_point, obs_image = obs_point[order], obs_view[order]
        obs_pixel = obs_uv[order] + rng.normal(0.0, 0.5, (len(obs_point), 2))
        return SparsePoints(xyz=xyz, rgb=pixel_rgb.astype(np.uint8), obs_point=obs_point, obs_image=obs_image,
                            obs_pixel=obs_pixel)

    def _observations(self, source, true_xyz, depths_of):
        """Views [M], points [M] and pixel coords [M, 2] of every unoccluded sighting, view-major."""
        C = len(self.viewmats)
        step = max(1, self.chunk_elements // (len(source) + self.pixels))
        views, points, uvs = [], [], []
        for lo in range(0, C, step):
            chunk = np.arange(lo, min(C, lo + step))
            seen, uv = visibility(true_xyz, depths_of(chunk), self.viewmats[chunk], self.K)
            seen |= chunk[:, None] == source[None]
            row, point = np.nonzero(seen)
            views.append(chunk[row])
            points.append(point)
            uvs.append(uv[row, point])
        return np.concatenate(views), np.concatenate(points), np.concatenate(uvs)

    @staticmethod
    def _source_colours(obs_view, obs_point, obs_uv, source, image_of) -> np.ndarray:
        """[N, 3] each point's colour in its source view, at the pixel it projects to there."""
        own = obs_view == source[obs_point]
        pixels, point = obs_uv[own], obs_point[own]
        rgb = np.zeros((len(source), 3), np.uint8)
        for view in np.unique(source):
            image = image_of(int(view))
            H, W = image.shape[:2]
            mine = source[point] == view
            px = np.clip(np.floor(pixels[mine]).astype(np.int64), 0, [W - 1, H - 1])
            rgb[point[mine]] = image[px[:, 1], px[:, 0]]
        return rgb


def _centers(viewmats: np.ndarray) -> np.ndarray:
    return -np.einsum("cji,cj->ci", viewmats[:, :3, :3], viewmats[:, :3, 3])
