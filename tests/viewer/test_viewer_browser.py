"""The viewer in a real browser: headless Chromium (Debian package) driven over the DevTools protocol.

Loads the page, waits until the server has seen the client and rendered for it, screenshots, and checks
the picture shows the render (the demo scene's sky colour) and the GUI panel. Set
HICO_VIEWER_SCREENSHOT=path to keep the screenshot.
"""

from __future__ import annotations

import os
import time

import cv2
import numpy as np
import pytest

from hico_plugin.viewer import RunViewerState, ViewerConfig, model_render_fn
from hico_plugin.viewer.demo import DemoDataset, DemoModel
from helpers_browser import CHROMIUM, DevToolsPage
from helpers_viewer import wait_for

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium not installed (apt-get install -y chromium)"),
]
SKY_RGB = np.array([0.75, 0.85, 1.0]) * 255  # DemoModel's background


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


