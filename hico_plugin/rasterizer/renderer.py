"""The renderer component: a config that builds a callable bound to one backend and its options."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional

from torch import Tensor

from hico_plugin.cameras import Camera
from hico_plugin.config import InstantiateConfig
from hico_plugin.errors import HicoError
from hico_plugin.rasterizer.api import rasterize
from hico_plugin.rasterizer.base import COMPOSITOR, FAR, NEAR, RASTERIZER_BACKENDS, RasterizerBackend, RenderOutputs


@dataclass
class RendererConfig(InstantiateConfig):
    """How Gaussians are rasterized."""

    backend: str = "torch"
    """Rasterizer backend: "torch" (pure torch, CPU or GPU) or "gsplat" (compiled CUDA, extra [cuda])."""
    tile_size: int = 0
    """Tile edge in pixels for binning and compositing; 0 = the compositor's own (16; 4 for the torch
    compositor).
    Outputs do not depend on it, only speed does."""
    near: float = NEAR
    """Gaussians with camera z <= near are culled."""
    far: float = FAR
    """Gaussians with camera z >= far are culled."""
    depth_normal_from: str = "plane_depth"
    """Depth map that depth_normal is derived from: "plane_depth" (PGSR/CityGS-X) or "depth"."""
    compositor: str = COMPOSITOR
    """Blending kernel of the torch backend: "fused" (C++ built on first use, CPU), "torch"
    (vectorised torch, any device) or "auto" (fused on CPU when it builds, else torch)."""
    use_compile: bool = True
    """Fuse the torch compositor with torch.compile (falls back to eager if compilation fails)."""

    def setup(self, **kwargs) -> "Renderer":
        # The backend is bound here, once: unknown names and options fail at build time.
        backend_class = RASTERIZER_BACKENDS.get(self.backend)
        try:
            backend = backend_class(compositor=self.compositor, use_compile=self.use_compile)
        except HicoError as err:
            raise HicoError(f"renderer.{err}") from None
        return Renderer(self, backend)


class Renderer:
    """Renders Gaussians from a Camera with the options of its RendererConfig and its bound backend."""

    def __init__(self, config: RendererConfig, backend: RasterizerBackend):
        self.config = config
        self.backend = backend

    def __call__(self, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                 colors: Tensor, camera: Camera, outputs: Iterable[str] = ("rgb",),
                 background: Optional[Tensor] = None) -> RenderOutputs:
        """means [N,3], quats [N,4], scales [N,3], opacities [N], colors [N,D] -> images [H,W,·]."""
        c = self.config
        return rasterize(
            means, quats, scales, opacities, colors, camera.viewmat.to(means), camera.K.to(means),
            camera.width, camera.height, outputs=outputs, background=background, near=c.near,
            far=c.far, backend=self.backend, tile_size=c.tile_size, depth_normal_from=c.depth_normal_from)
