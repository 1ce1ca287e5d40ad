"""Live viser viewer built on a render function (nerfview style).

Public API::

    Viewer(config: ViewerConfig, render_fn, state)      # or ViewerConfig(...).setup(render_fn=..., state=...)
    render_fn(camera: Camera, options: RenderOptions) -> np.ndarray uint8 [H, W, 3]
    model_render_fn(model: ViewableModel) -> render_fn   # model.render_for_display + visualize
    RunViewerState(model, dataset)                        # ViewerState; trainer.add_callback(state) to go live
    visualize(outputs, options) -> uint8 [H, W, 3]        # and the colormap / normal helpers
    viser_to_camera(wxyz, position, fov_y, width, height) -> Camera; camera_to_viser(camera)
    next_resolution(last_render_seconds, target_seconds, current, minimum, maximum) -> int

Wiring into training (rank 0; the model implements ViewableModel)::

    viewer = attach_viewer(trainer, ViewerConfig())   # RunViewerState as a trainer callback + Viewer
    trainer.train(); viewer.stop()
"""

from hico_plugin.viewer.conversions import camera_to_viser, render_size, viser_to_camera
from hico_plugin.visualization.options import COLORMAP_NAMES, OUTPUT_NAMES, REQUIRED_OUTPUTS, RenderOptions
from hico_plugin.viewer.state import (
    RenderFn,
    RunViewerState,
    TrainingCameras,
    ViewableModel,
    ViewerState,
    model_render_fn,
)
from hico_plugin.viewer.throttle import next_resolution, plan_render
from hico_plugin.viewer.viewer import Viewer, ViewerConfig, attach_viewer
from hico_plugin.visualization.visualize import (
    apply_colormap,
    level_colors,
    normal_disagreement_degrees,
    normalize_percentile,
    normals_to_rgb,
    visualize,
)

__all__ = [
    "COLORMAP_NAMES",
    "OUTPUT_NAMES",
    "REQUIRED_OUTPUTS",
    "RenderFn",
    "RenderOptions",
    "RunViewerState",
    "TrainingCameras",
    "ViewableModel",
    "Viewer",
    "ViewerConfig",
    "ViewerState",
    "apply_colormap",
    "attach_viewer",
    "camera_to_viser",
    "level_colors",
    "model_render_fn",
    "next_resolution",
    "normal_disagreement_degrees",
    "normalize_percentile",
    "normals_to_rgb",
    "plan_render",
    "render_size",
    "viser_to_camera",
    "visualize",
]
