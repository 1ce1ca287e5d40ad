"""The renderer component: a config that builds a callable bound to one backend and its options."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional

import torch
from torch import Tensor

from hico_plugin.cameras import Camera
from hico_plugin.config import InstantiateConfig
from hico_plugin.errors import HicoError
from hico_plugin.rasterizer.api import rasterize, use_fused
from hico_plugin.rasterizer.base import COMPOSITORS, RASTERIZER_BACKENDS, RenderOutputs


# Default tile edges. The vectorised torch compositor evaluates every pixel of a tile against every
# Gaussian binned to it, so small tiles waste fewer pairs on the few-pixel Gaussians of real renders
# (fwd+bwd of trained city-block views at 320x240, 1 thread: tile 16 1.34 s, 8 0.54 s, 4 0.35 s).
# The fused CPU compositor rejects a far pair before its exp and stops each pixel early, so tile size
# barely matters to it (train steps 232 / 228 / 223 ms at 16 / 8 / 4) and 16 keeps the fewest
# intersections, as gsplat's CUDA kernels are built around 16.
TORCH_COMPOSITOR_TILE_SIZE = 4
DEFAULT_TILE_SIZE = 16


def default_tile_size(backend: str, compositor: str, device: torch.device) -> int:
    """The tile edge used when RendererConfig.tile_size is 0."""
    if backend == "torch" and not use_fused(compositor, device):
        return TORCH_COMPOSITOR_TILE_SIZE
    return DEFAULT_TILE_SIZE


@dataclass
class RendererConfig(InstantiateConfig):
    """How Gaussians are rasterized."""

    backend: str = "torch"
    """Rasterizer backend: "torch" (pure torch, CPU or GPU) or "gsplat" (compiled CUDA, extra [cuda])."""
    tile_size: int = 0
    """Tile edge in pixels for binning and compositing; 0 = the compositor's own (16; 4 for the torch
    compositor).
    Outputs do not depend on it, only speed does."""
    near: float = 0.01
    """Gaussians with camera z <= near are culled."""
    far: float = 1e10
    """Gaussians with camera z >= far are culled."""
    depth_normal_from: str = "plane_depth"
    """Depth map that depth_normal is derived from: "plane_depth" (PGSR/CityGS-X) or "depth"."""
    compositor: str = "auto"
    """Blending kernel of the torch backend: "fused" (C++ built on first use, CPU), "torch"
    (vectorised torch, any device) or "auto" (fused on CPU when it builds, else torch)."""
    use_compile: bool = True
    """Fuse the torch compositor with torch.compile (falls back to eager if compilation fails)."""

    def setup(self, **kwargs) -> "Renderer":
        RASTERIZER_BACKENDS.get(self.backend)  # unknown names fail at build time, not mid-training
        if self.compositor not in COMPOSITORS:
            raise HicoError(f"renderer.compositor must be one of {list(COMPOSITORS)}, got "
                            f"'{self.compositor}'")
        return Renderer(self)


class Renderer:
    """Renders Gaussians from a Camera with the options of its RendererConfig."""

    def __init__(self, config: RendererConfig):
        self.config = config

    def __call__(self, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                 colors: Tensor, camera: Camera, outputs: Iterable[str] = ("rgb",),
                 background: Optional[Tensor] = None) -> RenderOutputs:
        """means [N,3], quats [N,4], scales [N,3], opacities [N], colors [N,D] -> images [H,W,·]."""
        c = self.config
        return rasterize(
            means, quats, scales, opacities, colors, camera.viewmat.to(means), camera.K.to(means),
            camera.width, camera.height, outputs=outputs, background=background, near=c.near,
            far=c.far, backend=c.backend,
            tile_size=c.tile_size or default_tile_size(c.backend, c.compositor, means.device),
            depth_normal_from=c.depth_normal_from, use_compile=c.use_compile, compositor=c.compositor)
