"""hico-process on rendered photos of a built-in scene: cameras recovered up to a similarity."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pycolmap
import pytest
from PIL import Image

from hico_plugin.cli.process import main as process_main
from hico_plugin.data import images as image_io
from hico_plugin.data.sources import DataSourceConfig
from hico_plugin.errors import HicoError
from hico_plugin.process.align import aligned_errors, umeyama
from hico_plugin.process.ingest import photo_info
from hico_plugin.process.matching import _resume_or_clear
from hico_plugin.process.video import extract_frames, sharpness
from hico_plugin.scenes.generate import generate_scene
from hico_plugin.scenes.geotagged import write_geotagged_photos

FAST = ["--max-features", "2048", "--num-threads", "2", "--camera-model", "SIMPLE_RADIAL", "--downscales", "2"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """City-block's 72 aerial views at 320x240 (view i on ring i % 3). Tiny's repeating checkers fold its
    ring and fewer city-block views (30) register only two images: this is the smallest built-in set
    measured to register fully (72 of 72, camera centres within 0.8 % of the spread)."""
    return generate_scene("city-block", tmp_path_factory.mktemp("scene") / "scene")


@pytest.fixture(scope="module")
def photos(scene):
    """The scene's photos only; returns (folder, {name: known centre}, camera spread = mean distance of
    the known centres from their mean)."""
    root = scene.parent
    known = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    centres = {image.name: image.projection_center() for image in known.images.values()}
    shutil.copytree(scene / "images", root / "photos")
    points = np.array(list(centres.values()))
    return root / "photos", centres, float(np.linalg.norm(points - points.mean(0), axis=1).mean())


def _centres(out):
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    return {image.name: image.projection_center() for image in model.images.values() if image.has_pose}


def _centre_errors(recovered, known, spread):
    """Distances of the recovered camera centres from the known ones after the best similarity, as a
    fraction of the camera spread (SfM fixes neither scale nor frame)."""
    names = sorted(recovered)
    return aligned_errors(np.array([recovered[n] for n in names]), np.array([known[n] for n in names])) / spread


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation = q * np.sign(np.linalg.det(q))
    dst = 2.5 * src @ rotation.T + np.array([1.0, -2.0, 3.0])
    scale, r, t = umeyama(src, dst)
    assert scale == pytest.approx(2.5) and np.allclose(r, rotation) and np.allclose(t, [1, -2, 3])
    assert aligned_errors(src, dst).max() < 1e-9


def test_images_register_write_the_dataset_and_resume(photos, tmp_path):
    folder, known, spread = photos
    out = tmp_path / "out"
    summary = process_main(["images", str(folder), "--output", str(out), *FAST])
    recovered = _centres(out)
    assert summary["registered"] == len(recovered) >= 0.9 * len(known)
    assert set(summary["dropped"]) == set(known) - set(recovered)
    errors = _centre_errors(recovered, known, spread)
    print(f"registered {len(recovered)}/{len(known)}; centre error / spread: median {np.median(errors):.2e}, "
          f"max {errors.max():.2e}")
    assert np.median(errors) < 0.005 and errors.max() < 0.02
    names = sorted(recovered)
    for name in names:
        undistorted = cv2.imread(str(out / "images" / name))
        half = cv2.imread(str(out / "images_2" / name))
        assert undistorted is not None and half.shape[0] == -(-undistorted.shape[0] // 2)
    again = process_main(["images", str(folder), "--output", str(out), *FAST])
    assert set(again["reused_stages"]) == {"ingest", "features", "matching", "mapping", "undistort", "downscale"}
    assert _centres(out).keys() == recovered.keys()
    # Here the fitted distortion moves no pixel by half a pixel: the photos are kept as taken. A copy
    # run again with --keep-below-px 0 reuses the reconstruction and resamples them.
    assert [choice["kept"] for choice in summary["undistortion"]] == [True]
    assert all((out / "images" / name).read_bytes() == (folder / name).read_bytes() for name in names)
    resampled = tmp_path / "resampled"
    shutil.copytree(out, resampled)
    forced = process_main(["images", str(folder), "--output", str(resampled), *FAST, "--keep-below-px", "0"])
    assert set(forced["reused_stages"]) == {"ingest", "features", "matching", "mapping"}
    assert [choice["kept"] for choice in forced["undistortion"]] == [False]
    kept_model, resampled_model = (pycolmap.Reconstruction(str(d / "sparse" / "0")) for d in (out, resampled))
    for image in kept_model.images.values():
        assert np.array_equal(resampled_model.images[image.image_id].cam_from_world().matrix(),
                              image.cam_from_world().matrix())
        assert (resampled / "images" / image.name).read_bytes() != (folder / image.name).read_bytes()


def test_photos_with_gps_are_matched_with_their_nearest_and_a_rerun_reuses_every_stage(scene, tmp_path):
    """12 neighbouring views of the inner ring as a drone's JPEGs with GPS in their EXIF: above
    --exhaustive-max, auto matches each with its --neighbors nearest by position (COLMAP's spatial
    pairing, horizontal distance), COLMAP reads the positions the photos carry, and the cameras are
    recovered."""
    tagged = write_geotagged_photos(scene, tmp_path / "tagged")
    folder = tmp_path / "photos"
    folder.mkdir()
    ring = sorted(tagged)[::3][:12]
    for name in ring:
        (tmp_path / "tagged" / name).rename(folder / name)
    out = tmp_path / "out"
    args = ["images", str(folder), "--output", str(out), *FAST, "--exhaustive-max", "8", "--neighbors", "6"]
    summary = process_main(args)
    assert summary["matcher"] == "spatial" and summary["mapper"] == "incremental"
    centres = np.array([tagged[name] for name in ring])
    distance = np.linalg.norm(centres[:, None, :2] - centres[None, :, :2], axis=-1)
    nearest = np.argsort(distance, axis=1)[:, 1:7]
    allowed = {frozenset((ring[i], ring[j])) for i in range(12) for j in nearest[i]}
    with pycolmap.Database.open(out / "colmap" / "database.db") as db:
        names = {image.image_id: image.name for image in db.read_all_images()}
        matched = {frozenset(names[i] for i in pycolmap.pair_id_to_image_pair(pair))
                   for pair in db.read_all_matches()[0]}
        priors = {names[prior.corr_data_id.id]: prior.position for prior in db.read_all_pose_priors()}
        assert summary["pairs"] == db.num_matched_image_pairs() < 12 * 11 // 2 and matched <= allowed
    for name in ring:  # what COLMAP read is what the photo carries (COLMAP keeps the altitude in float32)
        assert np.allclose(priors[name], photo_info(folder / name).gps, rtol=0, atol=[1e-7, 1e-7, 1e-3]), name
    recovered = _centres(out)
    assert summary["registered"] == len(recovered) >= 11
    errors = _centre_errors(recovered, tagged, float(np.linalg.norm(centres - centres.mean(0), axis=1).mean()))
    assert np.median(errors) < 0.01 and errors.max() < 0.03, errors
    again = process_main(args)
    assert set(again["reused_stages"]) == {"ingest", "features", "matching", "mapping", "undistort", "downscale"}
    # Another matching option redoes matching on the features extracted; a stopped matching stage with
    # the same options keeps the pairs it matched, and one with other options starts afresh.
    fewer = process_main([*args[:-1], "4"])
    assert set(fewer["reused_stages"]) == {"ingest", "features"} and fewer["pairs"] < summary["pairs"]
    state, database = out / "colmap" / "matching.json", out / "colmap" / "database.db"
    key = json.loads(state.read_text())["key"]
    assert _resume_or_clear(state, key, database)
    with pycolmap.Database.open(database) as db:
        assert db.num_matched_image_pairs() == fewer["pairs"]
    assert not _resume_or_clear(state, "other options", database)
    with pycolmap.Database.open(database) as db:
        assert db.num_matched_image_pairs() == 0


def _exif(orientation: int = 1, make: str = "", model: str = "") -> bytes:
    exif = Image.Exif()
    exif[0x0112] = orientation
    if make:
        exif[0x010F], exif[0x0110] = make, model
    return exif.tobytes()


# EXIF orientation -> how the stored pixels are turned from the upright view (viewers undo it).
_STORED_TURN = {3: Image.Transpose.ROTATE_180, 6: Image.Transpose.ROTATE_90, 8: Image.Transpose.ROTATE_270}


def _users_folder(folder, target):
    """City-block's views as a phone folder / download would hold them: turned JPEGs with an EXIF
    orientation tag, grey, 16-bit and transparent PNGs, a second camera (another size and EXIF model),
    and an empty, a truncated and a text file named like photos. Returns {name: what was done}."""
    target.mkdir()
    kinds = {}
    names = sorted(p.name for p in folder.iterdir())
    for index, name in enumerate(names):
        upright = Image.open(folder / name).convert("RGB")
        stem = name[:-4]
        if index in (0, 1, 2, 3, 4, 5):
            orientation = (6, 3, 8)[index % 3]
            new = f"{stem}.jpg"
            upright.transpose(_STORED_TURN[orientation]).save(target / new, quality=95, exif=_exif(orientation, "PhoneCo", "A1"))
            kinds[new] = f"jpeg, EXIF orientation {orientation}"
        elif index in (10, 11, 12):
            upright.convert("L").save(target / name)
            kinds[name] = "grayscale png"
        elif index == 13:
            grey = np.asarray(upright.convert("L"), np.uint16) * 257
            Image.fromarray(grey).save(target / name)
            kinds[name] = "16-bit grayscale png"
        elif index in (20, 21):
            rgba = upright.convert("RGBA")
            alpha = np.full((upright.height, upright.width), 255, np.uint8)
            alpha[:40, :40] = 0
            rgba.putalpha(Image.fromarray(alpha))
            rgba.save(target / name)
            kinds[name] = "png with alpha"
        elif 30 <= index < 40:
            new = f"{stem}.jpg"
            upright.resize((480, 360), Image.Resampling.LANCZOS).save(target / new, quality=95,
                                                                        exif=_exif(1, "DroneCo", "B2"))
            kinds[new] = "second camera: 480x360 jpeg, other EXIF model"
        else:
            shutil.copy2(folder / name, target / name)
    (target / "empty.jpg").write_bytes(b"")
    whole = (target / f"{names[40][:-4]}.jpg")
    Image.open(folder / names[41]).convert("RGB").save(whole, quality=95)
    (target / "cut.jpg").write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    whole.unlink()
    (target / "notes.jpg").write_text("shot list: north facade, then the roofs\n")
    kinds.update({"empty.jpg": "zero bytes", "cut.jpg": "truncated jpeg", "notes.jpg": "text file named .jpg"})
    return kinds


def test_photos_as_users_hand_them_over(photos, tmp_path):
    folder, known, spread = photos
    users = tmp_path / "users"
    kinds = _users_folder(folder, users)
    out = tmp_path / "out"
    summary = process_main(["images", str(users), "--output", str(out), *FAST])
    assert set(summary["skipped"]) == {"empty.jpg", "cut.jpg", "notes.jpg"}
    assert "empty file" in summary["skipped"]["empty.jpg"]
    assert "truncated" in summary["skipped"]["cut.jpg"] and "not an image" in summary["skipped"]["notes.jpg"]
    # One camera per camera the files name: the turned JPEGs' EXIF (PhoneCo A1), the untagged PNGs,
    # and the 480x360 DroneCo photos.
    assert summary["cameras"] == 3
    assert set(summary["masked"]) == {n for n, k in kinds.items() if "alpha" in k}
    # Turned photos are written upright (their tag applied), the others' pixels unchanged.
    for name, kind in kinds.items():
        if "orientation" in kind:
            ingested = image_io.read_rgb(out / "colmap" / "input" / name)
            upright = image_io.read_rgb(folder / f"{name[:-4]}.png")
            assert ingested.shape == upright.shape
            assert np.abs(ingested.astype(int) - upright.astype(int)).mean() < 3, name
    recovered = {name[:-4] + ".png": centre for name, centre in _centres(out).items()}
    assert len(recovered) >= 0.9 * len(known)
    errors = _centre_errors(recovered, known, spread)
    assert np.median(errors) < 0.01, np.median(errors)
    # The dataset hico-process wrote loads: every image's size agrees with its camera, masks included.
    dataset = DataSourceConfig(data=out).setup()
    masked = [i for i, name in enumerate(dataset.image_names) if "alpha" in kinds.get(name, "")]
    assert masked and all(dataset.mask(i) is not None for i in masked)
    for i in masked:
        mask = dataset.mask(i).squeeze().numpy()
        assert not mask[:30, :30].any() and mask[60:, 60:].all()
    # A forced single camera cannot hold two sizes: one line before any feature is extracted.
    with pytest.raises(HicoError, match=r"--camera-mode single: one camera has one image size.*480x360"):
        process_main(["images", str(users), "--output", str(tmp_path / "single"), *FAST, "--camera-mode", "single"])


def test_loaders_read_the_stored_pixels_of_a_turned_photo(tmp_path):
    """The stored pixel grid (what COLMAP's cameras and the header size checks describe), not the
    turned one OpenCV shows by default."""
    stored = np.zeros((30, 50, 3), np.uint8)
    stored[:, :10] = 255
    Image.fromarray(stored).save(tmp_path / "turned.jpg", quality=95, exif=_exif(6))
    assert image_io.read_rgb(tmp_path / "turned.jpg").shape == (30, 50, 3)
    assert cv2.imread(str(tmp_path / "turned.jpg")).shape == (50, 30, 3)  # what OpenCV does unasked


def test_too_few_photos_is_one_clear_error(tmp_path):
    (tmp_path / "photos").mkdir()
    blank = np.full((120, 160, 3), 128, np.uint8)
    for i in range(4):
        cv2.imwrite(str(tmp_path / "photos" / f"{i}.png"), blank)
    with pytest.raises(HicoError, match=r"registered no images|only \d+ of 4 images registered"):
        process_main(["images", str(tmp_path / "photos"), "--output", str(tmp_path / "out"), *FAST])
    with pytest.raises(HicoError, match=r"--keep-below-px: expected a distance in pixels >= 0, got -1"):
        process_main(["images", str(tmp_path / "photos"), "--output", str(tmp_path / "o3"), "--keep-below-px", "-1"])
    with pytest.raises(HicoError, match="found 0 photos"):
        process_main(["images", str(tmp_path / "out" / "colmap" / "sparse"), "--output", str(tmp_path / "o2")])


def _write_video(path, folder, names):
    """An MJPG video of ``names`` in order, each sharp frame between two motion-blurred copies of itself."""
    first = cv2.imread(str(folder / names[0]))
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, first.shape[1::-1])
    for name in names:
        frame = cv2.imread(str(folder / name))
        blurred = cv2.blur(frame, (9, 1))
        for out_frame in (blurred, frame, blurred):
            writer.write(out_frame)
    writer.release()


def test_video_keeps_the_sharp_frames(photos, tmp_path):
    folder, known, _ = photos
    video = tmp_path / "walk.avi"
    names = sorted(known)[:24]
    _write_video(video, folder, names)
    kept_dir = tmp_path / "frames"
    summary = extract_frames(video, kept_dir, len(names), lambda done, total: None)
    assert summary["kept_frames"] == len(names) and summary["video_frames"] == 3 * len(names)
    kept = sorted(kept_dir.glob("*.png"))
    sharp = [sharpness(cv2.imread(str(folder / name))) for name in names]
    got = [sharpness(cv2.imread(str(path))) for path in kept]
    # MJPG re-encodes: the kept frame is the sharp one, within the codec's loss (blurred ~3x lower)
    assert all(g > 0.8 * s for g, s in zip(got, sharp))


def test_video_to_dataset_recovers_the_flight(photos, tmp_path):
    """hico-process video end to end: a flight ring after ring (city-block's views interleave three
    rings; a video follows one, then the next) -> sharp frames -> SfM -> dataset; frame k is the k-th
    view flown, so its centre is known."""
    folder, known, spread = photos
    flight = [name for ring in range(3) for name in sorted(known)[ring::3]]
    video = tmp_path / "flight.avi"
    _write_video(video, folder, flight)
    out = tmp_path / "out"
    summary = process_main(["video", str(video), "--output", str(out), "--num-frames", str(len(flight)),
                            "--matcher", "exhaustive", *FAST])
    recovered = {flight[int(name.removeprefix("frame_").removesuffix(".png"))]: centre
                 for name, centre in _centres(out).items()}
    assert summary["registered"] == len(recovered) >= 0.9 * len(flight)
    errors = _centre_errors(recovered, known, spread)
    assert np.median(errors) < 0.005 and errors.max() < 0.03
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(_centres(out))


def test_video_command_reports_a_missing_file(tmp_path):
    with pytest.raises(HicoError, match="video file not found"):
        process_main(["video", str(tmp_path / "none.mp4"), "--output", str(tmp_path / "out")])
