"""The COLMAP model reader against pycolmap: every field of generated models, binary and text, with and
without rigs, as pycolmap reads them."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from hico_plugin.data.colmap import read_colmap_model
from hico_plugin.errors import HicoError
from hico_plugin.scenes.generate import generate_scene
from hico_plugin.scenes.ring_dataset import write_ring_dataset


def assert_reads_like_pycolmap(model_dir) -> None:
    ours = read_colmap_model(model_dir)
    theirs = pycolmap.Reconstruction(str(model_dir))
    images = sorted((image for image in theirs.images.values() if image.has_pose), key=lambda image: image.name)
    assert ours.names == [image.name for image in images]
    assert ours.camera_ids == [image.camera_id for image in images]
    assert sorted(ours.cameras) == sorted({image.camera_id for image in images})
    for camera_id, camera in ours.cameras.items():
        expected = theirs.cameras[camera_id].todict()
        expected["model"] = expected["model"].name
        assert camera.todict().keys() == expected.keys()
        for key, value in expected.items():
            assert np.array_equal(camera.todict()[key], value), key
    viewmats = np.stack([image.cam_from_world().matrix() for image in images])
    assert ours.viewmats.dtype == np.float64 and np.allclose(ours.viewmats[:, 3], [0, 0, 0, 1])
    assert np.abs(ours.viewmats[:, :3] - viewmats).max() < 1e-12
    points = [theirs.points3D[point_id] for point_id in sorted(theirs.points3D)]
    assert np.array_equal(ours.points, np.array([point.xyz for point in points]).reshape(-1, 3))
    assert np.array_equal(ours.point_colors, np.array([point.color for point in points], np.uint8).reshape(-1, 3))
    assert len(ours.tracks) == len(points) and ours.tracks.points is ours.points
    view_of_image = {image.image_id: view for view, image in enumerate(images)}
    for stride in (1, 3):
        expected = [(view_of_image[element.image_id], row) for row, point in enumerate(points[::stride])
                    for element in point.track.elements if element.image_id in view_of_image]
        views, rows = ours.tracks.observations(stride)
        assert views.dtype == rows.dtype == np.int64
        assert list(zip(views.tolist(), rows.tolist())) == expected


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The tiny built-in scene: a binary model with keypoints and tracks."""
    return generate_scene("tiny", tmp_path_factory.mktemp("colmap") / "scene")


@pytest.mark.parametrize("text", [False, True])
def test_generated_scene_reads_like_pycolmap(scene, tmp_path, text):
    model_dir = scene / "sparse" / "0"
    if text:
        model_dir = tmp_path / "text"
        model_dir.mkdir()
        pycolmap.Reconstruction(str(scene / "sparse" / "0")).write_text(str(model_dir))
    assert_reads_like_pycolmap(model_dir)
    assert len(read_colmap_model(model_dir).tracks.observations()[0]) > 0


@pytest.mark.parametrize("text", [False, True])
def test_distorted_ring_reads_like_pycolmap(tmp_path, text):
    write_ring_dataset(tmp_path, model="OPENCV", params=[30.0, 31.0, 20.5, 14.5, -0.12, 0.03, 0.001, -0.002],
                       num_images=7, text=text)
    assert_reads_like_pycolmap(tmp_path / "sparse" / "0")


def _rig_model(model_dir, text: bool) -> pycolmap.Reconstruction:
    """A rig of two cameras (the second turned and shifted from the first) on three frames, one frame
    unregistered, points observed by the registered images; written by pycolmap."""
    rng = np.random.default_rng(4)
    model = pycolmap.Reconstruction()
    cameras = [pycolmap.Camera.create_from_model_name(1, "PINHOLE", 60.0, 64, 48),
               pycolmap.Camera.create_from_model_name(2, "SIMPLE_RADIAL", 55.0, 64, 48)]
    for camera in cameras:
        model.add_camera(camera)
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(cameras[0].sensor_id)
    rig.add_sensor(cameras[1].sensor_id, pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.1, -0.2, 0.3])),
                                                          np.array([0.5, 0.0, 0.1])))
    model.add_rig(rig)
    for frame_id in (1, 2, 3):
        frame = pycolmap.Frame(frame_id=frame_id, rig_id=1)
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(rng.normal(size=3)), rng.normal(size=3))
        for camera_id in (1, 2):
            frame.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera_id),
                                              2 * frame_id + camera_id))
        model.add_frame(frame)
        for camera_id in (1, 2):
            model.add_image(pycolmap.Image(name=f"frame{frame_id}_cam{camera_id}.png", camera_id=camera_id,
                                           image_id=2 * frame_id + camera_id, frame_id=frame_id,
                                           points2D=[pycolmap.Point2D(xy) for xy in rng.uniform(0, 48, (5, 2))]))
    registered = [image_id for image_id in model.images if model.images[image_id].frame_id != 2]
    for k in range(5):
        observers = rng.choice(registered, 3, replace=False)
        model.add_point3D(rng.normal(size=3), pycolmap.Track([pycolmap.TrackElement(int(i), k) for i in observers]),
                          rng.integers(0, 256, 3, dtype=np.uint8))
    model.deregister_frame(2)
    model_dir.mkdir()
    (model.write_text if text else model.write_binary)(str(model_dir))
    return model


@pytest.mark.parametrize("text", [False, True])
def test_rig_with_an_offset_camera_and_an_unregistered_frame(tmp_path, text):
    """COLMAP writes each registered image's pose composed with its sensor_from_rig, and no
    unregistered image: the files read like pycolmap's frames and rigs."""
    model = _rig_model(tmp_path / "model", text)
    assert sorted(p.name.split(".")[0] for p in (tmp_path / "model").iterdir()) == [
        "cameras", "frames", "images", "points3D", "rigs"]
    assert_reads_like_pycolmap(tmp_path / "model")
    read = read_colmap_model(tmp_path / "model")
    assert read.names == sorted(image.name for image in model.images.values() if image.has_pose)
    assert len(read.names) == 4


def test_image_with_an_unknown_camera_is_one_error(tmp_path):
    write_ring_dataset(tmp_path, text=True, num_images=3)
    images = tmp_path / "sparse" / "0" / "images.txt"
    lines = images.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    fields = lines[header].split()
    lines[header] = " ".join(fields[:8] + ["9"] + fields[9:])
    images.write_text("\n".join(lines) + "\n")
    with pytest.raises(HicoError, match=r"images\.txt: images use cameras \[9\], which cameras\.txt does not list"):
        read_colmap_model(tmp_path / "sparse" / "0")


@pytest.mark.parametrize("line, match", [
    ("1 PINHOLE 40 30 32 32 20", r"cameras\.txt: line 4: PINHOLE takes 4 parameters, found 3"),
    ("1 PINHOLES 40 30 32 32 20 15", r"cameras\.txt: line 4: unknown camera model 'PINHOLES'"),
    ("1 PINHOLE forty 30 32 32 20 15", r"cameras\.txt: line 4: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS"),
])
def test_malformed_text_camera_is_one_error(tmp_path, line, match):
    write_ring_dataset(tmp_path, text=True, num_images=3)
    cameras = tmp_path / "sparse" / "0" / "cameras.txt"
    lines = cameras.read_text().splitlines()
    assert lines[3].startswith("1 PINHOLE")
    cameras.write_text("\n".join(lines[:3] + [line]) + "\n")
    with pytest.raises(HicoError, match=match):
        read_colmap_model(tmp_path / "sparse" / "0")
