"""What every rasterizer backend shares: the output record, the option names and defaults, the backend contract.

``rasterize`` validates, packs the per-Gaussian channels and derives the maps; a backend (a ``RasterizerBackend``
in ``RASTERIZER_BACKENDS``) only projects and composites. ``project(means, quats, scales, opacities, viewmats, Ks,
width, height, near, far, normals=False)`` gives at least ``means_cam`` [C,N,3], ``means2d`` [C,N,2], ``depths``
[C,N], ``radii`` [C,N] (int, 0 = culled), ``normals`` / ``distances`` (None, or with ``normals=True``
``geometry.gaussian_normals``' [C,N,3] / [C,N]); ``composite(projected, means2d [C,N,2], opacities [N], features
[C,N,D], width, height, tile_size)`` -> image [C,H,W,D] (D may be 0), alpha [C,H,W,1], blending the ``means2d``
handed in so its ``retain_grad()`` collects densification's gradients.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Optional

import torch
from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.registry import Registry

OUTPUT_NAMES = ("rgb", "alpha", "depth", "normal", "distance", "plane_depth", "depth_normal")
"""Every image a backend can render; ``outputs=`` is any subset."""

COMPOSITORS = ("auto", "fused", "torch")
"""Blending kernels of the torch backend (see ``rasterize``); other backends bring their own."""

DEPTH_NORMAL_SOURCES = ("plane_depth", "depth")
"""Which depth map ``depth_normal`` is back-projected from."""

NEAR = 0.01
"""Default near plane: Gaussians with camera z <= near are culled."""
FAR = 1e10
"""Default far plane: Gaussians with camera z >= far are culled."""
COMPOSITOR = "auto"
"""Default blending kernel of the torch backend."""
TILE_SIZE = 16
"""Tile edge of a backend that does not choose its own (gsplat's CUDA kernels are built around 16)."""


class RasterizerBackend:
    """Projects Gaussians into cameras and alpha-composites per-Gaussian channels (see the module
    docstring); ``compositor`` and ``use_compile`` choose the torch backend's kernels and are
    accepted, unused, by backends that bring their own."""

    def __init__(self, *, compositor: str = COMPOSITOR, use_compile: bool = True):
        if compositor not in COMPOSITORS:
            raise HicoError(f"compositor must be one of {list(COMPOSITORS)}, got '{compositor}'")
        self.compositor = compositor
        self.use_compile = use_compile

    def project(self, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmats: Tensor,
                Ks: Tensor, width: int, height: int, near: float, far: float, *, normals: bool = False) -> Any:
        raise NotImplementedError

    def composite(self, projected: Any, means2d: Tensor, opacities: Tensor, features: Tensor, width: int,
                  height: int, tile_size: int) -> tuple[Tensor, Tensor]:
        raise NotImplementedError

    def default_tile_size(self, device: torch.device) -> int:
        """The tile edge used when none is given (tile_size 0)."""
        return TILE_SIZE

    def uses_fused_kernels(self, device: torch.device) -> bool:
        """Whether renders on ``device`` run the package's fused CPU kernels, and so should the maps that
        ``rasterize`` derives from them (the depth normal)."""
        return False


RASTERIZER_BACKENDS: Registry[type[RasterizerBackend]] = Registry("rasterizer backend")


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
