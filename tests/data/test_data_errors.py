"""Bad datasets: each is one HicoError line naming the file/field, and hico-inspect exits 2 with it."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pycolmap
import pytest
from hico_plugin.scenes.ring_dataset import HEIGHT, WIDTH, write_ring_dataset

from hico_plugin.cli import inspect as inspect_cli
from hico_plugin.data import DataParserConfig
from hico_plugin.data.formats.colmap import ColmapFormat
from hico_plugin.errors import HicoError


def parse(root, **options):
    return DataParserConfig(data=root, **options).setup()


def expect_error(match: str, root, **options) -> str:
    with pytest.raises(HicoError, match=match) as info:
        parse(root, **options)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_missing_directory(tmp_path):
    expect_error(r"data directory .*nowhere: not found", tmp_path / "nowhere")


def test_no_sparse_model(tmp_path):
    (tmp_path / "images").mkdir()
    message = expect_error(r"no known dataset layout \(expected sparse/0 \(COLMAP\), transforms.json", tmp_path)
    assert "hico-process images" in message
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    (tmp_path / "sparse" / "0" / "cameras.bin").write_bytes(b"")
    expect_error(r"expected cameras, images and points3D as \.bin or \.txt", tmp_path)


def test_truncated_model_file(tmp_path):
    write_ring_dataset(tmp_path)
    images_bin = tmp_path / "sparse" / "0" / "images.bin"
    images_bin.write_bytes(images_bin.read_bytes()[:30])
    expect_error(r"sparse/0/images\.bin: images: 6 entries do not fit in the remaining 22 bytes", tmp_path)


def test_huge_count_in_a_model_file_fails_fast(tmp_path):
    """A flipped byte in an image's 2D-point count made pycolmap run for minutes (found by fuzzing)."""
    import struct

    write_ring_dataset(tmp_path)
    images_bin = tmp_path / "sparse" / "0" / "images.bin"
    data = bytearray(images_bin.read_bytes())
    name_end = data.index(b"\0", 8 + 64)
    data[name_end + 1:name_end + 9] = struct.pack("<Q", 2**40)
    images_bin.write_bytes(bytes(data))
    expect_error(r"images\.bin: image 0 2D points: 1099511627776 entries do not fit", tmp_path)


def test_image_listed_but_not_on_disk(tmp_path):
    written = write_ring_dataset(tmp_path)
    (tmp_path / "images" / written["names"][3]).unlink()
    expect_error(r"view_003\.png: image listed in the dataset but not on disk \(1 of 6 missing\)", tmp_path)


def test_missing_image_folder(tmp_path):
    write_ring_dataset(tmp_path)
    expect_error(r"images_x: image folder not found \(set --images-dir", tmp_path, format=ColmapFormat(images_dir="images_x"))


def test_image_size_disagrees_with_camera(tmp_path):
    written = write_ring_dataset(tmp_path)
    cv2.imwrite(str(tmp_path / "images" / written["names"][2]), np.zeros((HEIGHT, WIDTH + 3, 3), np.uint8))
    # Found at load from the header (train and test views alike), not when the view is first drawn.
    expect_error(r"view_002\.png: size 43x30 disagrees with its camera \(40x30", tmp_path)


@pytest.mark.parametrize("model", ["OPENCV_FISHEYE", "FULL_OPENCV"])
def test_unsupported_camera_model(tmp_path, model):
    write_ring_dataset(tmp_path, model=model)
    expect_error(
        rf"cameras: camera 1 has model {model}; supported models: PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL", tmp_path
    )


def test_zero_registered_images(tmp_path):
    write_ring_dataset(tmp_path, num_images=0)
    expect_error(r"the model has no registered images", tmp_path)


def test_empty_point_cloud(tmp_path):
    write_ring_dataset(tmp_path, num_points=0)
    expect_error(r"points3D: the point cloud is empty", tmp_path)


def _nan_point(reconstruction):
    reconstruction.points3D[next(iter(reconstruction.points3D))].xyz = np.array([np.nan, 0.0, 0.0])


