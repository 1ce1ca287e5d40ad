"""The viewer's server end to end, with a websocket client that speaks viser's protocol like a browser."""

from __future__ import annotations

import socket
import threading
import time
from typing import Any

import numpy as np
import pytest
import torch

from hico_plugin.errors import HicoError
from hico_plugin.viewer import TrainingCameras, Viewer, ViewerConfig, viser_to_camera
from hico_plugin.visualization import RenderOptions
from hico_plugin.viewer.demo import orbit_cameras
from helpers_viewer import ProtocolClient, wait_for


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class FakeState:
    """A ViewerState with fixed cameras / anchors; ``step`` advanced by the test's fake trainer."""

    def __init__(self, num_cameras: int = 12, training: bool = False):
        self.render_lock = threading.Lock()
        self.is_training = training
        self.is_paused = False
        self.step = 0
        self.checkpoints = 0
        self.thumbnails_read: list[int] = []
        self.cameras = orbit_cameras(num_cameras)

    def set_paused(self, paused: bool) -> None:
        self.is_paused = paused

    def request_checkpoint(self) -> None:
        self.checkpoints += 1

    def training_cameras(self, max_cameras: int) -> TrainingCameras:
        count = min(max_cameras, len(self.cameras))
        return TrainingCameras(orbit_cameras(count), list(range(count)))

    def thumbnail(self, index: int, size: int) -> np.ndarray:
        self.thumbnails_read.append(index)
        return np.full((size * 3 // 4, size, 3), 40 * index % 255, np.uint8)

    def anchors(self):
        positions = torch.randn(500, 3, generator=torch.Generator().manual_seed(0))
        return positions, torch.arange(500) % 3

    def stats(self) -> dict[str, Any]:
        return {"step": self.step, "loss": 0.5}

    def history(self) -> dict[str, np.ndarray]:
        steps = np.arange(self.step, dtype=np.float64)
        return {"step": steps, "loss": 1.0 / (steps + 1), "psnr": 20 + steps}


class RecordingRender:
    """render_fn that records its calls and paints a gradient (optionally failing or slow)."""

    def __init__(self, fail: bool = False, seconds: float = 0.0, state: FakeState | None = None):
        self.calls: list[tuple[Any, RenderOptions]] = []
        self.steps_at_render: list[int] = []
        self.fail = fail
        self.seconds = seconds
        self.state = state

    def __call__(self, camera, options):
        self.calls.append((camera, options))
        if self.state is not None:
            self.steps_at_render.append(self.state.step)
        if self.fail:
            raise RuntimeError("model exploded")
        time.sleep(self.seconds)
        ramp = np.linspace(0, 255, camera.width, dtype=np.float32).astype(np.uint8)
        return np.repeat(np.repeat(ramp[None, :, None], camera.height, 0), 3, 2)


_LOOK_MINUS_Z = (0.0, 1.0, 0.0, 0.0)  # 180 deg about x: camera z forward = world -z


def test_render_for_displays_a_browser_camera_and_frees_its_port(capsys):
    port = _free_port()
    state = FakeState(num_cameras=12)
    render = RecordingRender()
    viewer = Viewer(ViewerConfig(port=port, max_cameras=5, max_resolution=256, settle_seconds=0.05), render, state)
    client = None
    try:
        assert viewer.port == port and viewer.url == f"http://localhost:{port}"
        printed = capsys.readouterr().out
        assert f"http://localhost:{port}" in printed and f"ssh -L {port}:localhost:{port}" in printed
        assert len(viewer.scene.frustums) == 5 and viewer.scene.num_levels == 3
        assert wait_for(lambda: state.thumbnails_read == [0, 1, 2, 3, 4] and viewer.scene.frustums[-1].image is not None)
        client = ProtocolClient(port)
        client.send_camera(_LOOK_MINUS_Z, (0.5, 0.0, 4.0), fov=0.8, width=400, height=200)
        assert wait_for(lambda: viewer.render_count >= 1 and render.calls[-1][0].width == 256)
        assert viewer.clients_seen == 1 and viewer.last_error is None
        camera, options = render.calls[-1]
        expected = viser_to_camera(np.array(_LOOK_MINUS_Z), np.array([0.5, 0.0, 4.0]), 0.8, 256, 128)
        assert (camera.width, camera.height) == (256, 128)
        assert torch.allclose(camera.viewmat, expected.viewmat, atol=1e-5) and torch.allclose(camera.K, expected.K)
        assert options == viewer.render_options() and options.output == "rgb" and options.clca_enabled
        assert viewer.last_image.shape == (128, 256, 3)
        # A GUI change re-renders with the new options.
        viewer.gui.output.value = "depth"
        assert wait_for(lambda: render.calls[-1][1].output == "depth")
    finally:
        if client is not None:
            client.close()
        viewer.stop()
    with socket.socket() as probe, pytest.raises(ConnectionRefusedError):
        probe.connect(("127.0.0.1", port))
    again = Viewer(ViewerConfig(port=port), RecordingRender(), FakeState())  # the port can be bound again
    try:
        assert again.port == port
    finally:
        again.stop()


def test_bad_viewer_config_is_a_clear_error():
    with pytest.raises(HicoError, match="viewer.training_render_share"):
        Viewer(ViewerConfig(training_render_share=0.0), RecordingRender(), FakeState())
    with pytest.raises(HicoError, match="viewer.min_resolution"):
        Viewer(ViewerConfig(min_resolution=600, max_resolution=512), RecordingRender(), FakeState())


def test_busy_port_moves_to_the_next_one_and_prints_the_real_url(capsys):
    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen()
        busy = blocker.getsockname()[1]
        viewer = Viewer(ViewerConfig(port=busy), RecordingRender(), FakeState())
        try:
            assert viewer.port != busy
            assert f"http://localhost:{viewer.port}" in capsys.readouterr().out
        finally:
            viewer.stop()


def test_render_errors_are_reported_and_rendering_goes_on():
    state = FakeState()
    render = RecordingRender(fail=True)
    viewer = Viewer(ViewerConfig(port=_free_port(), settle_seconds=0.05, max_resolution=128), render, state)
    client = ProtocolClient(viewer.port)
    try:
        client.send_camera(_LOOK_MINUS_Z, (0.0, 0.0, 4.0))
        assert wait_for(lambda: viewer.last_error is not None)
        assert "model exploded" in viewer.last_error and "model exploded" in viewer.gui.render_status.content
        assert viewer.worker.thread.is_alive()
        render.fail = False  # the model recovered: the next camera move renders again
        client.send_camera(_LOOK_MINUS_Z, (0.0, 0.2, 4.0))
        assert wait_for(lambda: viewer.render_count >= 1 and viewer.last_error is None)
        assert viewer.worker.thread.is_alive()
    finally:
        client.close()
        viewer.stop()


def test_training_waits_for_at_most_one_render_per_step():
    state = FakeState(training=True)
    render = RecordingRender(seconds=0.02, state=state)
    viewer = Viewer(ViewerConfig(port=_free_port(), settle_seconds=10.0, max_resolution=64, min_resolution=32), render, state)
    stop = threading.Event()

    def train() -> None:
        while not stop.is_set():
            with state.render_lock:
                time.sleep(0.01)  # the training step
            state.step += 1

    trainer = threading.Thread(target=train)
    client = ProtocolClient(viewer.port)
    try:
        trainer.start()
        for i in range(60):  # a moving camera asks for a render all the time
            client.send_camera(_LOOK_MINUS_Z, (0.0, 0.01 * i, 4.0))
            time.sleep(0.02)
        assert wait_for(lambda: len(render.steps_at_render) >= 5)
    finally:
        stop.set()
        trainer.join()
        client.close()
        viewer.stop()
    steps = render.steps_at_render
    assert all(later > earlier for earlier, later in zip(steps, steps[1:])), steps  # never two renders per step
    assert state.step > len(steps)
