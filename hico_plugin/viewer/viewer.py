"""The live viser viewer: scene (training frustums, anchors), controls, stats, and the render thread.

One background thread does all the work that touches the model: it renders the browser cameras
(round robin over clients, one render per lock hold), refreshes the anchors, stats and plot. While
training runs unpaused it waits for the next training step after each lock hold, so training waits
for at most one render per step. GUI and camera callbacks only record what changed and wake it.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from hico_plugin.config import InstantiateConfig
from hico_plugin.errors import HicoError
from hico_plugin.viewer.conversions import camera_to_viser, render_size, viser_to_camera
from hico_plugin.viewer.lookup_overlay import parent_found_colors, read_parent_found
from hico_plugin.visualization.options import COLORMAP_NAMES, OUTPUT_NAMES, RenderOptions
from hico_plugin.viewer.state import (
    RenderFn,
    RunViewerState,
    TrainingCameras,
    ViewableModel,
    ViewerState,
    evenly_spaced,
    model_render_fn,
)
from hico_plugin.viewer.stats_panel import format_stats_markdown, plot_series
from hico_plugin.viewer.throttle import RenderKind, next_resolution, plan_render, refresh_interval
from hico_plugin.visualization.visualize import level_colors

logger = logging.getLogger(__name__)


@dataclass
class ViewerConfig(InstantiateConfig):
    """Live viser viewer."""

    host: str = "127.0.0.1"
    """Interface to bind; 127.0.0.1 keeps it local (reach it remotely through `ssh -L`), 0.0.0.0 opens it."""
    port: int = 7007
    """First port to try; when busy, viser takes the next free one (the real URL is printed)."""
    max_resolution: int = 512
    """Initial longest side of a settled (full) render, in pixels; adjustable in the GUI."""
    min_resolution: int = 64
    """Smallest longest side of a preview render while the camera moves."""
    target_preview_fps: float = 8.0
    """Preview renders are sized so one takes about 1 / this many seconds."""
    settle_seconds: float = 0.25
    """Time without camera / option changes after which the view is rendered at full resolution."""
    refresh_seconds: float = 1.0
    """While training: how often the stats and plot are refreshed (and at most how often the view is)."""
    training_render_share: float = 0.2
    """While training: the largest share of wall time spent re-rendering the view as the model changes."""
    refresh_render_seconds: float = 1.0
    """While training: model-update re-renders are sized to take about this long (1 s at share 0.2: one every 5 s)."""
    anchor_refresh_seconds: float = 5.0
    """While training: how often the anchor cloud is re-read from the model."""
    max_cameras: int = 100
    """Training cameras drawn as frustums (evenly chosen when there are more)."""
    thumbnail_size: int = 96
    """Longest side of the images drawn in the frustums (0: no images)."""
    frustum_scale: float = 0.08
    """Frustum size as a fraction of the camera spread."""
    max_anchor_points: int = 200_000
    """Anchors drawn at most (evenly subsampled beyond)."""
    anchor_point_size: float = 0.004
    """Anchor point size as a fraction of the camera spread."""
    max_wait_for_step_seconds: float = 2.0
    """Longest the render thread waits for a training step before rendering again anyway."""
    jpeg_quality: int = 85
    """Quality of the JPEG stream of rendered images."""

    def setup(self, **kwargs: Any) -> "Viewer":
        """``setup(render_fn=..., state=...)`` starts the viewer."""
        return Viewer(self, **kwargs)


@dataclass
class _ClientView:
    """What one browser shows and what it should show (see ``plan_render``)."""

    client: viser.ClientHandle
    version: int = 1
    rendered_version: int = 0
    rendered_full: bool = False
    rendered_step: int = -1
    last_change_time: float = field(default_factory=time.monotonic)
    notified_errors: set[str] = field(default_factory=set)


def _validate_config(config: ViewerConfig) -> None:
    if not 0 <= config.port <= 65535:
        raise HicoError(f"viewer.port: expected 0..65535, got {config.port}")
    if not 16 <= config.min_resolution <= config.max_resolution:
        raise HicoError(
            f"viewer.min_resolution / max_resolution: expected 16 <= min <= max, got {config.min_resolution} / {config.max_resolution}"
        )
    if config.target_preview_fps <= 0:
        raise HicoError(f"viewer.target_preview_fps: expected > 0, got {config.target_preview_fps}")
    if not 0.0 < config.training_render_share <= 1.0:
        raise HicoError(f"viewer.training_render_share: expected in (0, 1], got {config.training_render_share}")


class Viewer:
    """viser server showing ``state`` and renders of ``render_fn`` from each browser camera.

    ``url`` / ``port`` hold the address actually bound. ``render_count``, ``last_render_seconds`` and
    ``last_error`` report what the render thread did. ``stop()`` shuts the server and frees the port.
    """

    def __init__(self, config: ViewerConfig, render_fn: RenderFn, state: ViewerState):
        _validate_config(config)
        self.config = config
        self.render_fn = render_fn
        self.state = state
        self.render_count = 0
        self.last_render_seconds: float | None = None
        self.last_error: str | None = None
        self.last_image: np.ndarray | None = None
        self.clients_seen = 0
        self._views: dict[int, _ClientView] = {}
        self._views_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._preview_resolution = config.max_resolution
        self._refresh_resolution = config.max_resolution
        self._anchor_positions = np.zeros((0, 3), np.float32)
        self._anchor_levels = np.zeros((0,), np.int64)
        self._parent_found: np.ndarray | None = None
        self._anchors_per_level = np.zeros((0,), np.int64)
        self._num_levels = 1
        self._anchors_dirty = True
        self._plot_names: tuple[str, ...] = ()
        self._plot: Any = None
        self._next_round_robin = 0
        self._last_model_refresh = -math.inf  # when the view was last re-rendered for training progress
        self._model_refresh_seconds = 0.0  # and how long that render took

        try:
            self.server = viser.ViserServer(host=config.host, port=config.port, label="hico_plugin", verbose=False)
        except OSError as err:
            raise HicoError(f"viewer.host: cannot serve on {config.host}:{config.port} ({err})") from None
        self.port = self.server.get_port()
        shown_host = "localhost" if config.host in ("127.0.0.1", "localhost", "::1") else config.host
        self.url = f"http://{shown_host}:{self.port}"
        try:
            self._training_cameras = state.training_cameras(config.max_cameras)
            self._scene_extent = self._camera_spread(self._training_cameras)
            self._build_gui()
            self._build_scene()
        except BaseException:
            self.server.stop()  # do not leave a half-built server holding the port
            raise
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        self._thumbnail_thread = threading.Thread(target=self._load_thumbnails, name="hico-viewer-thumbnails", daemon=True)
        self._thread = threading.Thread(target=self._work, name="hico-viewer", daemon=True)
        self._thread.start()
        self._announce()

    # ------------------------------------------------------------------ lifecycle
    def _announce(self) -> None:
        print(f"viewer: {self.url}", flush=True)
        if self.config.host in ("127.0.0.1", "localhost", "::1"):
            print(
                f"viewer: on a remote machine, forward the port first: "
                f"ssh -L {self.port}:localhost:{self.port} {socket.gethostname()}",
                flush=True,
            )

    def stop(self) -> None:
        """Stop the render thread and the server (the port is free afterwards)."""
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=10.0)
        if self._thumbnail_thread.is_alive():
            self._thumbnail_thread.join(timeout=10.0)
        self.server.stop()

    def serve_forever(self) -> None:
        """Block until Ctrl-C (for ``hico-view``), then stop."""
        try:
            while not self._stop.wait(1.0):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()

    # ------------------------------------------------------------------ GUI
    def _build_gui(self) -> None:
        gui, config = self.server.gui, self.config
        with gui.add_folder("Render"):
            self._output = gui.add_dropdown("Output", OUTPUT_NAMES, initial_value="rgb", hint="What the live render shows")
            self._colormap = gui.add_dropdown("Colormap", COLORMAP_NAMES, initial_value="turbo")
            self._max_resolution = gui.add_slider(
                "Max resolution", min=config.min_resolution, max=4096, step=16, initial_value=config.max_resolution,
                hint="Longest side of the render once the camera stops",
            )
            self._render_status = gui.add_markdown("_waiting for a browser camera_")
        with gui.add_folder("Level of detail"):
            self._lod_override = gui.add_checkbox("Override levels", initial_value=False, hint="Draw only the level range below")
            self._level_range = gui.add_multi_slider("Level range", min=0, max=1, step=1, initial_value=(0, 1))
            self._distance_scale = gui.add_slider(
                "Distance scale", min=0.1, max=4.0, step=0.05, initial_value=1.0, hint=">1 picks coarser levels, <1 finer"
            )
            self._clca = gui.add_checkbox("CLCA", initial_value=True, hint="Cross-level context aggregation for this view")
        with gui.add_folder("Scene"):
            self._show_cameras = gui.add_checkbox("Training cameras", initial_value=True)
            self._show_anchors = gui.add_checkbox("Anchors", initial_value=True)
            self._anchor_level_filter = gui.add_multi_slider("Anchor levels", min=0, max=1, step=1, initial_value=(0, 1))
            self._parent_overlay = gui.add_checkbox(
                "CLCA parent found", initial_value=False,
                hint="Colour anchors green / red by whether CLCA finds a parent context (grey: level 0)")
        with gui.add_folder("Training"):
            self._pause = gui.add_button("Pause training", disabled=not self.state.is_training)
            self._checkpoint = gui.add_button("Save checkpoint", disabled=not self.state.is_training)
        with gui.add_folder("Stats") as self._stats_folder:
            self._stats_text = gui.add_markdown("_no statistics yet_")

        for handle in (self._output, self._colormap, self._max_resolution, self._lod_override, self._level_range,
                       self._distance_scale, self._clca):
            handle.on_update(lambda _: self._invalidate_views())
        self._show_cameras.on_update(lambda _: self._set_cameras_visible())
        for handle in (self._show_anchors, self._anchor_level_filter, self._parent_overlay):
            handle.on_update(lambda _: self._mark_anchors_dirty())
        self._pause.on_click(lambda _: self._toggle_pause())
        self._checkpoint.on_click(lambda event: self._request_checkpoint(event.client))

    def render_options(self) -> RenderOptions:
        """The GUI's current render request."""
        level_range = None
        if self._lod_override.value:
            low, high = self._level_range.value
            level_range = (int(low), int(high))
        return RenderOptions(
            output=self._output.value,
            colormap=self._colormap.value,
            max_resolution=int(self._max_resolution.value),
            level_range=level_range,
            distance_scale=float(self._distance_scale.value),
            clca_enabled=bool(self._clca.value),
            num_levels=self._num_levels,
        )

    def _toggle_pause(self) -> None:
        paused = not self.state.is_paused
        self.state.set_paused(paused)
        self._pause.label = "Resume training" if paused else "Pause training"

    def _request_checkpoint(self, client: viser.ClientHandle | None) -> None:
        self.state.request_checkpoint()
        if client is not None:
            client.add_notification("Checkpoint", "A checkpoint will be written after this step.", auto_close_seconds=4.0)

    # ------------------------------------------------------------------ scene
    @staticmethod
    def _camera_spread(training: TrainingCameras) -> float:
        """Median distance of the training cameras from their mean: the scene's length unit."""
        if len(training.cameras) < 2:
            return 1.0
        centers = training.cameras.centers.double().cpu().numpy()
        spread = float(np.median(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))
        return spread if spread > 1e-9 else 1.0

    def _build_scene(self) -> None:
        training = self._training_cameras
        self._frustums = []
        for position_in_list, dataset_index in enumerate(training.indices):
            camera = training.cameras[position_in_list]
            wxyz, position, fov_y, aspect = camera_to_viser(camera)
            frustum = self.server.scene.add_camera_frustum(
                f"/training_cameras/{dataset_index:05d}", fov=fov_y, aspect=aspect,
                scale=self.config.frustum_scale * self._scene_extent, thickness=1.5, thickness_units="screen",
                wxyz=wxyz, position=position, color=(40, 90, 200),
            )
            frustum.on_click(lambda event, camera=camera: self.jump_to(event.client, camera))
            self._frustums.append(frustum)
        if len(training.cameras):
            # Behind and above the first training view, looking where it looks: the first render shows
            # the scene with that camera's frustum in it rather than from inside the frustum.
            wxyz, position, fov_y, _ = camera_to_viser(training.cameras[0])
            rotation = viser.transforms.SO3(wxyz).as_matrix()
            forward, up = rotation[:, 2], -rotation[:, 1]
            initial = self.server.initial_camera
            initial.fov = fov_y
            initial.position = tuple(position + (0.3 * up - 0.5 * forward) * self._scene_extent)
            initial.look_at = tuple(position + forward * self._scene_extent)
            initial.up = tuple(up)
        self._anchor_cloud: Any = None
        self._refresh_anchors()

    def jump_to(self, client: viser.ClientHandle, camera: Any) -> None:
        """Move ``client``'s browser camera to a training view (pose and field of view)."""
        wxyz, position, fov_y, _ = camera_to_viser(camera)
        with client.atomic():
            client.camera.fov = fov_y
            client.camera.wxyz = wxyz
            client.camera.position = position

    def _load_thumbnails(self) -> None:
        """Put the training images into the frustums (in the background: reading them can be slow)."""
        if self.config.thumbnail_size <= 0:
            return
        for frustum, dataset_index in zip(self._frustums, self._training_cameras.indices):
            if self._stop.is_set():
                return
            try:
                thumbnail = self.state.thumbnail(dataset_index, self.config.thumbnail_size)
            except Exception as err:  # a missing image costs its thumbnail, not the viewer
                self._report_error(f"thumbnail of view {dataset_index} failed", err)
                continue
            if thumbnail is not None:
                frustum.image = thumbnail

    def _set_cameras_visible(self) -> None:
        for frustum in self._frustums:
            frustum.visible = bool(self._show_cameras.value)

    def _mark_anchors_dirty(self) -> None:
        self._anchors_dirty = True
        self._wake.set()

    def _refresh_anchors(self) -> None:
        """Read the anchors from the model (under the render lock) and rebuild the level sliders."""
        with self.state.render_lock:
            positions, levels = self.state.anchors()
            self._parent_found = read_parent_found(self.state)
        self._anchor_positions = positions.detach().cpu().float().numpy().reshape(-1, 3)
        self._anchor_levels = levels.detach().cpu().long().numpy().reshape(-1)
        num_levels = int(self._anchor_levels.max()) + 1 if len(self._anchor_levels) else 1
        if num_levels != self._num_levels:
            self._num_levels = num_levels
            top = max(num_levels - 1, 1)
            for slider in (self._level_range, self._anchor_level_filter):
                slider.max = top
                slider.value = (0, top)
        self._anchors_per_level = np.bincount(self._anchor_levels, minlength=num_levels) if len(self._anchor_levels) else np.zeros(0, int)
        self._anchors_dirty = True

    def _draw_anchors(self) -> None:
        self._anchors_dirty = False
        low, high = self._anchor_level_filter.value
        shown = np.nonzero((self._anchor_levels >= low) & (self._anchor_levels <= high))[0]
        shown = shown[evenly_spaced(len(shown), self.config.max_anchor_points)]
        points = self._anchor_positions[shown]
        colors = level_colors(self._anchor_levels[shown], self._num_levels)
        if self._parent_overlay.value and self._parent_found is not None:
            colors = parent_found_colors(self._parent_found[shown], self._anchor_levels[shown])
        if len(points) == 0:  # viser wants at least one point; an empty filter hides the cloud instead
            points, colors = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8)
        self._anchor_cloud = self.server.scene.add_point_cloud(
            "/anchors", points=points, colors=colors, point_size=self.config.anchor_point_size * self._scene_extent,
            precision="float32", point_shape="circle", visible=bool(self._show_anchors.value) and len(shown) > 0,
        )

    # ------------------------------------------------------------------ clients
    def _on_connect(self, client: viser.ClientHandle) -> None:
        with self._views_lock:
            self._views[client.client_id] = _ClientView(client)
            self.clients_seen += 1

        def on_camera(_: viser.CameraHandle) -> None:
            with self._views_lock:
                view = self._views.get(client.client_id)
                if view is not None:
                    view.version += 1
                    view.last_change_time = time.monotonic()
            self._wake.set()

        client.camera.on_update(on_camera)
        self._wake.set()

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self._views_lock:
            self._views.pop(client.client_id, None)

    def _invalidate_views(self) -> None:
        """A render option changed: every view is stale."""
        now = time.monotonic()
        with self._views_lock:
            for view in self._views.values():
                view.version += 1
                view.last_change_time = now
        self._wake.set()

    # ------------------------------------------------------------------ the render thread
    def _work(self) -> None:
        self._thumbnail_thread.start()
        last_refresh = -math.inf
        last_anchor_refresh = time.monotonic()
        seen_step = self.state.step
        while not self._stop.is_set():
            job = self._next_job()
            if job is None:
                self._wake.wait(0.05)
                self._wake.clear()
            now = time.monotonic()
            try:
                if now - last_refresh >= self.config.refresh_seconds:
                    last_refresh = now
                    if self.state.step != seen_step:
                        seen_step = self.state.step
                        if now - last_anchor_refresh >= self.config.anchor_refresh_seconds:
                            last_anchor_refresh = now
                            self._refresh_anchors()
                            self._yield_to_training()
                    self._update_stats()
                if self._anchors_dirty:
                    self._draw_anchors()
            except Exception as err:  # a broken panel must not stop renders (nor training)
                self._report_error("viewer update failed", err)
            if job is not None:
                self._render(*job)
                self._yield_to_training()

    def _next_job(self) -> tuple[_ClientView, RenderKind, int] | None:
        """The next client view to render (round robin) with its kind and version, if any."""
        now = time.monotonic()
        step = self.state.step
        refresh_due = now - self._last_model_refresh >= refresh_interval(
            self._model_refresh_seconds, self.config.refresh_seconds, self.config.training_render_share
        )
        with self._views_lock:
            views = list(self._views.values())
            for offset in range(len(views)):
                view = views[(self._next_round_robin + offset) % len(views)]
                kind = plan_render(now, view.last_change_time, view.version, view.rendered_version, view.rendered_full,
                                   self.config.settle_seconds, model_changed=refresh_due and view.rendered_step != step)
                if kind is not None:
                    self._next_round_robin = (self._next_round_robin + offset + 1) % len(views)
                    return view, kind, view.version
        return None

    def _yield_to_training(self) -> None:
        """While training runs unpaused, wait for its next step so it never waits for two renders."""
        if not self.state.is_training or self.state.is_paused:
            return
        step = self.state.step
        deadline = time.monotonic() + self.config.max_wait_for_step_seconds
        while (self.state.step == step and time.monotonic() < deadline and not self._stop.is_set()
               and self.state.is_training and not self.state.is_paused):
            time.sleep(0.005)

    def _render(self, view: _ClientView, kind: RenderKind, version: int) -> None:
        options = self.render_options()
        camera_handle = view.client.camera
        adaptive = {"full": options.max_resolution, "preview": self._preview_resolution, "refresh": self._refresh_resolution}
        longest = min(adaptive[kind], options.max_resolution)
        step = self.state.step
        width, height = render_size(camera_handle.aspect, longest)
        camera = viser_to_camera(camera_handle.wxyz, camera_handle.position, camera_handle.fov, width, height)
        start = time.perf_counter()
        try:
            with self.state.render_lock:
                image = self.render_fn(camera, options)
            image = _check_image(image, width, height)
        except Exception as err:
            self._report_error(f"render of '{options.output}' failed", err, view)
            # No retry until something changes.
            view.rendered_version, view.rendered_full, view.rendered_step = version, True, step
            return
        seconds = time.perf_counter() - start
        if kind == "refresh":
            self._last_model_refresh, self._model_refresh_seconds = time.monotonic(), seconds
            self._refresh_resolution = next_resolution(
                seconds, self.config.refresh_render_seconds, longest, self.config.min_resolution, options.max_resolution
            )
        elif kind == "preview":
            self._preview_resolution = next_resolution(
                seconds, 1.0 / self.config.target_preview_fps, longest, self.config.min_resolution, options.max_resolution
            )
        with self._views_lock:
            connected = view.client.client_id in self._views
        if connected:  # the browser may have left during the render
            view.client.scene.set_background_image(image, format="jpeg", jpeg_quality=self.config.jpeg_quality)
        view.rendered_version, view.rendered_step = version, step
        view.rendered_full = kind == "full" or (kind == "refresh" and view.rendered_full)
        self.render_count += 1
        self.last_render_seconds = seconds
        self.last_image = image
        self.last_error = None
        self._render_status.content = f"{options.output}: {width}x{height} ({kind}) in {seconds * 1000:.0f} ms"

    def _report_error(self, what: str, err: Exception, view: _ClientView | None = None) -> None:
        """Log it with its traceback, show it in the panel, notify the browser once per message."""
        message = f"{type(err).__name__}: {err}"
        logger.error("viewer: %s", what, exc_info=err)
        self.last_error = message
        self._render_status.content = f"**{what}:** `{message}`"
        if view is not None and message not in view.notified_errors:
            view.notified_errors.add(message)
            view.client.add_notification(what, message, color="red", auto_close_seconds=10.0)

    def _update_stats(self) -> None:
        stats = self.state.stats()
        self._stats_text.content = format_stats_markdown(stats, self._anchors_per_level)
        self._pause.disabled = self._checkpoint.disabled = not self.state.is_training
        steps, series = plot_series(self.state.history())
        if len(steps) < 2 or not series:
            return
        names = tuple(series)
        data = (steps, *series.values())
        if names != self._plot_names:  # a series appeared (e.g. PSNR): new plot layout
            if self._plot is not None:
                self._plot.remove()
            self._plot_names = names
            colors = {"loss": "#d9480f", "psnr": "#1c7ed6"}
            with self._stats_folder:
                self._plot = self.server.gui.add_uplot(
                    data,
                    ({"label": "step"}, *({"label": n, "stroke": colors.get(n, "#495057"), "scale": n} for n in names)),
                    axes=({}, *({"scale": n, "side": 3 if i == 0 else 1, "label": n} for i, n in enumerate(names))),
                    aspect=1.6,
                )
        else:
            self._plot.data = data


def attach_viewer(trainer: Any, config: ViewerConfig) -> Viewer:
    """Start a viewer on ``trainer``'s model and dataset and join the run as a callback (rank 0).

    The model must implement ViewableModel. Stop it with ``viewer.stop()`` after ``trainer.train()``.
    """
    if not isinstance(trainer.model, ViewableModel):
        raise HicoError(
            f"vis: model {type(trainer.model).__name__} cannot be viewed "
            "(it needs render_for_display(camera, options) and viewer_anchors()); use --vis none"
        )
    state = RunViewerState(trainer.model, trainer.dataset)
    state.attach(trainer)
    trainer.add_callback(state)
    return Viewer(config, model_render_fn(trainer.model), state)


def _check_image(image: Any, width: int, height: int) -> np.ndarray:
    """The render as uint8 [height, width, 3], or a ValueError saying what render_fn returned."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.shape != (height, width, 3):
        raise ValueError(f"render_fn returned {image.dtype} {image.shape}, expected uint8 ({height}, {width}, 3)")
    return image
