"""Live viser viewer built on a render function (nerfview style).

Public API: ``Viewer(config, render_fn, state)`` (or ``ViewerConfig(...).setup(render_fn=..., state=...)``);
``render_fn(camera: Camera, options: RenderOptions) -> np.ndarray uint8 [H, W, 3]``; ``model_render_fn(model:
ViewableModel)``; ``RunViewerState(model, dataset)``; ``viser_to_camera`` / ``camera_to_viser``;
``next_resolution`` (RenderOptions and visualize live in hico_plugin.visualization). In training (rank 0, a
ViewableModel): ``viewer = attach_viewer(trainer, ViewerConfig())``, then ``trainer.train(); viewer.stop()``.
"""

import importlib
from typing import Any

# Each public name and the module that defines it. They are imported on first use (PEP 562), so
# ``hico_plugin.viewer.config`` -- what a training config holds -- loads without viser.
_WHERE = {
    "camera_to_viser": "conversions", "render_size": "conversions", "viser_to_camera": "conversions",
    "RenderFn": "state", "RunViewerState": "state", "TrainingCameras": "state", "ViewableModel": "state",
    "ViewerState": "state", "model_render_fn": "state",
    "next_resolution": "throttle", "plan_render": "throttle",
    "ViewerConfig": "config",
    "Viewer": "viewer", "attach_viewer": "viewer",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
