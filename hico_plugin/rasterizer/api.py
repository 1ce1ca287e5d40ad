"""The functional entry point ``rasterize``: validation, channel packing and derived maps, around a
backend that projects and composites (base.py)."""

from __future__ import annotations

import os
from typing import Iterable, Optional, Union

import torch
from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.rasterizer.base import (
    COMPOSITOR, DEPTH_NORMAL_SOURCES, FAR, NEAR, OUTPUT_NAMES, RASTERIZER_BACKENDS, RasterizerBackend,
    RenderOutputs)
from hico_plugin.rasterizer.depth_normal_fused import (
    depth_normal_from_plane, depth_normal_fused_accepts, depth_normal_fused_available)
from hico_plugin.rasterizer.geometry import depth_to_normal, expected_depth, gaussian_normals, plane_depth


def rasterize(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
    viewmat: Tensor, K: Tensor, width: int, height: int, *,
    outputs: Iterable[str] = ("rgb",), background: Optional[Tensor] = None,
    near: float = NEAR, far: float = FAR, tile_size: int = 0,
    backend: Union[str, RasterizerBackend] = "torch", depth_normal_from: str = "plane_depth",
    use_compile: Optional[bool] = None, compositor: Optional[str] = None,
) -> RenderOutputs:
    """Render Gaussians into one camera (viewmat [4,4], K [3,3]) or C cameras ([C,4,4], [C,3,3]).

    means [N,3]; quats [N,4] (w,x,y,z, any norm, zero = identity); scales [N,3] (linear); opacities [N] in [0,1];
    colors [N,D]; background [D] or None (black). ``outputs``: any subset of rgb, alpha, depth, normal, distance,
    plane_depth, depth_normal; ``depth_normal_from``: "plane_depth" or "depth"; ``tile_size`` 0: the backend's.
    ``backend``: a name or a built RasterizerBackend; for a name, ``compositor`` "fused" / "torch" / "auto" (fused
    on CPU when it builds) and ``use_compile`` torch.compiles the torch one (None: unless HICO_NO_COMPILE=1).
    Returns images [H,W,·] ([C,H,W,·]), means2d [N,2] ([C,N,2]), radii [N] ([C,N]).
    """
    outputs = frozenset(outputs)
    _validate(means, quats, scales, opacities, colors, viewmat, K, width, height, outputs,
              background, near, far, tile_size, depth_normal_from)
    if isinstance(backend, str):
        if use_compile is None:
            use_compile = os.environ.get("HICO_NO_COMPILE") != "1"
        backend = RASTERIZER_BACKENDS.get(backend)(compositor=compositor or COMPOSITOR, use_compile=use_compile)
    elif compositor is not None or use_compile is not None:
        raise HicoError("rasterize: compositor and use_compile configure a backend given by name; a "
                        "RasterizerBackend brings its own")
    batched = viewmat.dim() == 3
    viewmats = viewmat if batched else viewmat[None]
    Ks = K if batched else K[None]

    need_normal, need_distance, _ = geometry_channels(outputs, depth_normal_from)
    projected = backend.project(means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
                                normals=need_normal or need_distance)
    means2d_out = projected.means2d if batched else projected.means2d.squeeze(0)
    means2d = means2d_out if batched else means2d_out[None]  # images depend on means2d_out itself
    features, sizes = _pack_channels(colors, quats, scales, viewmats, projected, outputs, depth_normal_from)
    image, alpha = backend.composite(projected, means2d, opacities, features, width, height,
                                     tile_size or backend.default_tile_size(means.device))
    maps = dict(zip(("rgb", "normal", "distance", "z"), image.split(sizes, -1)))

    result = RenderOutputs(means2d=means2d_out, radii=projected.radii if batched else projected.radii.squeeze(0))
    _derive_maps(result, maps, alpha, outputs, background, colors, Ks, depth_normal_from,
                 backend.uses_fused_kernels(means.device))
    if not batched:
        for name, rendered in result.images().items():
            setattr(result, name, rendered.squeeze(0))
    return result


