"""Render outputs -> uint8 pictures: colormaps, percentile depth normalisation, normals as RGB.

Pure functions of a RenderOutputs-style mapping (torch or numpy, any device): rgb [H, W, 3] in [0, 1]; depth /
plane_depth / distance / alpha / level [H, W, 1]; normal (n_r) / depth_normal (n_d) [H, W, 3]. Uncovered pixels
(alpha <= 0.5, or non-finite values) are black in scalar and normal views, so the colormap spans the surface only.
"""

from __future__ import annotations

from typing import Any, Mapping

import cv2
import numpy as np

from hico_plugin.visualization.options import RenderOptions

_CV2_COLORMAPS = {
    "turbo": cv2.COLORMAP_TURBO,
    "viridis": cv2.COLORMAP_VIRIDIS,
    "inferno": cv2.COLORMAP_INFERNO,
    "magma": cv2.COLORMAP_MAGMA,
    "jet": cv2.COLORMAP_JET,
}
COVERED_ALPHA = 0.5


def to_numpy(values: Any) -> np.ndarray:
    """A float32 numpy copy of a torch tensor (any device, detached) or array-like."""
    if hasattr(values, "detach"):
        values = values.detach().float().cpu().numpy()
    return np.asarray(values, dtype=np.float32)


def apply_colormap(values: np.ndarray, name: str = "turbo") -> np.ndarray:
    """values: [...] in [0, 1] (clipped; NaN -> black) -> uint8 [..., 3] RGB."""
    values = np.asarray(values, dtype=np.float32)
    finite = np.isfinite(values)
    levels = (np.clip(np.where(finite, values, 0.0), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if name == "gray":
        colors = np.repeat(levels[..., None], 3, axis=-1)
    elif name in _CV2_COLORMAPS:
        # applyColorMap wants a 2D image and answers BGR.
        flat = levels.reshape(-1, 1)
        colors = cv2.applyColorMap(flat, _CV2_COLORMAPS[name])[:, 0, ::-1].reshape(*levels.shape, 3)
    else:
        raise ValueError(f"colormap: '{name}' is not one of gray, {', '.join(_CV2_COLORMAPS)}")
    return np.where(finite[..., None], colors, 0).astype(np.uint8)


def normalize_percentile(values: np.ndarray, valid: np.ndarray, percentiles: tuple[float, float] = (1.0, 99.0)) -> np.ndarray:
    """values: [H, W], valid: [H, W] bool -> [H, W] in [0, 1], NaN where not valid.

    The low / high percentiles of the valid values map to 0 / 1, so a few far (sky) or near
    (floater) pixels do not flatten the rest of the picture.
    """
    valid = valid & np.isfinite(values)
    if not valid.any():
        return np.full(values.shape, np.nan, dtype=np.float32)
    low, high = np.percentile(values[valid], percentiles)
    scaled = (values - low) / max(float(high - low), 1e-12)
    return np.where(valid, np.clip(scaled, 0.0, 1.0), np.nan).astype(np.float32)


def normals_to_rgb(normals: Any) -> np.ndarray:
    """normals: [H, W, 3] (any length; zero / non-finite -> black) -> uint8 [H, W, 3], (n + 1) / 2."""
    normals = to_numpy(normals)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    usable = np.isfinite(length) & (length > 1e-8)
    unit = np.where(usable, normals / np.where(usable, length, 1.0), 0.0)
    rgb = ((unit + 1.0) * 0.5 * 255.0 + 0.5).clip(0, 255).astype(np.uint8)
    return np.where(usable, rgb, 0).astype(np.uint8)


def normal_disagreement_degrees(normal: Any, depth_normal: Any) -> np.ndarray:
    """Angle between the rendered normal n_r and the depth normal n_d, in degrees.

    normal, depth_normal: [H, W, 3] -> [H, W, 1] in [0, 180]; NaN where either is zero / non-finite.
    """
    n_r, n_d = to_numpy(normal), to_numpy(depth_normal)
    len_r = np.linalg.norm(n_r, axis=-1, keepdims=True)
    len_d = np.linalg.norm(n_d, axis=-1, keepdims=True)
    usable = (len_r > 1e-8) & (len_d > 1e-8) & np.isfinite(len_r) & np.isfinite(len_d)
    cosine = np.sum(n_r * n_d, axis=-1, keepdims=True) / np.where(usable, len_r * len_d, 1.0)
    degrees = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    return np.where(usable, degrees, np.nan).astype(np.float32)


def level_colors(levels: Any, num_levels: int, colormap: str = "turbo") -> np.ndarray:
    """levels: [...] octree levels (fractional allowed) -> uint8 [..., 3]; level 0 and
    num_levels - 1 sit at the two ends of the colormap (anchors and the level map share colours)."""
    levels = to_numpy(levels)
    return apply_colormap(levels / max(num_levels - 1, 1), colormap)


def covered_mask(outputs: Mapping[str, Any], shape: tuple[int, int]) -> np.ndarray:
    """[H, W] bool: pixels the render covers (alpha > 0.5), all True without an alpha output."""
    if outputs.get("alpha") is None:
        return np.ones(shape, dtype=bool)
    return to_numpy(outputs["alpha"])[..., 0] > COVERED_ALPHA


def _require(outputs: Mapping[str, Any], name: str) -> np.ndarray:
    if outputs.get(name) is None:
        raise KeyError(f"render outputs: '{name}' is missing (have {sorted(k for k, v in outputs.items() if v is not None)})")
    return to_numpy(outputs[name])


def visualize(outputs: Mapping[str, Any], options: RenderOptions) -> np.ndarray:
    """The picture of ``options.output``: uint8 [H, W, 3] RGB."""
    name = options.output
    if name == "rgb":
        rgb = _require(outputs, "rgb")[..., :3]
        return (np.clip(np.nan_to_num(rgb), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if name == "alpha":
        return apply_colormap(_require(outputs, "alpha")[..., 0], options.colormap)
    if name in ("normal", "depth_normal"):
        normals = _require(outputs, name)
        covered = covered_mask(outputs, normals.shape[:2])
        return np.where(covered[..., None], normals_to_rgb(normals), 0).astype(np.uint8)
    if name == "normal_disagreement":
        degrees = normal_disagreement_degrees(_require(outputs, "normal"), _require(outputs, "depth_normal"))[..., 0]
        covered = covered_mask(outputs, degrees.shape)
        scaled = np.where(covered, degrees / options.max_disagreement_degrees, np.nan)
        return apply_colormap(scaled, options.colormap)
    if name == "level":
        levels = _require(outputs, "level")[..., 0]
        covered = covered_mask(outputs, levels.shape)
        num_levels = options.num_levels or int(np.nanmax(levels, initial=0.0)) + 1
        return np.where(covered[..., None], level_colors(levels, num_levels, options.colormap), 0).astype(np.uint8)
    # depth, plane_depth, distance: scalar fields of unknown range.
    values = _require(outputs, name)[..., 0]
    covered = covered_mask(outputs, values.shape)
    return apply_colormap(normalize_percentile(values, covered, options.normalize_percentiles), options.colormap)
