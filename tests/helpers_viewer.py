"""A websocket client that speaks viser's protocol like a browser, for the viewer's tests."""

from __future__ import annotations

import threading
import time

import msgspec
import viser
import websockets.sync.client


class ProtocolClient:
    """A websocket client that announces a camera like viser's web client (and drains what it gets)."""

    def __init__(self, port: int):
        self.socket = websockets.sync.client.connect(
            f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None
        )
        self.received = 0
        self._reader = threading.Thread(target=self._drain, daemon=True)
        self._reader.start()

    def _drain(self) -> None:
        try:
            while True:
                self.socket.recv()
                self.received += 1
        except Exception:  # closed
            return

    def send_camera(self, wxyz, position, fov=1.0, width=400, height=300) -> None:
        message = {
            "type": "ViewerCameraMessage", "wxyz": tuple(map(float, wxyz)), "position": tuple(map(float, position)),
            "fov": fov, "near": 0.01, "far": 100.0, "image_height": height, "image_width": width,
            "look_at": (0.0, 0.0, 0.0), "up_direction": (0.0, 0.0, 1.0),
        }
        self.socket.send(msgspec.msgpack.encode(message))

    def close(self) -> None:
        self.socket.close()


def wait_for(condition, timeout: float = 30.0) -> bool:
    """Poll ``condition()`` until it holds (True) or ``timeout`` seconds pass (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return False
