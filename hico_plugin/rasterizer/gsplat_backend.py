"""The "gsplat" rasterizer backend: gsplat's CUDA projection and blending behind the backend contract (base.py).

``fully_fused_projection`` gets the opacities, so the extent is opacity-aware (per-axis radii [C,N,2] kept as
their maximum, [C,N]). As gsplat's pure-torch reference: camera z, centres, conics, 0.3 px^2 blur, Jacobian clamp,
near/far culling; its radius is ceil(3.33 sigma) per axis, ours ceil(sqrt(2 ln(255 o)) sigma) of the larger axis,
and ours culls o <= 1/255. Needs gsplat (``pip install -e ".[cuda]"``), CUDA torch and tensors, float32 (else one
HicoError); ``use_compile`` and ``compositor`` mean nothing here; default tile edge 16.
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass
from types import SimpleNamespace

import torch
from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.rasterizer.base import RASTERIZER_BACKENDS, RasterizerBackend
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


@dataclass
class GsplatProjection:
    """gsplat's projection of C cameras, with the fields the backend contract asks for."""

    means_cam: Tensor  # [C,N,3] centres in camera coordinates
    means2d: Tensor  # [C,N,2] projected centres in pixels
    depths: Tensor  # [C,N] camera z
    radii: Tensor  # [C,N] int32 max of gsplat's per-axis radii; 0 = culled
    radii_xy: Tensor  # [C,N,2] gsplat's per-axis radii, for its tile intersection
    conics: Tensor  # [C,N,3]
    ops: SimpleNamespace  # the gsplat kernels that projected, to composite with
    normals = None  # gsplat computes no normals: rasterize derives them from means_cam
    distances = None


@RASTERIZER_BACKENDS.register("gsplat")
class GsplatBackend(RasterizerBackend):
    """gsplat's CUDA projection, tile intersection and blending (float32, CUDA tensors)."""

    def project(self, means, quats, scales, opacities, viewmats, Ks, width, height, near, far, *,
                normals=False) -> GsplatProjection:
        ops = load_gsplat_ops(means.device)
        if means.dtype != torch.float32:
            raise HicoError(f"rasterizer backend 'gsplat' renders float32 only, got {means.dtype}")
        radii_xy, means2d, depths, conics, _ = ops.fully_fused_projection(
            means, None, _nonzero_quats(quats), scales, viewmats, Ks, width, height, eps2d=COV2D_BLUR,
            near_plane=near, far_plane=far, opacities=opacities)
        return GsplatProjection(world_to_camera(means, viewmats), means2d, depths,
                                radii_xy.amax(-1).to(torch.int32), radii_xy, conics, ops)

    def composite(self, projected: GsplatProjection, means2d, opacities, features, width, height, tile_size):
        ops = projected.ops
        num_cams, _, channels = features.shape
        if channels == 0:  # gsplat rejects zero channels, which an alpha-only render has
            features = features.new_zeros(*features.shape[:2], 1)
        tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
        _, isect_ids, flatten_ids = ops.isect_tiles(means2d, projected.radii_xy, projected.depths, tile_size,
                                                    tiles_x, tiles_y)
        isect_offsets = ops.isect_offset_encode(isect_ids, num_cams, tiles_x, tiles_y)
        image, alpha = ops.rasterize_to_pixels(
            means2d, projected.conics, features.contiguous(), opacities[None].expand(num_cams, -1).contiguous(),
            width, height, tile_size, isect_offsets, flatten_ids)
        return image[..., :channels], alpha
