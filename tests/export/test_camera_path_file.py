"""nerfstudio camera_path.json: known poses, the round trip through the source frame, nerfstudio's own
frame, and one line naming the key of every malformed file."""

from __future__ import annotations

import json
import math

import pytest
import torch

from hico_plugin.cameras import Cameras
from hico_plugin.data.transform import SceneTransform, rotation_about_z, rotation_to_z
from hico_plugin.errors import HicoError
from hico_plugin.export.camera_path_file import (keyframe_entries, nerfstudio_transform, read_camera_path,
                                                  read_keyframes, write_camera_path)

TURNED = SceneTransform(torch.tensor([3.0, -2.0, 10.0], dtype=torch.float64), 0.25,
                        rotation_about_z(0.7) @ rotation_to_z(torch.tensor([0.3, -0.2, 0.93], dtype=torch.float64) /
                                                              math.sqrt(0.3**2 + 0.2**2 + 0.93**2)))


def _document(**overrides):
    frame = {"camera_to_world": [1, 0, 0, 1, 0, 1, 0, 2, 0, 0, 1, 3, 0, 0, 0, 1], "fov": 90.0, "aspect": 2.0}
    return {"camera_type": "perspective", "render_width": 200, "render_height": 100, "fps": 24,
            "camera_path": [frame], **overrides}


def _write(tmp_path, document, name="camera_path.json"):
    path = tmp_path / name
    path.write_text(json.dumps(document))
    return path


def test_a_known_pose_maps_to_the_opencv_viewmat(tmp_path):
    cameras, fps = read_camera_path(_write(tmp_path, _document()), SceneTransform.identity())
    assert fps == 24 and len(cameras) == 1 and int(cameras.widths[0]) == 200 and int(cameras.heights[0]) == 100
    # OpenGL camera at (1, 2, 3) looking down -z, y up -> OpenCV: y and z flipped, viewmat = inverse
    expected = torch.tensor([[1.0, 0, 0, -1], [0, -1, 0, 2], [0, 0, -1, 3], [0, 0, 0, 1]])
    assert torch.allclose(cameras.viewmats[0], expected)
    assert cameras.Ks[0].tolist() == [[50.0, 0.0, 100.0], [0.0, 50.0, 50.0], [0.0, 0.0, 1.0]]  # fov 90: f = h / 2


def test_write_then_read_gives_the_same_cameras_in_a_turned_scaled_frame(tmp_path):
    gen = torch.Generator().manual_seed(0)
    rotations = torch.linalg.qr(torch.randn(5, 3, 3, generator=gen, dtype=torch.float64))[0]
    rotations = rotations * torch.det(rotations)[:, None, None]  # proper rotations
    viewmats = torch.eye(4, dtype=torch.float64).repeat(5, 1, 1)
    viewmats[:, :3, :3], viewmats[:, :3, 3] = rotations, torch.randn(5, 3, generator=gen, dtype=torch.float64)
    Ks = torch.tensor([[80.0, 0, 64], [0, 80.0, 48], [0, 0, 1]]).repeat(5, 1, 1)
    cameras = Cameras(viewmats.float(), Ks, torch.full((5,), 128), torch.full((5,), 96))
    path = write_camera_path(tmp_path / "path.json", cameras, TURNED, fps=30, keyframes=[{"fov": 60}], is_cycle=False)
    document = json.loads(path.read_text())
    assert document["keyframes"] == [{"fov": 60}] and document["is_cycle"] is False and document["seconds"] == 5 / 30
    back, fps = read_camera_path(path, TURNED)
    assert fps == 30 and torch.allclose(back.viewmats, cameras.viewmats, atol=1e-5)
    assert torch.allclose(back.Ks, Ks, atol=1e-4)
    # the file holds source-frame poses: another run's normalisation reads the same places
    centres = TURNED.points_to_colmap(cameras.centers.double())
    written = torch.tensor([f["camera_to_world"] for f in document["camera_path"]], dtype=torch.float64).view(5, 4, 4)
    assert torch.allclose(written[:, :3, 3], centres, atol=1e-5)


