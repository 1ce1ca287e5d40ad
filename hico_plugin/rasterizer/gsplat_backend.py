"""The "gsplat" rasterizer backend: gsplat's CUDA kernels with the pure-torch backend's contract.

Geometry is rendered as extra colour channels -- per-Gaussian camera-space normal (3), plane distance
(1) and camera z (1), exactly as the torch backend composites them -- and the derived maps
(expected depth, plane depth, depth normal) come from the same helpers in ``geometry.py``. The
projection is gsplat's ``fully_fused_projection`` given the opacities, so the drawn extent is
opacity-aware like the torch backend's (gsplat's radii are per axis, [C,N,2]; the RenderOutputs
contract keeps their maximum, [C,N]).

Conventions checked against gsplat's pure-torch reference (tests/test_gsplat_backend.py): camera z,
projected centres (pixel centres at +0.5) and conics agree to rounding, with the same 0.3 px^2 blur,
frustum-widened Jacobian clamp and near/far culling. Differences: the reference's radius is
ceil(3.33 sigma) per axis, ours ceil(sqrt(2 ln(255 o)) sigma) of the larger axis (3.329 sigma at o = 1,
smaller for fainter Gaussians); the reference keeps an ellipse whose integer radius touches the image
where ours, testing the exact extent, may cull it (< 1 px of difference); ours also culls o <= 1/255.

Needs gsplat (``pip install -e ".[cuda]"``), a CUDA torch and CUDA tensors; otherwise it raises one
HicoError naming the fix. gsplat's kernels are float32 only. ``use_compile`` and ``compositor``
(the torch backend's blending kernels) have no meaning here.
"""

from __future__ import annotations

import importlib.util
import math
from types import SimpleNamespace

import torch
from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.rasterizer.api import geometry_channels
from hico_plugin.rasterizer.base import RASTERIZER_BACKENDS, RenderOutputs
from hico_plugin.rasterizer.geometry import depth_to_normal, expected_depth, gaussian_normals, plane_depth
from hico_plugin.rasterizer.projection import COV2D_BLUR, world_to_camera

INSTALL_HINT = ('install it with `pip install -e ".[cuda]"` on a machine with a CUDA GPU and a CUDA build '
                'of torch, or use backend "torch"')


def load_gsplat_ops(device: torch.device) -> SimpleNamespace:
    """gsplat's projection / tile-intersection / compositing kernels, or a HicoError saying what is missing."""
    if importlib.util.find_spec("gsplat") is None:
        raise HicoError(f"rasterizer backend 'gsplat' needs the gsplat package, which is not installed; {INSTALL_HINT}")
    if not torch.cuda.is_available():
        raise HicoError(f"rasterizer backend 'gsplat' needs CUDA, but this torch sees no CUDA device; {INSTALL_HINT}")
    if device.type != "cuda":
        raise HicoError(f"rasterizer backend 'gsplat' needs the Gaussians on a CUDA device, got '{device}'; "
                        f"move the model to cuda or use backend 'torch'")
    import gsplat

    return SimpleNamespace(fully_fused_projection=gsplat.fully_fused_projection, isect_tiles=gsplat.isect_tiles,
                           isect_offset_encode=gsplat.isect_offset_encode,
                           rasterize_to_pixels=gsplat.rasterize_to_pixels)


def _nonzero_quats(quats: Tensor) -> Tensor:
    """Zero quaternions -> identity (gsplat would divide by their zero norm; the torch backend reads them so)."""
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    return torch.where(quats.norm(dim=-1, keepdim=True) > 1e-12, quats, identity)


@RASTERIZER_BACKENDS.register("gsplat")
def rasterize_gsplat(means, quats, scales, opacities, colors, viewmat, K, width, height, *,
                     outputs, background, near, far, tile_size, depth_normal_from, use_compile,
                     compositor) -> RenderOutputs:
    """The gsplat backend (see base.py for the backend contract)."""
    ops = load_gsplat_ops(means.device)
    if means.dtype != torch.float32:
        raise HicoError(f"rasterizer backend 'gsplat' renders float32 only, got {means.dtype}")
    batched = viewmat.dim() == 3
    viewmats = viewmat if batched else viewmat[None]
    Ks = K if batched else K[None]
    num_cams, n = viewmats.shape[0], means.shape[0]
    quats = _nonzero_quats(quats)

    radii_xy, projected, depths, conics, _ = ops.fully_fused_projection(
        means, None, quats, scales, viewmats, Ks, width, height, eps2d=COV2D_BLUR, near_plane=near,
        far_plane=far, opacities=opacities)
    # The images must depend on the very tensor handed out as means2d (retain_grad for densification).
    means2d_out = projected if batched else projected[0]
    means2d = means2d_out if batched else means2d_out[None]

    need_normal, need_distance, need_z = geometry_channels(outputs, depth_normal_from)
    channels = []
    if "rgb" in outputs:
        channels.append(colors[None].expand(num_cams, -1, -1))
    if need_normal or need_distance:
        normals, distances = gaussian_normals(quats, scales, world_to_camera(means, viewmats), viewmats)
        if need_normal:
            channels.append(normals)
        if need_distance:
            channels.append(distances[..., None])
    if need_z:
        channels.append(depths[..., None])
    # gsplat rejects zero channels, which an alpha-only render would have: composite a dummy one.
    features = torch.cat(channels, -1) if channels else means.new_zeros(num_cams, n, 1)

    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    _, isect_ids, flatten_ids = ops.isect_tiles(means2d, radii_xy, depths, tile_size, tiles_x, tiles_y)
    isect_offsets = ops.isect_offset_encode(isect_ids, num_cams, tiles_x, tiles_y)
    image, alpha = ops.rasterize_to_pixels(
        means2d, conics, features.contiguous(), opacities[None].expand(num_cams, -1).contiguous(),
        width, height, tile_size, isect_offsets, flatten_ids)

    sizes = [colors.shape[1] if "rgb" in outputs else 0, 3 if need_normal else 0, int(need_distance), int(need_z)]
    maps = dict(zip(["rgb", "normal", "distance", "z"], image[..., :sum(sizes)].split(sizes, -1)))
    radii = radii_xy.amax(-1).to(torch.int32)
    result = RenderOutputs(means2d=means2d_out, radii=radii if batched else radii[0])
    if "rgb" in outputs:
        bg = background if background is not None else colors.new_zeros(colors.shape[1])
        result.rgb = maps["rgb"] + (1.0 - alpha) * bg
    if "alpha" in outputs:
        result.alpha = alpha
    depth = expected_depth(maps["z"], alpha) if need_z else None
    if "depth" in outputs:
        result.depth = depth
    if "normal" in outputs:
        result.normal = maps["normal"]
    if "distance" in outputs:
        result.distance = maps["distance"]
    planar = plane_depth(maps["normal"], maps["distance"], alpha, Ks) if need_normal and need_distance else None
    if "plane_depth" in outputs:
        result.plane_depth = planar
    if "depth_normal" in outputs:
        result.depth_normal = depth_to_normal(planar if depth_normal_from == "plane_depth" else depth, Ks)
    if not batched:
        for name, rendered in result.images().items():
            setattr(result, name, rendered[0])
    return result
