"""The viewer in a real browser: headless Chromium (Debian package) driven over the DevTools protocol.

Loads the page, waits until the server has seen the client and rendered for it, screenshots, and checks
the picture shows the render (the demo scene's sky colour) and the GUI panel. Set
HICO_VIEWER_SCREENSHOT=path to keep the screenshot.
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
import threading
import time
import urllib.request

import cv2
import numpy as np
import pytest
import websockets.sync.client

from hico_plugin.viewer import RunViewerState, ViewerConfig, model_render_fn
from hico_plugin.viewer.demo import DemoDataset, DemoModel
from helpers_viewer import wait_for

CHROMIUM = next((shutil.which(name) for name in ("chromium", "chromium-browser", "google-chrome") if shutil.which(name)), None)
pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium not installed (apt-get install -y chromium)"),
]
SKY_RGB = np.array([0.75, 0.85, 1.0]) * 255  # DemoModel's background


class DevToolsPage:
    """One Chromium page driven over the DevTools protocol (only what the test needs)."""

    def __init__(self, profile_dir: str, width: int = 1200, height: int = 800):
        self.process = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={profile_dir}", "--remote-debugging-port=0", f"--window-size={width},{height}",
             "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )
        endpoint = self._devtools_endpoint(timeout=60.0)
        pages = json.load(urllib.request.urlopen(f"http://{endpoint}/json/list", timeout=10))
        target = next(page for page in pages if page["type"] == "page")
        self.socket = websockets.sync.client.connect(target["webSocketDebuggerUrl"], max_size=None)
        self._next_id = 0

    def _devtools_endpoint(self, timeout: float) -> str:
        found: list[str] = []
        ready = threading.Event()

        def read_stderr() -> None:  # keep draining: Chromium logs a lot and would block on a full pipe
            for line in self.process.stderr:
                match = re.search(r"DevTools listening on ws://([^/\s]+)/", line)
                if match and not found:
                    found.append(match.group(1))
                    ready.set()

        threading.Thread(target=read_stderr, daemon=True).start()
        if not ready.wait(timeout):
            raise RuntimeError("Chromium did not start its DevTools endpoint")
        return found[0]

    def call(self, method: str, **params):
        self._next_id += 1
        self.socket.send(json.dumps({"id": self._next_id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.socket.recv(timeout=60))
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def screenshot(self) -> np.ndarray:
        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]

    def close(self) -> None:
        self.socket.close()
        self.process.terminate()
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


def _sky_fraction(picture: np.ndarray) -> float:
    return float((np.abs(picture.astype(np.float32) - SKY_RGB).max(axis=-1) < 20).mean())


def test_viewer_in_headless_chromium(tmp_path):
    model, dataset = DemoModel(), DemoDataset(6)
    viewer = ViewerConfig(port=0, max_resolution=384).setup(
        render_fn=model_render_fn(model), state=RunViewerState(model, dataset)
    )
    page = None
    try:
        page = DevToolsPage(str(tmp_path / "profile"))
        page.call("Page.navigate", url=f"http://127.0.0.1:{viewer.port}")
        assert wait_for(lambda: viewer.clients_seen >= 1 and viewer.render_count >= 1, 90.0), "no client / no render"
        picture = None
        for _ in range(30):  # the JPEG reaches the canvas a little after the render
            time.sleep(1.0)
            picture = page.screenshot()
            if _sky_fraction(picture) > 0.05:
                break
        assert picture is not None and viewer.last_error is None
        if os.environ.get("HICO_VIEWER_SCREENSHOT"):
            cv2.imwrite(os.environ["HICO_VIEWER_SCREENSHOT"], picture[..., ::-1])
        assert picture.std() > 20.0, "blank screenshot"
        assert _sky_fraction(picture) > 0.05, "the render is not on the page"
        panel = picture[:, -300:]  # the GUI panel (white) sits on the right
        assert (panel.min(axis=-1) > 240).mean() > 0.2
    finally:
        if page is not None:
            page.close()
        viewer.stop()