def test_a_nerfstudio_frame_file_maps_to_the_source_frame(tmp_path):
    source = read_camera_path(_write(tmp_path, _document()), TURNED)[0]
    # nerfstudio's frame: x_ns = scale * (T @ [x; 1]); poses move with it, translations scaled
    transform = torch.cat([rotation_about_z(0.4), torch.tensor([[0.5], [-1.0], [2.0]], dtype=torch.float64)], 1)
    scale = 0.2
    c2w = torch.tensor(_document()["camera_path"][0]["camera_to_world"], dtype=torch.float64).view(4, 4)
    moved = torch.eye(4, dtype=torch.float64)
    moved[:3] = transform @ c2w
    moved[:3, 3] *= scale
    ns_file = _write(tmp_path, _document(camera_path=[{"camera_to_world": moved.flatten().tolist(), "fov": 90.0}]), "ns.json")
    ns_transforms = _write(tmp_path, {"transform": transform.tolist(), "scale": scale}, "dataparser_transforms.json")
    from_ns = read_camera_path(ns_file, TURNED, nerfstudio_transform(ns_transforms))[0]
    assert torch.allclose(from_ns.viewmats, source.viewmats, atol=1e-5)


BAD = {
    "null camera_path": (_document(camera_path=None), "camera_path: expected a non-empty list"),
    "no fps": ({k: v for k, v in _document().items() if k != "fps"}, "missing key 'fps'"),
    "fisheye": (_document(camera_type="fisheye"), "camera_type: only 'perspective'"),
    "short matrix": (_document(camera_path=[{"camera_to_world": [1, 0, 0], "fov": 50}]),
                     "camera_path[0].camera_to_world: expected 16 numbers (4x4), got 3"),
    "string in matrix": (_document(camera_path=[{"camera_to_world": ["a"] * 16, "fov": 50}]),
                         "camera_path[0].camera_to_world[0]: expected a finite number"),
    "not a rotation": (_document(camera_path=[{"camera_to_world": [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
                                               "fov": 50}]), "camera_path[0].camera_to_world: its 3x3 part is not a rotation"),
    "fov out of range": (_document(camera_path=[{"camera_to_world": _document()["camera_path"][0]["camera_to_world"],
                                                 "fov": 180}]), "camera_path[0].fov: expected a vertical field of view"),
    "no fov": (_document(camera_path=[{"camera_to_world": [1] * 16}]), "camera_path[0]: expected an object with"),
    "negative width": (_document(render_width=-5), "render_width: expected a number > 0"),
    "fractional height": (_document(render_height=10.5), "expected whole pixels"),
    "nan fps": (_document() | {"fps": float("nan")}, "fps: expected a finite number"),
    "a list": ([1, 2], "expected a JSON object"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_each_malformed_file_is_one_line_naming_the_key(tmp_path, case):
    document, message = BAD[case]
    with pytest.raises(HicoError) as error:
        read_camera_path(_write(tmp_path, document), SceneTransform.identity())
    assert message in str(error.value) and "\n" not in str(error.value)


def test_not_json_and_too_large_are_refused(tmp_path, monkeypatch):
    path = tmp_path / "camera_path.json"
    path.write_text("{not json")
    with pytest.raises(HicoError, match="not a camera_path.json"):
        read_camera_path(path, SceneTransform.identity())
    monkeypatch.setattr("hico_plugin.export.camera_path_file.MAX_FILE_BYTES", 4)
    path.write_text(json.dumps(_document()))
    with pytest.raises(HicoError, match="too large"):
        read_camera_path(path, SceneTransform.identity())


def test_keyframes_round_trip_with_their_transitions(tmp_path):
    cameras = read_camera_path(_write(tmp_path, _document(camera_path=[
        {"camera_to_world": [1, 0, 0, x, 0, 1, 0, 0, 0, 0, 1, 5, 0, 0, 0, 1], "fov": 40.0 + 10 * x} for x in range(3)])),
        TURNED)[0]
    path = write_camera_path(tmp_path / "keys.json", cameras, TURNED, fps=24,
                             keyframes=keyframe_entries(cameras, torch.tensor([1.5, 0.5, 2.0]), TURNED), is_cycle=True)
    keys, seconds, fps, loop = read_keyframes(path, TURNED)
    assert torch.allclose(keys.viewmats, cameras.viewmats, atol=1e-5) and torch.allclose(keys.Ks, cameras.Ks, atol=1e-3)
    assert seconds.tolist() == [1.5, 0.5, 2.0] and fps == 24 and loop is True
    # nerfstudio's panel leaves most keyframes on the default transition
    document = json.loads(path.read_text())
    document["keyframes"][1]["override_transition_enabled"] = False
    document["default_transition_sec"] = 3.0
    assert read_keyframes(_write(tmp_path, document, "ns_keys.json"), TURNED)[1].tolist() == [1.5, 3.0, 2.0]
    with pytest.raises(HicoError, match="keyframes: expected a non-empty list"):
        read_keyframes(_write(tmp_path, _document(), "no_keys.json"), TURNED)
