"""Rendering for people: what a person asks to see (``RenderOptions``: output, colormap, levels, CLCA
on/off) and how render outputs become pictures (``visualize``). Shared by the viewer and by
hico-eval / hico-render / hico-export, so it sits below both; a model draws a request with
``render_for_display(camera, options)``."""

from hico_plugin.visualization.options import COLORMAP_NAMES, OUTPUT_NAMES, REQUIRED_OUTPUTS, RenderOptions
from hico_plugin.visualization.visualize import (
    apply_colormap,
    level_colors,
    normal_disagreement_degrees,
    normalize_percentile,
    normals_to_rgb,
    visualize,
)

__all__ = [
    "COLORMAP_NAMES", "OUTPUT_NAMES", "REQUIRED_OUTPUTS", "RenderOptions", "apply_colormap", "level_colors",
    "normal_disagreement_degrees", "normalize_percentile", "normals_to_rgb", "visualize",
]
