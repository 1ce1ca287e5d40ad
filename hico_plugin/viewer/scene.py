"""What the viewer draws in 3D: the training cameras' frustums (with thumbnails) and the anchor cloud."""

from __future__ import annotations

import threading
from typing import Any, Callable

import numpy as np
import viser

from hico_plugin.viewer.conversions import camera_to_viser
from hico_plugin.viewer.gui import ViewerGui
from hico_plugin.viewer.lookup_overlay import parent_found_colors, read_parent_found
from hico_plugin.viewer.state import TrainingCameras, ViewerState, evenly_spaced
from hico_plugin.visualization.visualize import level_colors


def camera_spread(training: TrainingCameras) -> float:
    """Median distance of the training cameras from their mean: the scene's length unit."""
    if len(training.cameras) < 2:
        return 1.0
    centers = training.cameras.centers.double().cpu().numpy()
    spread = float(np.median(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))
    return spread if spread > 1e-9 else 1.0


class ViewerScene:
    """The frustums and anchors of ``state`` in ``server``'s scene, drawn as the ``gui`` asks.

    ``config`` is the ViewerConfig (max_cameras, frustum_scale, thumbnail_size, max_anchor_points,
    anchor_point_size). ``num_levels`` and ``anchors_per_level`` describe the anchors last read.
    """

    def __init__(self, server: viser.ViserServer, config: Any, state: ViewerState, gui: ViewerGui):
        self.server, self.config, self.state, self.gui = server, config, state, gui
        self.training = state.training_cameras(config.max_cameras)
        self.extent = camera_spread(self.training)
        self.anchor_positions = np.zeros((0, 3), np.float32)
        self.anchor_levels = np.zeros((0,), np.int64)
        self.parent_found: np.ndarray | None = None
        self.anchors_per_level = np.zeros((0,), np.int64)
        self.num_levels = 1
        self.anchors_dirty = True
        self.frustums = [self._add_frustum(i, dataset_index) for i, dataset_index in enumerate(self.training.indices)]
        if len(self.training.cameras):
            self._place_initial_camera()
        self.refresh_anchors()

    def _add_frustum(self, position_in_list: int, dataset_index: int) -> Any:
        camera = self.training.cameras[position_in_list]
        wxyz, position, fov_y, aspect = camera_to_viser(camera)
        frustum = self.server.scene.add_camera_frustum(
            f"/training_cameras/{dataset_index:05d}", fov=fov_y, aspect=aspect,
            scale=self.config.frustum_scale * self.extent, thickness=1.5, thickness_units="screen",
            wxyz=wxyz, position=position, color=(40, 90, 200),
        )
        frustum.on_click(lambda event: self.jump_to(event.client, camera))
        return frustum

    def _place_initial_camera(self) -> None:
        # Behind and above the first training view, looking where it looks: the first render shows
        # the scene with that camera's frustum in it rather than from inside the frustum.
        wxyz, position, fov_y, _ = camera_to_viser(self.training.cameras[0])
        rotation = viser.transforms.SO3(wxyz).as_matrix()
        forward, up = rotation[:, 2], -rotation[:, 1]
        initial = self.server.initial_camera
        initial.fov = fov_y
        initial.position = tuple(position + (0.3 * up - 0.5 * forward) * self.extent)
        initial.look_at = tuple(position + forward * self.extent)
        initial.up = tuple(up)

    def jump_to(self, client: viser.ClientHandle, camera: Any) -> None:
        """Move ``client``'s browser camera to a training view (pose and field of view)."""
        wxyz, position, fov_y, _ = camera_to_viser(camera)
        with client.atomic():
            client.camera.fov = fov_y
            client.camera.wxyz = wxyz
            client.camera.position = position

    def load_thumbnails(self, stop: threading.Event, report_error: Callable[[str, Exception], None]) -> None:
        """Put the training images into the frustums (in the background: reading them can be slow)."""
        if self.config.thumbnail_size <= 0:
            return
        for frustum, dataset_index in zip(self.frustums, self.training.indices):
            if stop.is_set():
                return
            try:
                thumbnail = self.state.thumbnail(dataset_index, self.config.thumbnail_size)
            except Exception as err:  # a missing image costs its thumbnail, not the viewer
                report_error(f"thumbnail of view {dataset_index} failed", err)
                continue
            if thumbnail is not None:
                frustum.image = thumbnail

    def set_cameras_visible(self) -> None:
        for frustum in self.frustums:
            frustum.visible = bool(self.gui.show_cameras.value)

    def refresh_anchors(self) -> None:
        """Read the anchors from the model (under the render lock) and rebuild the level sliders."""
        with self.state.render_lock:
            positions, levels = self.state.anchors()
            self.parent_found = read_parent_found(self.state)
        self.anchor_positions = positions.detach().cpu().float().numpy().reshape(-1, 3)
        self.anchor_levels = levels.detach().cpu().long().numpy().reshape(-1)
        num_levels = int(self.anchor_levels.max()) + 1 if len(self.anchor_levels) else 1
        if num_levels != self.num_levels:
            self.num_levels = num_levels
            self.gui.set_num_levels(num_levels)
        self.anchors_per_level = (np.bincount(self.anchor_levels, minlength=num_levels) if len(self.anchor_levels)
                                  else np.zeros(0, int))
        self.anchors_dirty = True

    def draw_anchors(self) -> None:
        self.anchors_dirty = False
        low, high = self.gui.anchor_level_filter.value
        shown = np.nonzero((self.anchor_levels >= low) & (self.anchor_levels <= high))[0]
        shown = shown[evenly_spaced(len(shown), self.config.max_anchor_points)]
        points = self.anchor_positions[shown]
        colors = level_colors(self.anchor_levels[shown], self.num_levels)
        if self.gui.parent_overlay.value and self.parent_found is not None:
            colors = parent_found_colors(self.parent_found[shown], self.anchor_levels[shown])
        if len(points) == 0:  # viser wants at least one point; an empty filter hides the cloud instead
            points, colors = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8)
        self.server.scene.add_point_cloud(
            "/anchors", points=points, colors=colors, point_size=self.config.anchor_point_size * self.extent,
            precision="float32", point_shape="circle", visible=bool(self.gui.show_anchors.value) and len(shown) > 0,
        )
