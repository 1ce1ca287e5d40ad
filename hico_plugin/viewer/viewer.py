"""The live viser viewer: its config, and the server that joins its parts.

gui.py builds the controls, scene.py draws the training frustums and the anchors, render_worker.py is
the one background thread that touches the model (renders, panel refreshes), stats_panel.py shows the
training stats and plot, camera_path_panel.py makes camera paths for videos.
"""

from __future__ import annotations

import socket
from typing import Any

import numpy as np
import viser

from hico_plugin.data.transform import SceneTransform
from hico_plugin.errors import HicoError
from hico_plugin.viewer.camera_path_panel import CameraPathPanel
from hico_plugin.viewer.config import ViewerConfig, validate_viewer_config
from hico_plugin.viewer.gui import build_gui
from hico_plugin.viewer.render_worker import RenderWorker
from hico_plugin.viewer.scene import ViewerScene
from hico_plugin.viewer.state import RenderFn, RunViewerState, ViewableModel, ViewerState, model_render_fn
from hico_plugin.viewer.stats_panel import StatsPanel
from hico_plugin.visualization.options import RenderOptions


class Viewer:
    """viser server showing ``state`` and renders of ``render_fn`` from each browser camera.

    ``url`` / ``port`` hold the address actually bound; ``gui``, ``scene``, ``stats`` and ``worker``
    are its parts. ``render_count``, ``last_render_seconds``, ``last_image`` and ``last_error`` report
    what the render thread did. ``stop()`` shuts the server and frees the port.
    """

    def __init__(self, config: ViewerConfig, render_fn: RenderFn, state: ViewerState):
        validate_viewer_config(config)
        self.config = config
        self.state = state
        try:
            self.server = viser.ViserServer(host=config.host, port=config.port, label="hico_plugin", verbose=False)
        except OSError as err:
            raise HicoError(f"viewer.host: cannot serve on {config.host}:{config.port} ({err})") from None
        self.port = self.server.get_port()
        shown_host = "localhost" if config.host in ("127.0.0.1", "localhost", "::1") else config.host
        self.url = f"http://{shown_host}:{self.port}"
        try:
            self.gui = build_gui(self.server.gui, config.min_resolution, config.max_resolution, state.is_training)
            self.scene = ViewerScene(self.server, config, state, self.gui)
        except BaseException:
            self.server.stop()  # do not leave a half-built server holding the port
            raise
        first = self.scene.training.cameras[0] if len(self.scene.training.cameras) else None
        self.camera_path = CameraPathPanel(
            self.server, getattr(state, "scene_transform", None) or SceneTransform.identity(),
            getattr(state, "camera_path_dir", None), self.scene.extent,
            (first.width, first.height) if first is not None else (1280, 720))
        self.stats = StatsPanel(self.server.gui, self.gui.stats_folder, self.gui.stats_text)
        self.worker = RenderWorker(config, render_fn, state, self.gui, self.scene, self.stats)
        self._wire_gui()
        self.server.on_client_connect(self.worker.on_connect)
        self.server.on_client_disconnect(self.worker.on_disconnect)
        self.worker.start()
        self._announce()

    def _wire_gui(self) -> None:
        for handle in self.gui.render_handles():
            handle.on_update(lambda _: self.worker.invalidate_views())
        self.gui.show_cameras.on_update(lambda _: self.scene.set_cameras_visible())
        for handle in self.gui.anchor_handles():
            handle.on_update(lambda _: self._mark_anchors_dirty())
        self.gui.pause.on_click(lambda _: self.toggle_pause())
        self.gui.checkpoint.on_click(lambda event: self.request_checkpoint(event.client))

    def _announce(self) -> None:
        print(f"viewer: {self.url}", flush=True)
        if self.config.host in ("127.0.0.1", "localhost", "::1"):
            print(
                f"viewer: on a remote machine, forward the port first: "
                f"ssh -L {self.port}:localhost:{self.port} {socket.gethostname()}",
                flush=True,
            )

    @property
    def render_count(self) -> int:
        return self.worker.render_count

    @property
    def last_render_seconds(self) -> float | None:
        return self.worker.last_render_seconds

    @property
    def last_image(self) -> np.ndarray | None:
        return self.worker.last_image

    @property
    def last_error(self) -> str | None:
        return self.worker.last_error

    @property
    def clients_seen(self) -> int:
        return self.worker.clients_seen

    def render_options(self) -> RenderOptions:
        """The GUI's current render request."""
        return self.gui.render_options(self.scene.num_levels)

    def toggle_pause(self) -> None:
        paused = not self.state.is_paused
        self.state.set_paused(paused)
        self.gui.pause.label = "Resume training" if paused else "Pause training"

    def request_checkpoint(self, client: viser.ClientHandle | None) -> None:
        self.state.request_checkpoint()
        if client is not None:
            client.add_notification("Checkpoint", "A checkpoint will be written after this step.", auto_close_seconds=4.0)

    def _mark_anchors_dirty(self) -> None:
        self.scene.anchors_dirty = True
        self.worker.wake.set()

    def stop(self) -> None:
        """Stop the render thread and the server (the port is free afterwards)."""
        self.worker.stop()
        self.server.stop()


def attach_viewer(trainer: Any, config: ViewerConfig) -> Viewer:
    """Start a viewer on ``trainer``'s model and dataset and join the run as a callback (rank 0).

    The model must implement ViewableModel. Stop it with ``viewer.stop()`` after ``trainer.train()``.
    """
    if not isinstance(trainer.model, ViewableModel):
        raise HicoError(
            f"vis: model {type(trainer.model).__name__} cannot be viewed "
            "(it needs render_for_display(camera, options) and viewer_anchors()); use --vis none"
        )
    state = RunViewerState(trainer.model, trainer.dataset, run_dir=trainer.run_dir)
    state.attach(trainer)
    trainer.add_callback(state)
    return Viewer(config, model_render_fn(trainer.model), state)
