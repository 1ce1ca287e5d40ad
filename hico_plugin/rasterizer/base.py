"""What every rasterizer backend shares: the output record, the output names and the backend registry.

A backend is a function registered in ``RASTERIZER_BACKENDS`` with exactly the signature of
``hico_plugin.rasterizer.rasterize`` minus ``backend``; ``rasterize`` validates the inputs first::

    backend(means [N,3], quats [N,4], scales [N,3], opacities [N], colors [N,D],
            viewmat [4,4] | [C,4,4], K [3,3] | [C,3,3], width: int, height: int, *,
            outputs: frozenset[str], background: Tensor [D] | None, near: float, far: float,
            tile_size: int, depth_normal_from: str, use_compile: bool, compositor: str
            ) -> RenderOutputs

It returns a RenderOutputs shaped like the cameras it got (leading C only for a [C,4,4] viewmat).
``means2d`` must be the very tensor the images were computed from, so that ``retain_grad()`` on it
collects the screen-space gradients used for densification; with a single camera, slice
``means2d[0]`` first and render from ``means2d[0][None]``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Callable, Optional

from torch import Tensor

from hico_plugin.registry import Registry

OUTPUT_NAMES = ("rgb", "alpha", "depth", "normal", "distance", "plane_depth", "depth_normal")
"""Every image a backend can render; ``outputs=`` is any subset."""

COMPOSITORS = ("auto", "fused", "torch")
"""Blending kernels of the torch backend (see ``rasterize``); other backends bring their own."""

DEPTH_NORMAL_SOURCES = ("plane_depth", "depth")
"""Which depth map ``depth_normal`` is back-projected from."""

RASTERIZER_BACKENDS: Registry[Callable[..., "RenderOutputs"]] = Registry("rasterizer backend")


@dataclass
class RenderOutputs:
    """Rendered images ([H,W,·], or [C,H,W,·] with a camera dimension); None unless asked for."""

    rgb: Optional[Tensor] = None  # [H,W,D] colours composited over the background
    alpha: Optional[Tensor] = None  # [H,W,1] accumulated opacity
    depth: Optional[Tensor] = None  # [H,W,1] expected camera z / alpha; 0 where nothing is drawn
    normal: Optional[Tensor] = None  # [H,W,3] n_r: composited camera-space normals (not normalised)
    distance: Optional[Tensor] = None  # [H,W,1] d: composited plane distances |n . mu_cam|
    plane_depth: Optional[Tensor] = None  # [H,W,1] distance / -(normal . ray); 0 where undefined
    depth_normal: Optional[Tensor] = None  # [H,W,3] n_d: unit normal of the back-projected depth map
    means2d: Optional[Tensor] = None  # [N,2] projected centres, on the autograd path (retain_grad)
    radii: Optional[Tensor] = None  # [N] int pixel radius of the drawn extent; 0 = culled

    def images(self) -> dict[str, Tensor]:
        """The rendered images that are present, by output name."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if f.name in OUTPUT_NAMES and getattr(self, f.name) is not None}