def test_nan_point(tmp_path):
    write_ring_dataset(tmp_path, edit=_nan_point)
    expect_error(r"points3D: 1 points have NaN/inf coordinates", tmp_path)


def test_inf_pose(tmp_path):
    def spoil(reconstruction):
        matrix = reconstruction.frames[2].rig_from_world.matrix()
        matrix[1, 3] = np.inf
        reconstruction.frames[2].rig_from_world = pycolmap.Rigid3d(matrix)

    write_ring_dataset(tmp_path, edit=spoil)
    expect_error(r"images: NaN/inf pose for \['view_001\.png'\]", tmp_path)


def test_duplicate_image_names(tmp_path):
    write_ring_dataset(tmp_path, text=True, num_images=3)
    images_txt = tmp_path / "sparse" / "0" / "images.txt"
    images_txt.write_text(images_txt.read_text().replace("view_001.png", "view_000.png"))
    expect_error(r"duplicate image names \['view_000\.png'\]", tmp_path)


@pytest.mark.parametrize("truncate", ["png", "jpg"])
def test_truncated_image_file(tmp_path, truncate):
    written = write_ring_dataset(tmp_path)
    name = written["names"][4]
    _, encoded = cv2.imencode(f".{truncate}", np.full((HEIGHT, WIDTH, 3), 90, np.uint8))
    # Header intact, pixels cut: the load-time header check passes, decoding names the file.
    (tmp_path / "images" / name).write_bytes(encoded.tobytes()[: len(encoded) - 12])
    dataset = parse(tmp_path)
    with pytest.raises(HicoError, match=r"view_004\.png: unreadable or truncated image file"):
        dataset.image(4)
    with pytest.raises(HicoError, match=r"view_004\.png: unreadable or truncated"):
        dataset.verify_images()


def test_test_split_leaving_no_training_images(tmp_path):
    written = write_ring_dataset(tmp_path, num_images=3)
    expect_error(r"--test-every 1: the test split takes all 3 images", tmp_path, test_every=1)
    expect_error(r"--test-names: the test split takes all 3 images", tmp_path, test_names=tuple(written["names"]))
    expect_error(r"--test-names: \['nope\.png'\] are not registered", tmp_path, test_names=("nope.png",))


def run_inspect(monkeypatch, capsys, *args) -> tuple[int, str, str]:
    monkeypatch.setattr(sys, "argv", ["hico-inspect", *map(str, args)])
    try:
        inspect_cli.entrypoint()
        code = 0
    except SystemExit as exit_:
        code = exit_.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_inspect_prints_one_error_line_and_exits_2(tmp_path, monkeypatch, capsys):
    write_ring_dataset(tmp_path, num_points=0)
    code, out, err = run_inspect(monkeypatch, capsys, tmp_path)
    assert code == 2 and out == ""
    assert err.startswith("error: ") and err.count("\n") == 1 and "point cloud is empty" in err


def test_inspect_summary(tmp_path, monkeypatch, capsys):
    write_ring_dataset(tmp_path, num_images=10, model="SIMPLE_RADIAL", params=[32.0, 20.0, 15.0, -0.05])
    (tmp_path / "scene.json").write_text('{"name": "probe"}')
    code, out, err = run_inspect(monkeypatch, capsys, tmp_path, "--downscale", "2", "--verify-images")
    assert code == 0, err
    assert "(scene 'probe')" in out
    assert "images       10 registered: 8 train, 2 test" in out
    assert "cameras      1: SIMPLE_RADIAL x1  (1 undistorted to PINHOLE)" in out
    assert "points       40 sparse points" in out
    assert "LOD range" in out and "octree levels" in out
    assert "verified     all 10 images" in out


