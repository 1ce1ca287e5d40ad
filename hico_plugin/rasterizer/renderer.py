"""The renderer component: a config that builds a callable bound to one backend and its options."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional

from torch import Tensor

from hico_plugin.cameras import Camera
from hico_plugin.config import InstantiateConfig
from hico_plugin.rasterizer.api import rasterize
from hico_plugin.rasterizer.base import RASTERIZER_BACKENDS, RenderOutputs


# gsplat's CUDA kernels are built around 16 x 16 tiles. The torch backend evaluates every pixel of a
# tile against every Gaussian binned to it, so small tiles waste fewer pairs on the few-pixel Gaussians
# of real renders: measured fwd+bwd of trained city-block views at 320x240, 1 thread: 16 -> 1.34 s,
# 8 -> 0.54 s, 4 -> 0.35 s (benchmarks/rasterizer.py --tile-size compares random scenes).
DEFAULT_TILE_SIZES = {"torch": 4, "gsplat": 16}


@dataclass
class RendererConfig(InstantiateConfig):
    """How Gaussians are rasterized."""

    backend: str = "torch"
    """Rasterizer backend: "torch" (pure torch, CPU or GPU) or "gsplat" (compiled CUDA, extra [cuda])."""
    tile_size: int = 0
    """Tile edge in pixels for binning and compositing; 0 = the backend's own (DEFAULT_TILE_SIZES).
    Outputs do not depend on it, only speed does."""
    near: float = 0.01
    """Gaussians with camera z <= near are culled."""
    far: float = 1e10
    """Gaussians with camera z >= far are culled."""
    depth_normal_from: str = "plane_depth"
    """Depth map that depth_normal is derived from: "plane_depth" (PGSR/CityGS-X) or "depth"."""
    use_compile: bool = True
    """Fuse the torch compositor with torch.compile (falls back to eager if compilation fails)."""

    def setup(self, **kwargs) -> "Renderer":
        RASTERIZER_BACKENDS.get(self.backend)  # unknown names fail at build time, not mid-training
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
            far=c.far, tile_size=c.tile_size or DEFAULT_TILE_SIZES.get(c.backend, 16), backend=c.backend,
            depth_normal_from=c.depth_normal_from, use_compile=c.use_compile)
