"""The camera-path panel driven in headless Chromium on a trained run: open the panel, add a keyframe,
move the view, add another, save; the saved camera_path.json renders with hico-render camera-path.
Set HICO_VIEWER_SCREENSHOT=path to keep a screenshot of the path drawn in the scene."""

from __future__ import annotations

import json
import math
import os
import shutil
import time

import cv2
import numpy as np
import pytest
from viser import transforms as vtf

from hico_plugin.cli import render as render_cli
from hico_plugin.engine import load_run
from hico_plugin.viewer import RunViewerState, ViewerConfig, model_render_fn
from helpers_browser import CHROMIUM, DevToolsPage
from helpers_viewer import wait_for

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium not installed (apt-get install -y chromium)"),
]


def test_camera_path_made_in_the_browser_renders(tiny_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)  # the panel saves into the run's folder
    run = load_run(run_dir / "config.yml")
    viewer = ViewerConfig(port=0, thumbnail_size=0).setup(
        render_fn=model_render_fn(run.model), state=RunViewerState(run.model, run.dataset, run_dir=run_dir))
    panel, page = viewer.camera_path, None
    try:
        page = DevToolsPage(str(tmp_path / "profile"))
        page.call("Page.navigate", url=f"http://127.0.0.1:{viewer.port}")
        assert wait_for(lambda: len(viewer.server.get_clients()) == 1, 90.0), "the page did not connect"
        client = next(iter(viewer.server.get_clients().values()))
        assert wait_for(lambda: page.click_text("Camera path"), 60.0), "no camera path folder"  # unfold it
        assert wait_for(lambda: page.click_text("Add keyframe"), 30.0), "no Add keyframe button"
        assert wait_for(lambda: len(panel.keyframes) == 1, 30.0)
        first = panel.keyframes[0].position.copy()
        # the view moves (as a drag would): the server turns the browser's camera, the browser reports it back
        moved = first + np.array([0.8, -0.4, 0.3])
        with client.atomic():
            client.camera.position = moved
            client.camera.wxyz = vtf.SO3(client.camera.wxyz).multiply(vtf.SO3.from_y_radians(0.3)).wxyz
        assert wait_for(lambda: np.allclose(client.camera.position, moved, atol=1e-4), 30.0)
        time.sleep(0.5)
        assert page.click_text("Add keyframe")
        assert wait_for(lambda: len(panel.keyframes) == 2, 30.0)
        assert np.allclose(panel.keyframes[1].position, moved, atol=1e-3)
        time.sleep(1.0)  # the path and frustums reach the page
        if os.environ.get("HICO_VIEWER_SCREENSHOT"):
            cv2.imwrite(os.environ["HICO_VIEWER_SCREENSHOT"], page.screenshot()[..., ::-1])
        assert page.click_text("Save")
        saved = run_dir / "camera_paths" / "camera_path.json"
        assert wait_for(saved.is_file, 30.0), panel.status.content
        document = json.loads(saved.read_text())
        assert len(document["keyframes"]) == 2 and len(document["camera_path"]) == 61  # 2 s at 30 fps
    finally:
        if page is not None:
            page.close()
        viewer.stop()
    out = render_cli.main(render_cli.parse(["camera-path", "--load-config", str(run_dir / "config.yml"),
                                            "--camera-path", str(saved), "--scale", "0.25",
                                            "--output-dir", str(tmp_path / "renders")]))
    frames = sorted((out / "rgb").iterdir())
    assert len(frames) == 61
    first_frame, last_frame = (cv2.imread(str(frames[i])) for i in (0, -1))
    assert first_frame.std() > 5 and not np.array_equal(first_frame, last_frame)  # a scene, seen from two places
    assert math.isclose(document["fps"], 30.0)
