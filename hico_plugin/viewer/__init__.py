"""Live viser viewer built on a render function (nerfview style).

Public API::

    Viewer(config: ViewerConfig, render_fn, state)      # or ViewerConfig(...).setup(render_fn=..., state=...)
    render_fn(camera: Camera, options: RenderOptions) -> np.ndarray uint8 [H, W, 3]
    model_render_fn(model: ViewableModel) -> render_fn   # model.render_for_display + visualize
    RunViewerState(model, dataset)                        # ViewerState; trainer.add_callback(state) to go live
    (RenderOptions and visualize live in hico_plugin.visualization, below the viewer and the CLI)
    viser_to_camera(wxyz, position, fov_y, width, height) -> Camera; camera_to_viser(camera)
    next_resolution(last_render_seconds, target_seconds, current, minimum, maximum) -> int

Wiring into training (rank 0; the model implements ViewableModel)::

    viewer = attach_viewer(trainer, ViewerConfig())   # RunViewerState as a trainer callback + Viewer
    trainer.train(); viewer.stop()
"""

from hico_plugin.viewer.conversions import camera_to_viser, render_size, viser_to_camera
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

__all__ = [
    "RenderFn",
    "RunViewerState",
    "TrainingCameras",
    "ViewableModel",
    "Viewer",
    "ViewerConfig",
    "ViewerState",
    "attach_viewer",
    "camera_to_viser",
    "model_render_fn",
    "next_resolution",
    "plan_render",
    "render_size",
    "viser_to_camera",
]
