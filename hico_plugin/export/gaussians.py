"""Decoded Gaussians and anchors -> PLY vertex rows.

Gaussians use the Inria 3DGS layout (SuperSplat and most splat viewers), ``x y z nx ny nz f_dc_0..2 opacity
scale_0..2 rot_0..3``: colour as the degree-0 SH coefficient ``(rgb - 0.5) / C0``, opacity as its logit, log
scales, unit (w, x, y, z) quaternions. Rows that a viewer cannot draw are dropped and counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from hico_plugin.data.transform import SceneTransform
from hico_plugin.export.camera_paths import rotmat_to_quat
from hico_plugin.rasterizer.geometry import gaussian_normals

SH_C0 = 0.28209479177387814
MIN_OPACITY = 1.0 / 255.0  # below this a Gaussian never changes a pixel (3DGS' alpha cut-off)
_MAX_OPACITY = 1.0 - 1e-7  # keeps the logit finite for opacity 1
INRIA_FIELDS = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


@dataclass
class DroppedRows:
    """How many rows an export kept and why the others were dropped (each row counted once, in the
    order non-finite, zero quaternion, near-transparent)."""

    kept: int
    non_finite: int
    zero_quaternion: int
    transparent: int

    @property
    def dropped(self) -> int:
        return self.non_finite + self.zero_quaternion + self.transparent


def gaussians_to_colmap(means: Tensor, quats: Tensor, scales: Tensor,
                        transform: SceneTransform) -> tuple[Tensor, Tensor, Tensor]:
    """Undo the scene normalisation (rotation, translation, isotropic scale): means [N, 3], quats
    [N, 4] (w, x, y, z, any norm; a zero quaternion stays zero) and scales [N, 3] (linear) in the
    normalised frame -> the same in COLMAP's frame."""
    rotated = _turned(transform.rotation.T, quats)  # normalised -> COLMAP axes
    return transform.points_to_colmap(means), rotated, scales / transform.scale


def gaussians_from_colmap(means: Tensor, quats: Tensor, scales: Tensor,
                          transform: SceneTransform) -> tuple[Tensor, Tensor, Tensor]:
    """``gaussians_to_colmap``'s inverse: means [N, 3], quats [N, 4] (w, x, y, z) and scales [N, 3]
    in COLMAP's frame -> the normalised frame."""
    rotated = _turned(transform.rotation, quats)  # COLMAP -> normalised axes
    return transform.points_from_colmap(means), rotated, scales * transform.scale


def _turned(rotation: Tensor, quats: Tensor) -> Tensor:
    """Quaternions [N, 4] (w, x, y, z) of orientations turned by the rotation matrix [3, 3] (its
    quaternion times each)."""
    w1, x1, y1, z1 = rotmat_to_quat(rotation.to(quats.device, torch.float64)).to(quats.dtype).unbind(-1)
    w2, x2, y2, z2 = quats.unbind(-1)
    return torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)


def rows_to_gaussians(rows: np.ndarray) -> dict[str, Tensor]:
    """Inria-layout rows (a PLY or SPZ read back) -> means [N, 3], quats [N, 4] (w, x, y, z), scales
    [N, 3] linear, opacities [N], colors [N, 3] RGB (float32): what ``inria_vertices`` was given."""
    def column(*names: str) -> Tensor:
        return torch.from_numpy(np.stack([rows[n] for n in names], -1).astype(np.float32))

    return {"means": column("x", "y", "z"), "quats": column("rot_0", "rot_1", "rot_2", "rot_3"),
            "scales": torch.exp(column("scale_0", "scale_1", "scale_2")),
            "opacities": torch.sigmoid(column("opacity")[:, 0]),
            "colors": column("f_dc_0", "f_dc_1", "f_dc_2") * SH_C0 + 0.5}


def facing_normals(means: Tensor, quats: Tensor, scales: Tensor, eye: Tensor) -> Tensor:
    """World normals [N, 3]: each Gaussian's shortest axis, turned towards the point ``eye`` ([3], or
    [N, 3] one per Gaussian) (the rasterizer's normal rule, evaluated in world axes)."""
    identity = torch.eye(4, dtype=means.dtype, device=means.device)[None]
    normals, _ = gaussian_normals(quats, scales, (means - eye)[None], identity)
    return normals[0]


def inria_vertices(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
                   normals: Tensor | None = None) -> tuple[np.ndarray, DroppedRows]:
    """Inria-layout rows of a Gaussian set.

    means [N, 3]; quats [N, 4] (w, x, y, z, any norm); scales [N, 3] linear; opacities [N] in
    [0, 1]; colors [N, 3] RGB in [0, 1]; normals [N, 3] or None (zeros, as 3DGS writes).
    Returns (structured float32 array [M] with ``INRIA_FIELDS``, DroppedRows): a row is dropped when
    any written value is non-finite (NaN / inf input, scale <= 0), its quaternion is zero, or its
    opacity is below 1/255.
    """
    def f64(t: Tensor) -> np.ndarray:
        return t.detach().to("cpu", torch.float64).numpy()

    means, quats, scales, opacities, colors = map(f64, (means, quats, scales, opacities, colors))
    normals = np.zeros_like(means) if normals is None else f64(normals)
    quat_norm = np.linalg.norm(quats, axis=-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        opacity = np.clip(opacities, None, _MAX_OPACITY)
        columns = np.concatenate([
            means, normals, (colors - 0.5) / SH_C0, np.log(opacity / (1.0 - opacity))[:, None],
            np.log(scales), quats / quat_norm], axis=-1)
    inputs = np.concatenate([means, normals, colors, opacities[:, None], quats, scales], axis=-1)
    non_finite = ~(np.isfinite(inputs).all(-1) & (scales > 0).all(-1))
    zero_quat = ~non_finite & ~(quat_norm[:, 0] > 1e-12)
    transparent = ~non_finite & ~zero_quat & (opacities < MIN_OPACITY)
    keep = ~(non_finite | zero_quat | transparent)
    rows = np.empty(int(keep.sum()), dtype=[(name, "<f4") for name in INRIA_FIELDS])
    for i, name in enumerate(INRIA_FIELDS):
        rows[name] = columns[keep, i]
    return rows, DroppedRows(int(keep.sum()), int(non_finite.sum()), int(zero_quat.sum()), int(transparent.sum()))


def anchor_vertices(positions: Tensor, levels: Tensor, features: Tensor,
                    colors: np.ndarray | None = None) -> np.ndarray:
    """Anchor rows: x y z (float), level (int), f_anchor_0..D-1 (float) and, when ``colors`` [N, 3]
    uint8 is given, red green blue (so point-cloud viewers show the levels).

    positions [N, 3]; levels [N]; features [N, D].
    """
    positions = positions.detach().to("cpu", torch.float32).numpy()
    features = features.detach().to("cpu", torch.float32).numpy()
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("level", "<i4")]
    fields += [(f"f_anchor_{i}", "<f4") for i in range(features.shape[1])]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rows = np.empty(len(positions), dtype=fields)
    for i, axis in enumerate("xyz"):
        rows[axis] = positions[:, i]
    rows["level"] = levels.detach().cpu().numpy()
    for i in range(features.shape[1]):
        rows[f"f_anchor_{i}"] = features[:, i]
    if colors is not None:
        for i, channel in enumerate(("red", "green", "blue")):
            rows[channel] = colors[:, i]
    return rows
