"""The functional entry point ``rasterize`` and the pure-torch backend registered as "torch"."""

from __future__ import annotations

import os
from typing import Iterable, Optional

import torch
from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.rasterizer.base import (
    COMPOSITORS, DEPTH_NORMAL_SOURCES, OUTPUT_NAMES, RASTERIZER_BACKENDS, RenderOutputs)
from hico_plugin.rasterizer.composite import composite
from hico_plugin.rasterizer.fused import (
    EXTENSION, bin_gaussians_fused, composite_fused, fused_available)
from hico_plugin.rasterizer.geometry import (
    depth_to_normal, expected_depth, gaussian_normals, plane_depth)
from hico_plugin.rasterizer.projection import project_gaussians
from hico_plugin.rasterizer.tiling import bin_gaussians


def rasterize(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
    viewmat: Tensor, K: Tensor, width: int, height: int, *,
    outputs: Iterable[str] = ("rgb",), background: Optional[Tensor] = None,
    near: float = 0.01, far: float = 1e10, tile_size: int = 16, backend: str = "torch",
    depth_normal_from: str = "plane_depth", use_compile: Optional[bool] = None,
    compositor: str = "auto",
) -> RenderOutputs:
    """Render Gaussians into one camera (viewmat [4,4], K [3,3]) or C cameras ([C,4,4], [C,3,3]).

    means [N,3]; quats [N,4] (w,x,y,z, any norm, zero = identity); scales [N,3] (linear);
    opacities [N] in [0,1]; colors [N,D] (any D); background [D] or None (black).
    ``outputs`` is any subset of rgb, alpha, depth, normal, distance, plane_depth, depth_normal
    (see RenderOutputs); only what is asked is computed. ``depth_normal_from`` picks the depth map
    that ``depth_normal`` differentiates ("plane_depth" or "depth"). ``compositor`` picks the torch
    backend's binning and blending kernels: "fused" (compiled C++ on CPU, early termination per
    pixel), "torch" (vectorised torch, any device) or "auto" (fused on CPU when it builds).
    ``use_compile`` fuses the torch compositor with torch.compile (None: on unless
    HICO_NO_COMPILE=1; the first call compiles).
    Images come back [H,W,·] (or [C,H,W,·]); means2d [N,2] ([C,N,2]) and radii [N] ([C,N]).
    """
    outputs = frozenset(outputs)
    _validate(means, quats, scales, opacities, colors, viewmat, K, width, height, outputs,
              background, near, far, tile_size, depth_normal_from, compositor)
    if use_compile is None:
        use_compile = os.environ.get("HICO_NO_COMPILE") != "1"
    render = RASTERIZER_BACKENDS.get(backend)
    return render(means, quats, scales, opacities, colors, viewmat, K, width, height,
                  outputs=outputs, background=background, near=near, far=far, tile_size=tile_size,
                  depth_normal_from=depth_normal_from, use_compile=use_compile,
                  compositor=compositor)


def _validate(means, quats, scales, opacities, colors, viewmat, K, width, height, outputs,
              background, near, far, tile_size, depth_normal_from, compositor) -> None:
    tensors = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                   viewmat=viewmat, K=K)
    for name, t in tensors.items():
        if not isinstance(t, Tensor) or not t.is_floating_point():
            raise HicoError(f"rasterize: {name} must be a floating-point tensor, got "
                            f"{getattr(t, 'dtype', type(t).__name__)}")
    n = means.shape[0] if means.dim() == 2 else -1
    expected = dict(means=(n, 3), quats=(n, 4), scales=(n, 3), opacities=(n,),
                    colors=(n, colors.shape[-1] if colors.dim() == 2 else -1))
    for name, shape in expected.items():
        if n < 0 or tuple(tensors[name].shape) != shape:
            raise HicoError(f"rasterize: {name} must have shape {list(shape) if n >= 0 else '[N,3]'}"
                            f" (N = len(means)), got {list(tensors[name].shape)}")
    batched = viewmat.dim() == 3
    if tuple(viewmat.shape[-2:]) != (4, 4) or viewmat.dim() not in (2, 3):
        raise HicoError(f"rasterize: viewmat must be [4,4] or [C,4,4], got {list(viewmat.shape)}")
    want_k = (viewmat.shape[0], 3, 3) if batched else (3, 3)
    if tuple(K.shape) != want_k:
        raise HicoError(f"rasterize: K must be {list(want_k)} to match viewmat, got {list(K.shape)}")
    dtypes = {t.dtype for t in tensors.values()}
    if len(dtypes) > 1:
        raise HicoError(f"rasterize: all inputs must share one dtype, got {sorted(map(str, dtypes))}")
    if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
        raise HicoError(f"rasterize: width and height must be positive ints, got {width}x{height}")
    unknown = sorted(outputs - set(OUTPUT_NAMES))
    if unknown:
        raise HicoError(f"rasterize: unknown outputs {unknown}; choose from {list(OUTPUT_NAMES)}")
    if background is not None and tuple(background.shape) != (colors.shape[-1],):
        raise HicoError(f"rasterize: background must have shape [{colors.shape[-1]}] (one value per "
                        f"colour channel), got {list(background.shape)}")
    if not 0 < near < far:
        raise HicoError(f"rasterize: need 0 < near < far, got near={near}, far={far}")
    if not (isinstance(tile_size, int) and tile_size > 0):
        raise HicoError(f"rasterize: tile_size must be a positive int, got {tile_size}")
    if depth_normal_from not in DEPTH_NORMAL_SOURCES:
        raise HicoError(f"rasterize: depth_normal_from must be one of {list(DEPTH_NORMAL_SOURCES)},"
                        f" got '{depth_normal_from}'")
    if compositor not in COMPOSITORS:
        raise HicoError(f"rasterize: compositor must be one of {list(COMPOSITORS)}, got '{compositor}'")


