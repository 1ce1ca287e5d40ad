"""Gaussian rasterization: one functional entry point over backends that project and composite (a
pure-torch tiled one and gsplat's).

    from hico_plugin.rasterizer import rasterize
    out = rasterize(means, quats, scales, opacities, colors, viewmat, K, W, H,
                    outputs=("rgb", "alpha", "normal", "plane_depth", "depth_normal"))
"""

import importlib.util

from hico_plugin.rasterizer.api import rasterize
from hico_plugin.rasterizer.base import (
    DEPTH_NORMAL_SOURCES, OUTPUT_NAMES, RASTERIZER_BACKENDS, RasterizerBackend, RenderOutputs)
from hico_plugin.rasterizer.geometry import depth_to_normal, expected_depth, gaussian_normals, plane_depth
from hico_plugin.rasterizer.projection import Projection, project_gaussians, quat_to_rotmat
from hico_plugin.rasterizer.renderer import Renderer, RendererConfig
from hico_plugin.rasterizer.torch_backend import TorchBackend

# The gsplat backend registers itself on import; it imports without gsplat and fails only when used.
if importlib.util.find_spec("hico_plugin.rasterizer.gsplat_backend") is not None:
    importlib.import_module("hico_plugin.rasterizer.gsplat_backend")

__all__ = [
    "DEPTH_NORMAL_SOURCES", "OUTPUT_NAMES", "Projection", "RASTERIZER_BACKENDS", "RasterizerBackend",
    "RenderOutputs", "Renderer", "RendererConfig", "TorchBackend", "depth_to_normal", "expected_depth", "gaussian_normals",
    "plane_depth", "project_gaussians", "quat_to_rotmat", "rasterize",
]
