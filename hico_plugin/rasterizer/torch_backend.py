"""The backend registered as "torch": projection, tile binning and blending by the fused C++ CPU kernels
or their torch twins (any device). The fused projection runs exactly when the fused compositor does (and
it takes the inputs: viewmats and Ks without a gradient); otherwise the torch reference."""

from __future__ import annotations

import torch
from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.rasterizer.base import RASTERIZER_BACKENDS, TILE_SIZE, RasterizerBackend
from hico_plugin.rasterizer.composite import composite
from hico_plugin.rasterizer.fused import EXTENSION, bin_gaussians_fused, composite_fused, fused_available
from hico_plugin.rasterizer.projection import Projection, project_gaussians
from hico_plugin.rasterizer.projection_fused import (
    project_gaussians_fused, projection_fused_accepts, projection_fused_available)
from hico_plugin.rasterizer.tiling import TileBins, bin_gaussians

# The vectorised torch compositor evaluates every pixel of a tile against every Gaussian binned to
# it, so small tiles waste fewer pairs on the few-pixel Gaussians of real renders. The fused CPU
# compositor rejects a far pair before its exp and stops each pixel early, so tile size barely
# matters to it and the common 16 keeps the fewest intersections (timings: benchmarks/RESULTS.md).
TORCH_COMPOSITOR_TILE_SIZE = 4


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


@RASTERIZER_BACKENDS.register("torch")
class TorchBackend(RasterizerBackend):
    """Pure torch (plus the optional fused C++ projection and blending on CPU); float32 and float64."""

    def project(self, means, quats, scales, opacities, viewmats, Ks, width, height, near, far, *,
                normals=False) -> Projection:
        gaussians = (means, quats, scales, opacities, viewmats, Ks)
        if (use_fused(self.compositor, means.device) and projection_fused_accepts(*gaussians)
                and projection_fused_available()):
            return project_gaussians_fused(*gaussians, width, height, near, far, normals=normals)
        return project_gaussians(*gaussians, width, height, near, far)

    def composite(self, projected: Projection, means2d, opacities, features, width, height, tile_size):
        num_cams, n = means2d.shape[:2]
        fused = use_fused(self.compositor, means2d.device)
        bin_fn = bin_gaussians_fused if fused else bin_gaussians
        bins = bin_fn(means2d, projected.conics, projected.reach, projected.extents, projected.depths,
                      projected.radii, width, height, tile_size)
        flat = (means2d.reshape(-1, 2), projected.conics.reshape(-1, 3),
                opacities[None].expand(num_cams, -1).reshape(-1),
                features.reshape(num_cams * n, features.shape[-1]))
        if fused:
            image, alpha = composite_fused(*flat, bins, image_size=(width, height))
            return image, alpha[..., None]
        tiled, tiled_alpha = composite(*flat, bins, use_compile=self.use_compile)
        image = _untile(torch.cat([tiled, tiled_alpha[..., None]], -1), num_cams, bins, width, height)
        return image[..., :-1], image[..., -1:]

    def default_tile_size(self, device: torch.device) -> int:
        return TILE_SIZE if use_fused(self.compositor, device) else TORCH_COMPOSITOR_TILE_SIZE

    def uses_fused_kernels(self, device: torch.device) -> bool:
        return use_fused(self.compositor, device)


def _untile(tiled: Tensor, num_cams: int, bins: TileBins, width: int, height: int) -> Tensor:
    """[T,P,D] tiles (camera-major, row-major) -> [C,H,W,D] images, cropped to the image size."""
    ts = bins.tile_size
    image = tiled.reshape(num_cams, bins.tiles_y, bins.tiles_x, ts, ts, -1)
    image = image.permute(0, 1, 3, 2, 4, 5).reshape(num_cams, bins.tiles_y * ts, bins.tiles_x * ts, -1)
    return image[:, :height, :width]