@pytest.mark.parametrize("breakage", ["missing", "no_points", "nan_point", "no_training_images"])
def test_train_prints_one_error_line_and_exits_2(tmp_path, monkeypatch, capsys, breakage):
    """hico-train loads data through the same parser: the same one-line errors, exit 2, no traceback."""
    from hico_plugin.cli import train as train_cli

    root, extra = tmp_path / "data", []
    if breakage == "no_points":
        write_ring_dataset(root, num_points=0)
    elif breakage == "nan_point":
        write_ring_dataset(root, edit=_nan_point)
    elif breakage == "no_training_images":
        write_ring_dataset(root, num_images=3)
        extra = ["--test-every", "1"]
    expected = {"missing": "not found", "no_points": "point cloud is empty", "nan_point": "NaN/inf coordinates",
                "no_training_images": "the test split takes all 3 images"}[breakage]
    argv = ["hico-gs-lite", "--data", str(root), "--vis", "none", "--output-dir", str(tmp_path / "run"), *extra]
    with pytest.raises(SystemExit) as exit_:
        train_cli.entrypoint(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2
    assert err.startswith("error: ") and err.count("\n") == 1 and expected in err, err


@pytest.mark.parametrize("params, match", [
    ([0.0, 0.0, 20.0, 15.0], r"camera 1: focal length fx=0, fy=0; expected positive"),
    ([-50.0, -50.0, 20.0, 15.0], r"camera 1: focal length fx=-50, fy=-50; expected positive"),
    ([32.0, 32.0, 500.0, 15.0], r"camera 1: principal point \(500, 15\) lies far outside the 40x30 image"),
])
def test_bad_intrinsics_fail_at_load(tmp_path, params, match):
    write_ring_dataset(tmp_path, params=params)
    message = expect_error(match, tmp_path)
    assert "sparse/0/cameras" in message


def test_tiny_images_fail_at_load(tmp_path):
    write_ring_dataset(tmp_path, size=(1, 1))
    expect_error(r"camera 1: image size 1x1; expected at least 16x16 px", tmp_path)


def test_test_image_with_wrong_size_fails_at_load(tmp_path):
    """A test view (index 0 with --test-every 8) is checked at load too, not at the final eval."""
    written = write_ring_dataset(tmp_path)
    cv2.imwrite(str(tmp_path / "images" / written["names"][0]), np.zeros((HEIGHT + 1, WIDTH, 3), np.uint8))
    expect_error(r"view_000\.png: size 40x31 disagrees with its camera", tmp_path)


def _rename_image(new_name):
    def edit(reconstruction):
        reconstruction.images[1].name = new_name
    return edit


@pytest.mark.parametrize("name, match", [
    ("/etc/hostname", r"'/etc/hostname' is absolute"),
    ("../outside.png", r"'\.\./outside\.png' climbs out of"),
    ("sub/../../outside.png", r"climbs out of"),
])
def test_image_names_outside_the_image_folder_are_refused(tmp_path, name, match):
    write_ring_dataset(tmp_path, edit=_rename_image(name))
    message = expect_error(match, tmp_path)
    assert "sparse/0/images: image" in message


def test_symlink_leaving_the_image_folder_is_refused(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    cv2.imwrite(str(outside / "secret.png"), np.zeros((HEIGHT, WIDTH, 3), np.uint8))
    root = tmp_path / "data"
    written = write_ring_dataset(root)
    link = root / "images" / written["names"][1]
    link.unlink()
    link.symlink_to(outside / "secret.png")
    expect_error(r"view_001\.png' resolves to .*outside .*images \(a symlink leaves the folder\)", root)


def test_inspect_verifies_images_by_default(tmp_path, monkeypatch, capsys):
    written = write_ring_dataset(tmp_path)
    _, encoded = cv2.imencode(".png", np.full((HEIGHT, WIDTH, 3), 90, np.uint8))
    (tmp_path / "images" / written["names"][3]).write_bytes(encoded.tobytes()[:-12])
    code, out, err = run_inspect(monkeypatch, capsys, tmp_path)
    assert code == 2 and err.count("\n") == 1 and "view_003.png: unreadable or truncated" in err
    # the effects analysis (on by default) decodes the images itself, so skipping needs both flags
    code, out, err = run_inspect(monkeypatch, capsys, tmp_path, "--no-verify-images", "--no-effects")
    assert code == 0 and "verified" not in out
