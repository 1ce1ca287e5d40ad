"""The undistort stage on a generated twin: near-pinhole cameras keep their photos, distorted ones are resampled."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest

from hico_plugin.process.stages import StageRunner
from hico_plugin.process.undistort import describe, max_distortion_px, pinhole_twin, undistort
from hico_plugin.scenes.generate import generate_scene

# k1 of the twin's two OPENCV cameras (160x120, f = 138.6 px): 0.001 moves the corners by 0.05 px,
# 0.05 by 2.60 px.
NEAR_PINHOLE_K1, DISTORTED_K1 = 0.001, 0.05


def _twin(tmp_path, k1s=(NEAR_PINHOLE_K1, DISTORTED_K1), masked=True):
    """A COLMAP model of the `tiny` scene's 4 views (160x120) with camera 1 (OPENCV, k1s[0]) on the
    even views and camera 2 (OPENCV, k1s[1]) on the odd ones, one keypoint each, and (``masked``) a
    transparency mask per photo; returns (model dir, photo dir, mask dir, out dir)."""
    scene = generate_scene("tiny", tmp_path / "scene", num_views=4, width=160, height=120)
    known = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    f = known.cameras[1].focal_length_x
    model = pycolmap.Reconstruction()
    for camera_id, k1 in zip((1, 2), k1s):
        camera = pycolmap.Camera.create_from_model_name(camera_id, "OPENCV", f, 160, 120)
        camera.params = [f, f, 80.0, 60.0, k1, 0.0, 0.0, 0.0]
        model.add_camera_with_trivial_rig(camera)
    masks = tmp_path / "masks"
    if masked:
        masks.mkdir()
    for image in known.images.values():
        model.add_image_with_trivial_frame(
            pycolmap.Image(name=image.name, camera_id=1 + image.image_id % 2, image_id=image.image_id,
                           points2D=[pycolmap.Point2D(np.array([10.0, 20.0]))]), image.cam_from_world())
        if masked:
            mask = np.full((120, 160), 255, np.uint8)
            mask[:30, :30] = 0
            cv2.imwrite(str(masks / f"{image.name}.png"), mask)
    (tmp_path / "model").mkdir()
    model.write_binary(str(tmp_path / "model"))
    return tmp_path / "model", scene / "images", masks, tmp_path / "out"


def test_near_pinhole_photos_are_kept_and_distorted_ones_undistorted(tmp_path):
    model_dir, photos, masks, out = _twin(tmp_path)
    first = StageRunner(out).run("undistort", "key", lambda report: undistort(model_dir, photos, masks, out, report))
    again = StageRunner(out)
    assert again.run("undistort", "key", lambda report: pytest.fail("redone")) == first and again.reused
    lines = [describe(choice) for choice in first["cameras"]]
    print("\n".join(lines))
    assert lines[0] == ("camera 1 (OPENCV, 160x120): distortion moves pixels by at most 0.05 px; photos kept as "
                        "taken, camera written as PINHOLE")
    assert lines[1] == ("camera 2 (OPENCV, 160x120): distortion moves pixels by at most 2.60 px; photos undistorted "
                        "to PINHOLE")
    source = pycolmap.Reconstruction(str(model_dir))
    written = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    kept, resampled = written.cameras[1], written.cameras[2]
    assert (kept.model.name, kept.width, kept.height) == ("PINHOLE", 160, 120)
    assert np.allclose(kept.params, source.cameras[1].params[:4])
    expected = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), source.cameras[2])
    assert (resampled.model.name, resampled.width, resampled.height) == ("PINHOLE", expected.width, expected.height)
    assert np.allclose(resampled.params, expected.params)
    for image in written.images.values():
        taken = (photos / image.name).read_bytes()
        stored = cv2.imread(str(out / "images" / image.name))
        mask = cv2.imread(str(out / "masks" / image.name), cv2.IMREAD_GRAYSCALE)
        assert stored.shape[:2] == mask.shape == (written.cameras[image.camera_id].height,
                                                  written.cameras[image.camera_id].width)
        assert not mask[:20, :20].any() and mask[60:, 60:].all()
        if image.camera_id == 1:
            assert (out / "images" / image.name).read_bytes() == taken, image.name
            assert np.allclose(image.points2D[0].xy, [10.0, 20.0])
        else:
            assert stored.shape != cv2.imread(str(photos / image.name)).shape
            assert not np.allclose(image.points2D[0].xy, [10.0, 20.0])
    assert sorted(p.name for p in (out / "colmap").iterdir()) == []  # no staging folder left behind


def test_all_near_pinhole_runs_no_undistorter(tmp_path):
    model_dir, photos, masks, out = _twin(tmp_path, k1s=(NEAR_PINHOLE_K1, -NEAR_PINHOLE_K1), masked=False)
    summary = undistort(model_dir, photos, masks, out, lambda done, total: None)
    assert [choice["kept"] for choice in summary["cameras"]] == [True, True]
    written = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert {camera.model.name for camera in written.cameras.values()} == {"PINHOLE"}
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(p.name for p in photos.iterdir())
    for image in written.images.values():
        assert (out / "images" / image.name).read_bytes() == (photos / image.name).read_bytes(), image.name
    assert not (out / "masks").exists()


def test_keep_below_zero_resamples_every_distorted_camera(tmp_path):
    """keep_below_px 0 (how the cost of resampling is measured): even a camera whose distortion moves
    pixels by 0.05 px has its photos undistorted."""
    model_dir, photos, masks, out = _twin(tmp_path, k1s=(NEAR_PINHOLE_K1, -NEAR_PINHOLE_K1), masked=False)
    summary = undistort(model_dir, photos, masks, out, lambda done, total: None, keep_below_px=0.0)
    assert [choice["kept"] for choice in summary["cameras"]] == [False, False]
    assert describe(summary["cameras"][0]).endswith("at most 0.05 px; photos undistorted to PINHOLE")
    for image in pycolmap.Reconstruction(str(out / "sparse" / "0")).images.values():
        assert (out / "images" / image.name).read_bytes() != (photos / image.name).read_bytes(), image.name


def test_max_distortion_is_the_corner_shift_of_a_radial_camera():
    # SIMPLE_RADIAL f=100, principal point (100, 50), k=0.01 on 200x100: the corner's ray (-1, -0.5)
    # has r^2 = 1.25 and lands at (1 + k r^2) times its pinhole position, so it moves by
    # f * k * r^2 * r = 100 * 0.0125 * sqrt(1.25) = 1.3975 px, the most of any pixel (radial, growing).
    camera = pycolmap.Camera.create_from_model_name(3, "SIMPLE_RADIAL", 100.0, 200, 100)
    camera.params = [100.0, 100.0, 50.0, 0.01]
    assert max_distortion_px(camera) == pytest.approx(100 * 0.0125 * np.sqrt(1.25), rel=1e-9)
    twin = pinhole_twin(camera)
    assert (twin.camera_id, twin.model.name, twin.width, twin.height) == (3, "PINHOLE", 200, 100)
    assert np.allclose(twin.params, [100.0, 100.0, 100.0, 50.0])
    assert max_distortion_px(twin) == 0.0


def test_a_fisheye_is_never_near_pinhole():
    """Equidistant projection (theta, not tan theta) even with zero coefficients."""
    camera = pycolmap.Camera.create_from_model_name(1, "OPENCV_FISHEYE", 100.0, 200, 100)
    assert max_distortion_px(camera) > 10
