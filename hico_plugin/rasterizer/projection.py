"""EWA projection of 3-D Gaussians to screen-space ellipses (3DGS / gsplat conventions).

The torch reference, used on any device; projection_fused.py computes the same (and the Gaussians' normals) in
one C++ CPU kernel where the torch backend runs its fused compositor."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

ALPHA_MIN = 1.0 / 255.0  # pairs below this alpha are skipped when compositing
COV2D_BLUR = 0.3  # px^2 added to the 2-D covariance diagonal (anti-aliasing low-pass, as 3DGS)
FRUSTUM_MARGIN = 0.3  # the Jacobian is evaluated inside the frustum widened by 1.3 x tan(half FoV)
DET_MIN = 1e-12  # floor of the 2-D covariance's determinant (>= 0.09 in exact arithmetic; guards rounding only)
QUAT_NORM_MIN = 1e-12  # a quaternion of a smaller norm is read as the identity


@dataclass
class Projection:
    """Per-camera screen-space Gaussians; every field but ``reach`` has a leading camera dimension C.
    means_cam, means2d, conics, depths, normals and distances are differentiable w.r.t. the Gaussians."""

    means_cam: Tensor  # [C,N,3] centres in camera coordinates
    means2d: Tensor  # [C,N,2] projected centres in pixels (pixel centres at +0.5)
    conics: Tensor  # [C,N,3] inverse 2-D covariance (a, b, c) of [[a, b], [b, c]]
    depths: Tensor  # [C,N] camera z
    reach: Tensor  # [N] Mahalanobis radius where alpha falls to 1/255 (0 below that opacity)
    extents: Tensor  # [C,N,2] half-width / half-height in px of the drawn ellipse's bounding box
    radii: Tensor  # [C,N] int32 ceil(max extent); 0 = culled
    normals: Optional[Tensor] = None  # [C,N,3] camera-space normals (geometry.gaussian_normals), when asked for
    distances: Optional[Tensor] = None  # [C,N] their plane distances |n . mu_cam|, when asked for


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices of (w,x,y,z) quaternions of any norm: [N,4] -> [N,3,3].

    A zero quaternion is read as the identity, with zero gradient (instead of a 1/eps blow-up).
    """
    norm = quats.norm(dim=-1, keepdim=True)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    ok = norm > QUAT_NORM_MIN
    q = torch.where(ok, quats, identity) / torch.where(ok, norm, torch.ones_like(norm))
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, -1).reshape(*quats.shape[:-1], 3, 3)


def opacity_reach(opacities: Tensor) -> Tensor:
    """opacities [N] -> [N] the largest Mahalanobis radius r where o * exp(-r^2/2) still reaches alpha 1/255;
    0 (culled) at opacity <= 1/255. Only for binning, so without gradient."""
    with torch.no_grad():
        level = torch.log(opacities.clamp_min(1e-30) / ALPHA_MIN)
        return torch.sqrt(2.0 * level.clamp_min(0.0))


def world_to_camera(means: Tensor, viewmats: Tensor) -> Tensor:
    """means [N,3], viewmats [C,4,4] -> [C,N,3].

    Computed in float64: city-scale coordinates (1e5 m) cancel against the translation, and float32
    matmul error there would be centimetres; the result is cast back to the input dtype.
    """
    rot = viewmats[:, :3, :3].double()
    trans = viewmats[:, :3, 3].double()
    return (torch.einsum("cij,nj->cni", rot, means.double()) + trans[:, None, :]).to(means.dtype)


def project_gaussians(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmats: Tensor, Ks: Tensor,
    width: int, height: int, near: float = 0.01, far: float = 1e10,
) -> Projection:
    """Project Gaussians into C cameras.

    means [N,3], quats [N,4] (w,x,y,z), scales [N,3] (linear), opacities [N] in [0,1], viewmats [C,4,4]
    world->camera, Ks [C,3,3]. Culled (radius 0): centre z <= near or >= far, opacity <= 1/255, or an ellipse that
    misses the image. The extent is opacity-aware, o * exp(-r^2/2) >= 1/255 (r the Mahalanobis distance), so
    nothing above the compositing cut is dropped (gsplat's 3 sigma is o = 1, ~3.33).
    """
    means_cam = world_to_camera(means, viewmats)  # [C,N,3]
    x, y, z = means_cam.unbind(-1)
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    in_depth = (z > near) & (z < far)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))  # keeps culled Gaussians' maths finite

    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], -1)

    # Perspective Jacobian at the centre, with x/z and y/z clamped to the widened frustum (gsplat).
    lim_x_pos = (width - cx) / fx + FRUSTUM_MARGIN * (0.5 * width / fx)
    lim_x_neg = cx / fx + FRUSTUM_MARGIN * (0.5 * width / fx)
    lim_y_pos = (height - cy) / fy + FRUSTUM_MARGIN * (0.5 * height / fy)
    lim_y_neg = cy / fy + FRUSTUM_MARGIN * (0.5 * height / fy)
    tx = z_safe * torch.maximum(torch.minimum(x / z_safe, lim_x_pos), -lim_x_neg)
    ty = z_safe * torch.maximum(torch.minimum(y / z_safe, lim_y_pos), -lim_y_neg)
    zeros = torch.zeros_like(z)
    jac = torch.stack([
        fx / z_safe, zeros, -fx * tx / z_safe**2,
        zeros, fy / z_safe, -fy * ty / z_safe**2,
    ], -1).reshape(*z.shape, 2, 3)  # [C,N,2,3]

    # Sigma_2d = (J W R S)(J W R S)^T: a product of a factor with its transpose stays PSD.
    factor = quat_to_rotmat(quats) * scales[:, None, :]  # [N,3,3] = R S
    factor = torch.einsum("cij,njk->cnik", viewmats[:, :3, :3], factor)  # W R S
    factor = jac @ factor  # [C,N,2,3]
    cov2d = factor @ factor.transpose(-1, -2)
    a = cov2d[..., 0, 0] + COV2D_BLUR
    b = cov2d[..., 0, 1]
    c = cov2d[..., 1, 1] + COV2D_BLUR
    det = (a * c - b * b).clamp_min(DET_MIN)
    conics = torch.stack([c / det, -b / det, a / det], -1)

    with torch.no_grad():
        reach = opacity_reach(opacities)
        extents = torch.stack([reach * a.sqrt(), reach * c.sqrt()], -1)  # ellipse bbox half-sizes
        u, v = means2d.unbind(-1)
        ex, ey = extents.unbind(-1)
        # Pixel i (centre i+0.5) is covered when |i + 0.5 - u| <= ex.
        on_image = (u + ex > 0) & (u - ex < width) & (v + ey > 0) & (v - ey < height)
        visible = in_depth & (reach > 0) & on_image & torch.isfinite(u) & torch.isfinite(v)
        extents = torch.where(visible[..., None], extents, torch.zeros_like(extents))
        radii = torch.ceil(extents.amax(-1).clamp_max(2.0**30)).to(torch.int32)
        radii = torch.where(visible, radii.clamp_min(1), torch.zeros_like(radii))
    return Projection(means_cam, means2d, conics, z, reach, extents, radii)