def geometry_channels(outputs: frozenset[str], depth_normal_from: str) -> tuple[bool, bool, bool]:
    """Which per-Gaussian geometry channels the requested outputs need: (normal, distance, z)."""
    dn_plane = "depth_normal" in outputs and depth_normal_from == "plane_depth"
    dn_depth = "depth_normal" in outputs and depth_normal_from == "depth"
    need_normal = bool({"normal", "plane_depth"} & outputs) or dn_plane
    need_distance = bool({"distance", "plane_depth"} & outputs) or dn_plane
    need_z = "depth" in outputs or dn_depth
    return need_normal, need_distance, need_z


@RASTERIZER_BACKENDS.register("torch")
def rasterize_torch(means, quats, scales, opacities, colors, viewmat, K, width, height, *,
                    outputs, background, near, far, tile_size, depth_normal_from, use_compile,
                    compositor) -> RenderOutputs:
    """The pure-torch backend (see base.py for the backend contract)."""
    batched = viewmat.dim() == 3
    viewmats = viewmat if batched else viewmat[None]
    Ks = K if batched else K[None]
    num_cams, n = viewmats.shape[0], means.shape[0]

    proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, near, far)
    means2d_out = proj.means2d if batched else proj.means2d[0]
    means2d = means2d_out if batched else means2d_out[None]  # images depend on means2d_out itself

    need_normal, need_distance, need_z = geometry_channels(outputs, depth_normal_from)
    channels = []
    if "rgb" in outputs:
        channels.append(colors[None].expand(num_cams, -1, -1))
    if need_normal or need_distance:
        normals, distances = gaussian_normals(quats, scales, proj.means_cam, viewmats)
        if need_normal:
            channels.append(normals)
        if need_distance:
            channels.append(distances[..., None])
    if need_z:
        channels.append(proj.depths[..., None])
    features = torch.cat(channels, -1) if channels else means.new_zeros(num_cams, n, 0)

    fused = use_fused(compositor, means.device)
    bin_fn = bin_gaussians_fused if fused else bin_gaussians
    bins = bin_fn(means2d, proj.conics, proj.reach, proj.extents, proj.depths, proj.radii,
                  width, height, tile_size)
    flat = (means2d.reshape(-1, 2), proj.conics.reshape(-1, 3),
            opacities[None].expand(num_cams, -1).reshape(-1),
            features.reshape(num_cams * n, features.shape[-1]))
    if fused:
        tiled, tiled_alpha = composite_fused(*flat, bins)
    else:
        tiled, tiled_alpha = composite(*flat, bins, use_compile=use_compile)
    image = _untile(torch.cat([tiled, tiled_alpha[..., None]], -1), num_cams, bins, width, height)
    maps = dict(zip(["rgb", "normal", "distance", "z"], image[..., :-1].split(
        [colors.shape[1] if "rgb" in outputs else 0, 3 if need_normal else 0,
         int(need_distance), int(need_z)], -1)))
    alpha = image[..., -1:]

    result = RenderOutputs(means2d=means2d_out, radii=proj.radii if batched else proj.radii[0])
    if "rgb" in outputs:
        bg = background if background is not None else colors.new_zeros(colors.shape[1])
        result.rgb = maps["rgb"] + (1.0 - alpha) * bg
    if "alpha" in outputs:
        result.alpha = alpha
    if need_z:
        depth = expected_depth(maps["z"], alpha)
        result.depth = depth if "depth" in outputs else None
    if "normal" in outputs:
        result.normal = maps["normal"]
    if "distance" in outputs:
        result.distance = maps["distance"]
    if need_normal and need_distance:
        planar = plane_depth(maps["normal"], maps["distance"], alpha, Ks)
        result.plane_depth = planar if "plane_depth" in outputs else None
    if "depth_normal" in outputs:
        result.depth_normal = depth_to_normal(planar if depth_normal_from == "plane_depth" else depth, Ks)
    if not batched:
        for name, image in result.images().items():
            setattr(result, name, image[0])
    return result


def use_fused(compositor: str, device: torch.device) -> bool:
    """Whether ``compositor`` resolves to the fused CPU kernel for tensors on ``device``."""
    if compositor == "torch":
        return False
    on_cpu = device.type == "cpu"
    if compositor == "auto":
        return on_cpu and fused_available()
    if not on_cpu:
        raise HicoError(f"rasterize: compositor='fused' runs on CPU tensors, got {device}; use "
                        "'torch' (or the gsplat backend) on a GPU")
    if not fused_available():
        raise HicoError(f"rasterize: compositor='fused' could not be built ({EXTENSION.error}); "
                        "install a C++ compiler or use compositor='torch'")
    return True


def _untile(tiled: Tensor, num_cams: int, bins, width: int, height: int) -> Tensor:
    """[T,P,D] tiles (camera-major, row-major) -> [C,H,W,D] images, cropped to the image size."""
    ts = bins.tile_size
    image = tiled.reshape(num_cams, bins.tiles_y, bins.tiles_x, ts, ts, -1)
    image = image.permute(0, 1, 3, 2, 4, 5).reshape(num_cams, bins.tiles_y * ts, bins.tiles_x * ts, -1)
    return image[:, :height, :width]
