"""Built-in scenes: COLMAP round trip, exact ground truth, effects, cache, CLI."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pycolmap
import pytest

from hico_plugin.errors import HicoError
from hico_plugin.scenes import SCENES
from hico_plugin.scenes import capture_effects as fx
from hico_plugin.scenes import generate as gen
from hico_plugin.scenes.generate import generate_scene, scene_config
from hico_plugin.scenes.render import render_view

# a city-block small enough for a unit test, all of its effects declared
SMALL_CITY = dict(num_views=4, width=48, height=32, sparse_points=60, surface_spacing=2.0, blocks=1)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    path = generate_scene("tiny", tmp_path_factory.mktemp("scenes") / "tiny")
    return path, scene_config("tiny").setup("tiny")


def _read(path, name):
    return np.load(path / "ground_truth" / name)


def test_tiny_round_trips_through_colmap(tiny):
    path, scene = tiny
    rec = pycolmap.Reconstruction(str(path / "sparse" / "0"))
    assert rec.num_images() == len(scene.viewmats) == 12
    (camera,) = rec.cameras.values()
    assert camera.model.name == "PINHOLE" and (camera.width, camera.height) == (64, 48)
    np.testing.assert_allclose(camera.params, [scene.K[0, 0], scene.K[1, 1], scene.K[0, 2], scene.K[1, 2]])
    for image in rec.images.values():
        index = int(image.name[5:9])
        np.testing.assert_allclose(image.cam_from_world().matrix(), scene.viewmats[index, :3], atol=1e-9)
        png = cv2.imread(str(path / "images" / image.name))
        assert png.shape == (48, 64, 3)
        assert _read(path, f"depth/{image.name[:-4]}.npy").shape == (48, 64)
    assert rec.num_points3D() > 100
    for point in rec.points3D.values():
        assert point.track.length() >= 2  # seen by at least two cameras, like an SfM point
        for element in point.track.elements:
            image = rec.images[element.image_id]
            observed = image.points2D[element.point2D_idx]
            assert observed.point3D_id != pycolmap.INVALID_POINT3D_ID
            projected = camera.img_from_cam(image.cam_from_world() * point.xyz)
            assert np.linalg.norm(projected - observed.xy) < 4.0  # 0.5 px keypoint + small 3D noise
    meta = json.loads((path / "scene.json").read_text())
    assert meta["scene"] == "tiny" and meta["declared_effects"] == [] and meta["enabled_effects"] == []


def test_ground_depth_matches_the_ray_plane_intersection(tiny):
    path, scene = tiny
    u, v = np.meshgrid(np.arange(64) + 0.5, np.arange(48) + 0.5)
    rays_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(scene.K).T  # z = 1: t is depth
    checked = 0
    for i, viewmat in enumerate(scene.viewmats):
        depth = _read(path, f"depth/view_{i:04d}.npy")
        normal = _read(path, f"normal/view_{i:04d}.npy")
        rotation = viewmat[:3, :3]
        center = -rotation.T @ viewmat[:3, 3]
        dirs = rays_cam @ rotation  # world, unnormalised
        ground_depth = -center[2] / dirs[..., 2]  # plane z = 0
        ground_up = np.abs(normal - rotation[:, 2]).max(-1) < 1e-6  # normal is world +z
        on_ground = ground_up & (np.abs((center + dirs * depth[..., None])[..., 2]) < 1e-4)
        np.testing.assert_allclose(depth[on_ground], ground_depth[on_ground], rtol=1e-5)
        hit = depth > 0
        # nothing is ever behind the ground plane
        assert (depth[hit & (ground_depth > 0)] <= ground_depth[hit & (ground_depth > 0)] * (1 + 1e-5)).all()
        checked += on_ground.sum()
    assert checked > 1000


def test_normals_are_unit_and_face_the_camera(tiny):
    path, scene = tiny
    u, v = np.meshgrid(np.arange(64) + 0.5, np.arange(48) + 0.5)
    rays_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(scene.K).T
    for i in range(len(scene.viewmats)):
        depth = _read(path, f"depth/view_{i:04d}.npy")
        normal = _read(path, f"normal/view_{i:04d}.npy")
        hit = depth > 0
        assert hit.any() and (~hit).any()  # tiny shows the box, the ground and empty background
        np.testing.assert_allclose(np.linalg.norm(normal[hit], axis=-1), 1.0, atol=1e-5)
        assert (normal[~hit] == 0).all() and (depth[~hit] == 0).all()
        assert ((normal * rays_cam).sum(-1)[hit] < 0).all()


def test_surface_points_lie_on_the_tiny_geometry(tiny):
    path, scene = tiny
    points = _read(path, "surface_points.npy").astype(np.float64)
    assert len(points) > 1000
    ground, cube = scene.primitives
    on_ground = np.abs(points[:, 2]) < 1e-4
    signed = (points @ cube.normals.T - cube.offsets).max(1)  # 0 on the box surface
    assert (on_ground | (np.abs(signed) < 1e-4)).all()
    assert (~on_ground).sum() > 50  # the box is sampled too


def test_plain_images_are_exactly_shading_times_texture(tiny):
    path, scene = tiny
    cfg = scene.config
    for i in (0, 5):
        view = render_view(scene.caster, scene.viewmats[i], scene.K, 64, 48, scene.sun, cfg.ambient, cfg.shadows)
        expected = np.round(np.clip(view.albedo * view.shading[..., None], 0, 1) * 255).astype(np.uint8)
        image = cv2.cvtColor(cv2.imread(str(path / "images" / f"view_{i:04d}.png")), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(image, expected)
        assert (image[~view.hit] == 0).all()  # no sky declared: background stays black


def _no_effect_may_run(monkeypatch):
    def forbidden(*args, **kwargs):
        raise AssertionError("an effect that is not enabled ran")

    for name in ("exposure_gains", "apply_exposure", "apply_sky", "apply_sensor_noise"):
        monkeypatch.setattr(fx, name, forbidden)


def test_undeclared_and_disabled_effects_never_run(tmp_path, monkeypatch):
    _no_effect_may_run(monkeypatch)
    generate_scene("tiny", tmp_path / "tiny", num_views=3)
    off = {"exposure": False, "sky": False, "multi_distance": False}
    generate_scene("city-block", tmp_path / "city", effects=off, **SMALL_CITY)
    with pytest.raises(HicoError, match="does not declare effect 'sky'"):
        generate_scene("tiny", tmp_path / "bad", effects={"sky": True})


def test_declared_effects_are_simulated(tmp_path):
    off = {"exposure": False, "sky": False, "multi_distance": False}
    # one ray per pixel, so that a pixel is all sky or all surface (depth == 0 exactly where sky shows)
    small = {**SMALL_CITY, "pixel_samples": 1}
    plain = generate_scene("city-block", tmp_path / "plain", effects=off, **small)
    exposed = generate_scene("city-block", tmp_path / "exposed", effects={**off, "exposure": True}, **small)
    sky = generate_scene("city-block", tmp_path / "sky", effects={**off, "sky": True}, **small)
    meta = json.loads((exposed / "scene.json").read_text())
    assert meta["enabled_effects"] == ["exposure"]
    assert meta["declared_effects"] == ["exposure", "sky", "multi_distance"]
    gains = np.array(meta["exposure_gains"])
    assert gains.shape == (4, 3) and np.ptp(gains[:, 1]) > 0.05  # per-image gains differ
    for i in range(4):
        a = cv2.imread(str(plain / "images" / f"view_{i:04d}.png")).astype(np.float64)[..., ::-1]
        b = cv2.imread(str(exposed / "images" / f"view_{i:04d}.png")).astype(np.float64)[..., ::-1]
        usable = (a > 20).all(-1) & (b < 250).all(-1)
        ratio = b[usable].sum(0) / a[usable].sum(0)
        np.testing.assert_allclose(ratio, gains[i], rtol=0.03)
        depth = np.load(plain / "ground_truth" / "depth" / f"view_{i:04d}.npy")
        s = cv2.imread(str(sky / "images" / f"view_{i:04d}.png"))
        p = cv2.imread(str(plain / "images" / f"view_{i:04d}.png"))
        assert (p[depth == 0] == 0).all() and (s[depth == 0] > 100).all()
        np.testing.assert_array_equal(s[depth > 0], p[depth > 0])


def test_multi_distance_spreads_camera_distances():
    near_far = scene_config("city-block").setup().viewmats
    single = scene_config("city-block", effects={"multi_distance": False}).setup().viewmats

    def spread(viewmats):
        centers = -np.einsum("cji,cj->ci", viewmats[:, :3, :3], viewmats[:, :3, 3])
        distance = np.linalg.norm(centers, axis=1)
        return distance.max() / distance.min()

    assert spread(near_far) > 2.5 and spread(single) < 1.3


def test_cache_hit_and_key(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path))
    first = generate_scene("tiny", num_views=3)
    assert first.parent == tmp_path / "scenes" and (first / "scene.json").is_file()
    # a cold cache says what the wait is, with the views as they are rendered
    assert capsys.readouterr().err.splitlines() == [
        f"hico: rendering the built-in scene tiny (3 views at 64x48), first run only; cached in {tmp_path / 'scenes'}",
        "  rendered 1/3 views", "  rendered 2/3 views", "  rendered 3/3 views"]

    def no_render(*args, **kwargs):
        raise AssertionError("cache miss")

    monkeypatch.setattr(gen, "write_scene", no_render)
    assert generate_scene("tiny", num_views=3) == first
    assert capsys.readouterr().err == ""  # a cached scene is silent
    with pytest.raises(AssertionError, match="cache miss"):
        generate_scene("tiny", num_views=4)  # other parameters, other cache entry


def test_view_progress_in_a_log_is_a_line_every_tenth_of_the_views():
    import io

    log = io.StringIO()
    report = gen.view_progress(72, log)
    for done in range(1, 73):
        report(done)
    assert log.getvalue().splitlines() == [f"  rendered {done}/72 views" for done in (*range(7, 71, 7), 72)]


def test_a_crash_leaves_no_partial_scene(tmp_path, monkeypatch):
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path))
    calls = []

    def flaky(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("disk full")
        return real(*args, **kwargs)

    real = gen.render_view
    monkeypatch.setattr(gen, "render_view", flaky)
    with pytest.raises(RuntimeError):
        generate_scene("tiny", num_views=3)
    assert list((tmp_path / "scenes").iterdir()) == []


def test_bad_parameters_are_one_line_errors(tmp_path):
    with pytest.raises(HicoError, match="no parameter 'views'"):
        generate_scene("tiny", tmp_path / "a", views=3)
    with pytest.raises(HicoError, match="unknown scene 'castle'"):
        generate_scene("castle", tmp_path / "b")
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "notes.txt").write_text("mine")
    with pytest.raises(HicoError, match="not a generated scene"):
        generate_scene("tiny", tmp_path / "c")


def test_cli_generates_and_reports(tmp_path, capsys):
    from hico_plugin.cli.scene import entrypoint, main

    out = main(["tiny", "--out", str(tmp_path / "cli"), "--num-views", "4"])
    printed = capsys.readouterr().out
    assert out == tmp_path / "cli" and "views      4 x 64x48" in printed and "declared: (none)" in printed
    main(["tiny", "--out", str(tmp_path / "cli"), "--num-views", "5"])  # regenerating replaces it
    assert len(list((tmp_path / "cli" / "images").iterdir())) == 5
    said = capsys.readouterr().err.splitlines()
    assert said[0] == f"hico: rendering the built-in scene tiny (5 views at 64x48) into {tmp_path / 'cli'}"
    import sys

    argv = sys.argv
    sys.argv = ["hico-scene", "tiny", "--out", str(tmp_path / "bad"), "--width", "2"]
    try:
        with pytest.raises(SystemExit) as exit_info:
            entrypoint()
    finally:
        sys.argv = argv
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip() == "error: scene 'tiny': width must be >= 8, got 2"


def test_every_scene_is_registered_with_declared_effects():
    assert {"tiny", "city-block", "pagoda", "room"} <= set(SCENES.names())
    assert scene_config("pagoda").effects.declared() == ["exposure", "sky", "sensor_noise"]


def test_pixel_colour_integrates_over_the_pixel():
    """n x n rays per pixel of a W x H view are exactly the pixel centres of the same view at nW x nH:
    the supersampled image equals the box-filtered large point-sampled one (sky included)."""
    n = 3
    scene = scene_config("city-block", **{**SMALL_CITY, "pixel_samples": n}).setup("city-block")
    big = scene_config("city-block", **{**SMALL_CITY, "width": 48 * n, "height": 32 * n,
                                        "pixel_samples": 1}).setup("city-block")
    viewmat, cfg = scene.viewmats[1], scene.config
    centre = render_view(scene.caster, viewmat, scene.K, 48, 32, scene.sun, cfg.ambient, cfg.shadows)
    small = gen._pixel_colour(scene, viewmat, centre, sky=True)
    large = render_view(big.caster, viewmat, big.K, 48 * n, 32 * n, big.sun, cfg.ambient, cfg.shadows)
    pooled = fx.apply_sky(large.rgb, large.hit, large.dirs_world).reshape(32, n, 48, n, 3).mean((1, 3))
    np.testing.assert_allclose(small, pooled, atol=1e-6)
    # and it is not the point-sampled image: edges and textures blend
    point = fx.apply_sky(centre.rgb, centre.hit, centre.dirs_world)
    assert np.abs(small - point).max() > 0.1