def _pack_channels(colors: Tensor, quats: Tensor, scales: Tensor, viewmats: Tensor, projected,
                   outputs: frozenset[str], depth_normal_from: str) -> tuple[Tensor, list[int]]:
    """The per-Gaussian channels the outputs need, [C,N,D], as colour | normal (3) | plane distance (1)
    | camera z (1), and the width of each of those four groups (0 when not needed). The normals and
    distances are the projection's when its backend computed them, else ``gaussian_normals`` of its
    camera-space centres."""
    num_cams, n = projected.means2d.shape[:2]
    need_normal, need_distance, need_z = geometry_channels(outputs, depth_normal_from)
    channels = []
    if "rgb" in outputs:
        channels.append(colors[None].expand(num_cams, -1, -1))
    if need_normal or need_distance:
        normals, distances = projected.normals, projected.distances
        if normals is None:
            normals, distances = gaussian_normals(quats, scales, projected.means_cam, viewmats)
        if need_normal:
            channels.append(normals)
        if need_distance:
            channels.append(distances[..., None])
    if need_z:
        channels.append(projected.depths[..., None])
    features = torch.cat(channels, -1) if channels else colors.new_zeros(num_cams, n, 0)
    sizes = [colors.shape[1] if "rgb" in outputs else 0, 3 if need_normal else 0, int(need_distance), int(need_z)]
    return features, sizes


def _derive_maps(result: RenderOutputs, maps: dict[str, Tensor], alpha: Tensor, outputs: frozenset[str],
                 background: Optional[Tensor], colors: Tensor, Ks: Tensor, depth_normal_from: str,
                 fused: bool) -> None:
    """Fill ``result`` with the asked images from the composited channel ``maps`` ([C,H,W,·]); ``fused``:
    the render ran the fused CPU kernels, so the depth normal of the plane depth may too."""
    if "rgb" in outputs:
        bg = background if background is not None else colors.new_zeros(colors.shape[1])
        result.rgb = maps["rgb"] + (1.0 - alpha) * bg
    if "alpha" in outputs:
        result.alpha = alpha
    depth = expected_depth(maps["z"], alpha) if maps["z"].shape[-1] else None
    if "depth" in outputs:
        result.depth = depth
    if "normal" in outputs:
        result.normal = maps["normal"]
    if "distance" in outputs:
        result.distance = maps["distance"]
    if "plane_depth" in outputs:
        result.plane_depth = plane_depth(maps["normal"], maps["distance"], alpha, Ks)
    if "depth_normal" in outputs and depth_normal_from == "depth":
        result.depth_normal = depth_to_normal(depth, Ks)
    elif "depth_normal" in outputs:
        planes = (maps["normal"], maps["distance"], alpha, Ks)
        if fused and depth_normal_fused_accepts(*planes) and depth_normal_fused_available():
            result.depth_normal = depth_normal_from_plane(*planes)
        else:
            planar = result.plane_depth if result.plane_depth is not None else plane_depth(*planes)
            result.depth_normal = depth_to_normal(planar, Ks)


def _validate(means, quats, scales, opacities, colors, viewmat, K, width, height, outputs,
              background, near, far, tile_size, depth_normal_from) -> None:
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
    if not (isinstance(tile_size, int) and tile_size >= 0):
        raise HicoError(f"rasterize: tile_size must be a positive int (0 = the backend's own), got {tile_size}")
    if depth_normal_from not in DEPTH_NORMAL_SOURCES:
        raise HicoError(f"rasterize: depth_normal_from must be one of {list(DEPTH_NORMAL_SOURCES)},"
                        f" got '{depth_normal_from}'")


def geometry_channels(outputs: frozenset[str], depth_normal_from: str) -> tuple[bool, bool, bool]:
    """Which per-Gaussian geometry channels the requested outputs need: (normal, distance, z)."""
    dn_plane = "depth_normal" in outputs and depth_normal_from == "plane_depth"
    dn_depth = "depth_normal" in outputs and depth_normal_from == "depth"
    need_normal = bool({"normal", "plane_depth"} & outputs) or dn_plane
    need_distance = bool({"distance", "plane_depth"} & outputs) or dn_plane
    need_z = "depth" in outputs or dn_depth
    return need_normal, need_distance, need_z
