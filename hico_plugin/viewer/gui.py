"""The viewer's control panel: the viser GUI handles, and the render request they describe."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import viser

from hico_plugin.visualization.options import COLORMAP_NAMES, OUTPUT_NAMES, RenderOptions


@dataclass
class ViewerGui:
    """Handles of every control; the viewer wires their callbacks."""

    output: Any
    colormap: Any
    max_resolution: Any
    render_status: Any
    lod_override: Any
    level_range: Any
    distance_scale: Any
    clca: Any
    show_cameras: Any
    show_anchors: Any
    anchor_level_filter: Any
    parent_overlay: Any
    pause: Any
    checkpoint: Any
    stats_folder: Any
    stats_text: Any

    def render_handles(self) -> tuple[Any, ...]:
        """Controls whose change makes every rendered view stale."""
        return (self.output, self.colormap, self.max_resolution, self.lod_override, self.level_range,
                self.distance_scale, self.clca)

    def anchor_handles(self) -> tuple[Any, ...]:
        """Controls whose change redraws the anchor cloud."""
        return (self.show_anchors, self.anchor_level_filter, self.parent_overlay)

    def render_options(self, num_levels: int) -> RenderOptions:
        """The current render request of a model with ``num_levels`` octree levels."""
        level_range = None
        if self.lod_override.value:
            low, high = self.level_range.value
            level_range = (int(low), int(high))
        return RenderOptions(
            output=self.output.value,
            colormap=self.colormap.value,
            max_resolution=int(self.max_resolution.value),
            level_range=level_range,
            distance_scale=float(self.distance_scale.value),
            clca_enabled=bool(self.clca.value),
            num_levels=num_levels,
        )

    def set_num_levels(self, num_levels: int) -> None:
        """Resize both level sliders to 0..num_levels-1 and select every level."""
        top = max(num_levels - 1, 1)
        for slider in (self.level_range, self.anchor_level_filter):
            slider.max = top
            slider.value = (0, top)

    def enable_training_buttons(self, is_training: bool) -> None:
        self.pause.disabled = self.checkpoint.disabled = not is_training


def build_gui(gui: viser.GuiApi, min_resolution: int, max_resolution: int, is_training: bool) -> ViewerGui:
    """Add the viewer's folders and controls to ``gui``."""
    with gui.add_folder("Render"):
        output = gui.add_dropdown("Output", OUTPUT_NAMES, initial_value="rgb", hint="What the live render shows")
        colormap = gui.add_dropdown("Colormap", COLORMAP_NAMES, initial_value="turbo")
        resolution = gui.add_slider(
            "Max resolution", min=min_resolution, max=4096, step=16, initial_value=max_resolution,
            hint="Longest side of the render once the camera stops",
        )
        render_status = gui.add_markdown("_waiting for a browser camera_")
    with gui.add_folder("Level of detail"):
        lod_override = gui.add_checkbox("Override levels", initial_value=False, hint="Draw only the level range below")
        level_range = gui.add_multi_slider("Level range", min=0, max=1, step=1, initial_value=(0, 1))
        distance_scale = gui.add_slider(
            "Distance scale", min=0.1, max=4.0, step=0.05, initial_value=1.0, hint=">1 picks coarser levels, <1 finer"
        )
        clca = gui.add_checkbox("CLCA", initial_value=True, hint="Cross-level context aggregation for this view")
    with gui.add_folder("Scene"):
        show_cameras = gui.add_checkbox("Training cameras", initial_value=True)
        show_anchors = gui.add_checkbox("Anchors", initial_value=True)
        anchor_level_filter = gui.add_multi_slider("Anchor levels", min=0, max=1, step=1, initial_value=(0, 1))
        parent_overlay = gui.add_checkbox(
            "CLCA parent found", initial_value=False,
            hint="Colour anchors green / red by whether CLCA finds a parent context (grey: level 0)")
    with gui.add_folder("Training"):
        pause = gui.add_button("Pause training", disabled=not is_training)
        checkpoint = gui.add_button("Save checkpoint", disabled=not is_training)
    with gui.add_folder("Stats") as stats_folder:
        stats_text = gui.add_markdown("_no statistics yet_")
    return ViewerGui(output, colormap, resolution, render_status, lod_override, level_range, distance_scale, clca,
                     show_cameras, show_anchors, anchor_level_filter, parent_overlay, pause, checkpoint, stats_folder,
                     stats_text)
