"""The camera-path panel on a live viewer, with a websocket client standing in for the browser: keyframes
at the client's camera, edited, reordered, deleted, saved as camera_path.json in the run's folder and
loaded back; the saved frames are the panel's path in the dataset's source frame."""

from __future__ import annotations

import json
import math
import socket

import numpy as np
import pytest
import torch
from viser import transforms as vtf

from hico_plugin.data.transform import SceneTransform, rotation_about_z
from hico_plugin.errors import HicoError
from hico_plugin.export.camera_path_file import read_camera_path
from hico_plugin.viewer import RunViewerState, ViewerConfig, model_render_fn
from hico_plugin.viewer.demo import DemoDataset, DemoModel
from helpers_viewer import ProtocolClient, wait_for


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture
def live(tmp_path):
    dataset = DemoDataset(8)
    dataset.transform = SceneTransform(torch.tensor([5.0, 1.0, -2.0], dtype=torch.float64), 0.5, rotation_about_z(0.3))
    model = DemoModel()
    state = RunViewerState(model, dataset, run_dir=tmp_path)
    viewer = ViewerConfig(port=_free_port(), thumbnail_size=0).setup(render_fn=model_render_fn(model), state=state)
    client = ProtocolClient(viewer.port)
    try:
        client.send_camera((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 3.0))  # viser counts a client once it has a camera
        assert wait_for(lambda: len(viewer.server.get_clients()) == 1)
        yield viewer, client, next(iter(viewer.server.get_clients().values()))
    finally:
        client.close()
        viewer.stop()


def _stand_at(client, handle, position, yaw: float) -> None:
    """The 'browser' moves its camera; wait until the server has it."""
    wxyz = vtf.SO3.from_z_radians(yaw).multiply(vtf.SO3.from_x_radians(-math.pi / 2)).wxyz
    client.send_camera(wxyz, position, fov=math.radians(50))
    assert wait_for(lambda: np.allclose(handle.camera.position, position, atol=1e-6))


def test_keyframes_edit_save_and_load(live, tmp_path):
    viewer, client, handle = live
    panel = viewer.camera_path
    spots = [(3.0, 0.0, 1.0), (0.0, 3.0, 1.2), (-3.0, 0.0, 1.4)]
    for i, spot in enumerate(spots):
        _stand_at(client, handle, spot, yaw=i * math.pi / 2)
        panel.add(handle)
    assert [k.position.tolist() for k in panel.keyframes] == [list(s) for s in spots]
    assert panel.keyframes[0].fov_deg == pytest.approx(50) and panel.choice.options == ("1", "2", "3")
    assert panel.status.content == "3 keyframes, 4.0 s"  # two transitions of 2 s
    # select the second, give it 1 s and a wider lens, move it to the end, then back
    panel.choice.value = "2"
    panel._select_from_gui()
    panel.seconds.value, panel.fov.value = 1.0, 70.0
    panel._edit_selected()
    assert (panel.keyframes[1].seconds, panel.keyframes[1].fov_deg) == (1.0, 70.0)
    panel.shift_selected(1)
    assert [k.position[1] for k in panel.keyframes] == [0.0, 0.0, 3.0] and panel.selected == 2
    panel.shift_selected(-1)
    # a fourth keyframe, then moved and deleted
    _stand_at(client, handle, (0.0, -3.0, 1.0), yaw=0.2)
    panel.add(handle)  # after the selected (second) one
    assert [k.position[1] for k in panel.keyframes] == [0.0, 3.0, -3.0, 0.0]
    _stand_at(client, handle, (0.5, -2.5, 1.0), yaw=0.2)
    panel.move_selected(handle)
    assert panel.keyframes[2].position.tolist() == [0.5, -2.5, 1.0]
    panel.delete_selected()
    assert len(panel.keyframes) == 3
    panel.fps.value = 10
    frames = panel.frames()
    assert len(frames) == 31  # 2 s + 1 s at 10 fps, both ends included
    # Play flies the client's camera along the frames, ending at the last
    panel.play(handle)
    end = frames.centers[-1].double().numpy()
    assert wait_for(lambda: np.allclose(handle.camera.position, end, atol=1e-4), 30.0)
    # saved in the run's camera_paths/, in the source frame: read back, they are the panel's frames
    panel.file_name.value = "fly"
    saved = panel.save()
    assert saved == tmp_path / "camera_paths" / "fly.json"
    read, fps = read_camera_path(saved, viewer.state.scene_transform)
    assert fps == 10 and torch.allclose(read.viewmats, frames.viewmats, atol=1e-4)
    document = json.loads(saved.read_text())
    assert len(document["keyframes"]) == 3 and document["keyframes"][1]["override_transition_sec"] == 1.0
    source_centres = viewer.state.scene_transform.points_to_colmap(frames.centers.double())
    written = torch.tensor(document["camera_path"][5]["camera_to_world"], dtype=torch.float64).view(4, 4)[:3, 3]
    assert torch.allclose(written, source_centres[5], atol=1e-4)
    # loading replaces the keyframes by the file's
    before = [(k.position.copy(), k.fov_deg, k.seconds) for k in panel.keyframes]
    panel.delete_selected()
    panel.load()
    assert len(panel.keyframes) == 3
    for (position, fov, seconds), keyframe in zip(before, panel.keyframes):
        assert np.allclose(keyframe.position, position, atol=1e-5)
        assert keyframe.fov_deg == pytest.approx(fov, abs=1e-3) and keyframe.seconds == seconds


def test_a_file_name_that_leaves_the_folder_is_refused(live):
    viewer, _, handle = live
    panel = viewer.camera_path
    with pytest.raises(HicoError, match="add a keyframe first"):
        panel.save()
    panel.add(handle)
    for name in ("../escape.json", "/tmp/x.json", ".hidden", ""):
        panel.file_name.value = name
        with pytest.raises(HicoError, match="not a plain file name"):
            panel.save()
