"""The viewer's one background thread: renders the browser cameras and keeps the panels current.

It renders the browser cameras (round robin over clients, one render per lock hold) and refreshes the
anchors, stats and plot. While training runs unpaused it waits for the next training step after each
lock hold, so training waits for at most one render per step. GUI and camera callbacks only record
what changed and wake it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from hico_plugin.viewer.conversions import render_size, viser_to_camera
from hico_plugin.viewer.gui import ViewerGui
from hico_plugin.viewer.scene import ViewerScene
from hico_plugin.viewer.state import RenderFn, ViewerState
from hico_plugin.viewer.stats_panel import StatsPanel
from hico_plugin.viewer.throttle import RenderKind, next_resolution, plan_render, refresh_interval

logger = logging.getLogger(__name__)


@dataclass
class ClientView:
    """What one browser shows and what it should show (see ``plan_render``)."""

    client: viser.ClientHandle
    version: int = 1
    rendered_version: int = 0
    rendered_full: bool = False
    rendered_step: int = -1
    last_change_time: float = field(default_factory=time.monotonic)
    notified_errors: set[str] = field(default_factory=set)


class RenderWorker:
    """Renders of ``render_fn`` for every connected browser, and the periodic panel updates.

    ``render_count``, ``last_render_seconds``, ``last_image`` and ``last_error`` report what it did;
    ``config`` is the ViewerConfig (resolutions, timings, jpeg_quality).
    """

    def __init__(self, config: Any, render_fn: RenderFn, state: ViewerState, gui: ViewerGui, scene: ViewerScene,
                 stats: StatsPanel):
        self.config, self.render_fn, self.state = config, render_fn, state
        self.gui, self.scene, self.stats = gui, scene, stats
        self.render_count = 0
        self.last_render_seconds: float | None = None
        self.last_error: str | None = None
        self.last_image: np.ndarray | None = None
        self.clients_seen = 0
        self.views: dict[int, ClientView] = {}
        self.views_lock = threading.Lock()
        self.wake = threading.Event()
        self.stopping = threading.Event()
        self.preview_resolution = config.max_resolution
        self.refresh_resolution = config.max_resolution
        self.next_round_robin = 0
        self.last_model_refresh = -math.inf  # when the view was last re-rendered for training progress
        self.model_refresh_seconds = 0.0  # and how long that render took
        self.thumbnail_thread = threading.Thread(target=scene.load_thumbnails, args=(self.stopping, self.report_error),
                                                 name="hico-viewer-thumbnails", daemon=True)
        self.thread = threading.Thread(target=self._work, name="hico-viewer", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self.stopping.set()
        self.wake.set()
        self.thread.join(timeout=10.0)
        if self.thumbnail_thread.is_alive():
            self.thumbnail_thread.join(timeout=10.0)

    # ------------------------------------------------------------------ clients
    def on_connect(self, client: viser.ClientHandle) -> None:
        with self.views_lock:
            self.views[client.client_id] = ClientView(client)
            self.clients_seen += 1

        def on_camera(_: viser.CameraHandle) -> None:
            with self.views_lock:
                view = self.views.get(client.client_id)
                if view is not None:
                    view.version += 1
                    view.last_change_time = time.monotonic()
            self.wake.set()

        client.camera.on_update(on_camera)
        self.wake.set()

    def on_disconnect(self, client: viser.ClientHandle) -> None:
        with self.views_lock:
            self.views.pop(client.client_id, None)

    def invalidate_views(self) -> None:
        """A render option changed: every view is stale."""
        now = time.monotonic()
        with self.views_lock:
            for view in self.views.values():
                view.version += 1
                view.last_change_time = now
        self.wake.set()

    # ------------------------------------------------------------------ the thread
    def _work(self) -> None:
        self.thumbnail_thread.start()
        last_refresh = -math.inf
        last_anchor_refresh = time.monotonic()
        seen_step = self.state.step
        while not self.stopping.is_set():
            job = self._next_job()
            if job is None:
                self.wake.wait(0.05)
                self.wake.clear()
            now = time.monotonic()
            try:
                if now - last_refresh >= self.config.refresh_seconds:
                    last_refresh = now
                    if self.state.step != seen_step:
                        seen_step = self.state.step
                        if now - last_anchor_refresh >= self.config.anchor_refresh_seconds:
                            last_anchor_refresh = now
                            self.scene.refresh_anchors()
                            self._yield_to_training()
                    self.gui.enable_training_buttons(self.state.is_training)
                    self.stats.update(self.state.stats(), self.state.history(), self.scene.anchors_per_level)
                if self.scene.anchors_dirty:
                    self.scene.draw_anchors()
            except Exception as err:  # a broken panel must not stop renders (nor training)
                self.report_error("viewer update failed", err)
            if job is not None:
                self._render(*job)
                self._yield_to_training()

    def _next_job(self) -> tuple[ClientView, RenderKind, int] | None:
        """The next client view to render (round robin) with its kind and version, if any."""
        now = time.monotonic()
        step = self.state.step
        refresh_due = now - self.last_model_refresh >= refresh_interval(
            self.model_refresh_seconds, self.config.refresh_seconds, self.config.training_render_share
        )
        with self.views_lock:
            views = list(self.views.values())
            for offset in range(len(views)):
                view = views[(self.next_round_robin + offset) % len(views)]
                kind = plan_render(now, view.last_change_time, view.version, view.rendered_version, view.rendered_full,
                                   self.config.settle_seconds, model_changed=refresh_due and view.rendered_step != step)
                if kind is not None:
                    self.next_round_robin = (self.next_round_robin + offset + 1) % len(views)
                    return view, kind, view.version
        return None

    def _yield_to_training(self) -> None:
        """While training runs unpaused, wait for its next step so it never waits for two renders."""
        if not self.state.is_training or self.state.is_paused:
            return
        step = self.state.step
        deadline = time.monotonic() + self.config.max_wait_for_step_seconds
        while (self.state.step == step and time.monotonic() < deadline and not self.stopping.is_set()
               and self.state.is_training and not self.state.is_paused):
            time.sleep(0.005)

    def _render(self, view: ClientView, kind: RenderKind, version: int) -> None:
        options = self.gui.render_options(self.scene.num_levels)
        camera_handle = view.client.camera
        adaptive = {"full": options.max_resolution, "preview": self.preview_resolution, "refresh": self.refresh_resolution}
        longest = min(adaptive[kind], options.max_resolution)
        step = self.state.step
        width, height = render_size(camera_handle.aspect, longest)
        camera = viser_to_camera(camera_handle.wxyz, camera_handle.position, camera_handle.fov, width, height)
        start = time.perf_counter()
        try:
            with self.state.render_lock:
                image = self.render_fn(camera, options)
            image = check_image(image, width, height)
        except Exception as err:
            self.report_error(f"render of '{options.output}' failed", err, view)
            # No retry until something changes.
            view.rendered_version, view.rendered_full, view.rendered_step = version, True, step
            return
        seconds = time.perf_counter() - start
        if kind == "refresh":
            self.last_model_refresh, self.model_refresh_seconds = time.monotonic(), seconds
            self.refresh_resolution = next_resolution(
                seconds, self.config.refresh_render_seconds, longest, self.config.min_resolution, options.max_resolution
            )
        elif kind == "preview":
            self.preview_resolution = next_resolution(
                seconds, 1.0 / self.config.target_preview_fps, longest, self.config.min_resolution, options.max_resolution
            )
        with self.views_lock:
            connected = view.client.client_id in self.views
        if connected:  # the browser may have left during the render
            view.client.scene.set_background_image(image, format="jpeg", jpeg_quality=self.config.jpeg_quality)
        view.rendered_version, view.rendered_step = version, step
        view.rendered_full = kind == "full" or (kind == "refresh" and view.rendered_full)
        self.render_count += 1
        self.last_render_seconds = seconds
        self.last_image = image
        self.last_error = None
        self.gui.render_status.content = f"{options.output}: {width}x{height} ({kind}) in {seconds * 1000:.0f} ms"

    def report_error(self, what: str, err: Exception, view: ClientView | None = None) -> None:
        """Log it with its traceback, show it in the panel, notify the browser once per message."""
        message = f"{type(err).__name__}: {err}"
        logger.error("viewer: %s", what, exc_info=err)
        self.last_error = message
        self.gui.render_status.content = f"**{what}:** `{message}`"
        if view is not None and message not in view.notified_errors:
            view.notified_errors.add(message)
            view.client.add_notification(what, message, color="red", auto_close_seconds=10.0)


def check_image(image: Any, width: int, height: int) -> np.ndarray:
    """The render as uint8 [height, width, 3], or a ValueError saying what render_fn returned."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.shape != (height, width, 3):
        raise ValueError(f"render_fn returned {image.dtype} {image.shape}, expected uint8 ({height}, {width}, 3)")
    return image
