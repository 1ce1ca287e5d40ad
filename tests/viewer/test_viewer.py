"""Viewer logic as pure functions: throttle, camera conversion, visualisation, stats, state adapter."""

from __future__ import annotations

import math
import threading

import cv2
import numpy as np
import pytest
import torch
from viser import transforms as vtf

from hico_plugin.viewer import (RunViewerState, camera_to_viser, model_render_fn, next_resolution, plan_render,
                                render_size, viser_to_camera)
from hico_plugin.visualization import (OUTPUT_NAMES, RenderOptions, apply_colormap, level_colors,
                                       normal_disagreement_degrees, normalize_percentile, normals_to_rgb, visualize)
from hico_plugin.viewer.demo import DemoDataset, DemoModel, depth_to_normal
from hico_plugin.viewer.state import evenly_spaced, make_thumbnail
from hico_plugin.viewer.throttle import refresh_interval
from hico_plugin.viewer.stats_panel import format_stats_markdown, plot_series


# ---------------------------------------------------------------------------------------- throttle
def test_next_resolution_scales_with_square_root_of_time_ratio():
    # 4x too slow -> half the side (a quarter of the pixels); on target -> unchanged.
    assert next_resolution(0.4, 0.1, 400, 64, 1024) == 200
    assert next_resolution(0.1, 0.1, 400, 64, 1024) == 400
    assert next_resolution(0.1 / 2.25, 0.1, 400, 64, 1024) == 600


def test_next_resolution_limits_step_and_clamps():
    assert next_resolution(100.0, 0.1, 400, 64, 1024) == 200  # at most halved per frame
    assert next_resolution(1e-6, 0.1, 400, 64, 1024) == 800  # at most doubled per frame
    assert next_resolution(100.0, 0.1, 100, 64, 1024) == 64
    assert next_resolution(1e-6, 0.1, 900, 64, 1024) == 1024
    assert next_resolution(0.0, 0.1, 300, 64, 1024) == 600  # unusable measurement: grow
    with pytest.raises(ValueError):
        next_resolution(0.1, 0.1, 300, 512, 256)


def test_plan_render_preview_while_moving_then_one_full_render():
    settle = 0.25
    assert plan_render(10.0, 9.9, 3, 2, False, settle) == "preview"  # camera moving
    assert plan_render(10.0, 9.9, 3, 3, False, settle) is None  # preview shown, not settled yet
    assert plan_render(10.0, 9.5, 3, 3, False, settle) == "full"  # settled: full resolution
    assert plan_render(10.0, 9.5, 3, 3, True, settle) is None  # full shown: nothing to do
    assert plan_render(10.0, 9.5, 4, 3, True, settle) == "full"  # change long ago (model update)
    assert plan_render(10.0, -math.inf, 4, 3, True, settle) == "full"


def test_plan_render_refreshes_for_training_progress_at_preview_size():
    settle = 0.25
    assert plan_render(10.0, 9.0, 3, 3, True, settle, model_changed=True) == "refresh"
    assert plan_render(10.0, 9.9, 4, 3, True, settle, model_changed=True) == "preview"  # the user comes first
    assert plan_render(10.0, 9.0, 3, 3, False, settle, model_changed=True) == "full"


def test_refresh_interval_bounds_the_renders_share_of_training_time():
    assert refresh_interval(2.0, 1.0, 0.2) == pytest.approx(8.0)
    assert refresh_interval(0.05, 1.0, 0.2) == 1.0
    assert refresh_interval(1.0, 0.0, 1.0) == 0.0
    with pytest.raises(ValueError):
        refresh_interval(1.0, 1.0, 0.0)


def test_render_size_keeps_aspect_and_longest_side():
    assert render_size(16 / 9, 512) == (512, 288)
    assert render_size(0.5, 512) == (256, 512)
    assert render_size(1.0, 100) == (100, 100)
    assert render_size(float("nan"), 64) == (64, 64)


# ---------------------------------------------------------------------------------------- cameras
def _look_down_minus_z_wxyz() -> np.ndarray:
    # Camera axes in world (OpenCV): x right = +x, y down = -y (world +y is up), z forward = -z.
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    return vtf.SO3.from_matrix(rotation).wxyz


def test_viser_to_camera_known_pose():
    fov_y = math.radians(60.0)
    camera = viser_to_camera(_look_down_minus_z_wxyz(), np.array([0.0, 0.0, 5.0]), fov_y, 400, 300)
    viewmat = camera.viewmat.double()
    assert torch.allclose(camera.center.double(), torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64), atol=1e-6)
    # World point 1 right, 2 up of the origin: camera coords x=1, y=-2 (down is +y), z=5 (in front).
    point_camera = viewmat @ torch.tensor([1.0, 2.0, 0.0, 1.0], dtype=torch.float64)
    assert torch.allclose(point_camera[:3], torch.tensor([1.0, -2.0, 5.0], dtype=torch.float64), atol=1e-6)
    focal = 150.0 / math.tan(math.radians(30.0))
    expected_K = torch.tensor([[focal, 0, 200.0], [0, focal, 150.0], [0, 0, 1]])
    assert torch.allclose(camera.K, expected_K, atol=1e-3)
    pixel = camera.K.double() @ point_camera[:3]
    u, v = (pixel[:2] / pixel[2]).tolist()
    assert u > 200.0 and v < 150.0  # right of and above the image centre
    # The top image edge sits at half the vertical fov above the optical axis.
    top = viewmat @ torch.tensor([0.0, 5.0 * math.tan(fov_y / 2), 0.0, 1.0], dtype=torch.float64)
    assert abs(float((camera.K.double() @ top[:3])[1] / top[2])) < 1e-3


def test_camera_to_viser_round_trip_matches_viser_pose_convention():
    generator = torch.Generator().manual_seed(3)
    wxyz = torch.nn.functional.normalize(torch.randn(4, generator=generator, dtype=torch.float64), dim=0).numpy()
    position = np.array([0.3, -1.2, 2.5])
    camera = viser_to_camera(wxyz, position, 0.9, 320, 240)
    back_wxyz, back_position, back_fov, aspect = camera_to_viser(camera)
    assert np.allclose(vtf.SO3(back_wxyz).as_matrix(), vtf.SO3(wxyz).as_matrix(), atol=1e-5)
    assert np.allclose(back_position, position, atol=1e-5)
    assert back_fov == pytest.approx(0.9, abs=1e-6) and aspect == pytest.approx(320 / 240)
    # viser: P_world = R p_camera + t, so the camera-frame +Z axis is the look direction.
    look = vtf.SO3(wxyz).as_matrix()[:, 2]
    ahead = camera.viewmat.double() @ torch.tensor([*(position + 2.0 * look), 1.0], dtype=torch.float64)
    assert torch.allclose(ahead[:3], torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64), atol=1e-5)


# ---------------------------------------------------------------------------------------- visualisation
def test_apply_colormap_matches_cv2_and_blacks_out_nan():
    values = np.array([[0.0, 1.0, np.nan, 2.0]])
    colors = apply_colormap(values, "turbo")
    turbo = cv2.applyColorMap(np.array([[0, 255]], np.uint8), cv2.COLORMAP_TURBO)[0, :, ::-1]
    assert colors.dtype == np.uint8 and colors.shape == (1, 4, 3)
    assert np.array_equal(colors[0, :2], turbo)
    assert np.array_equal(colors[0, 2], [0, 0, 0])
    assert np.array_equal(colors[0, 3], turbo[1])  # clipped to 1
    assert np.array_equal(apply_colormap(np.array([0.5]), "gray"), [[128, 128, 128]])
    with pytest.raises(ValueError):
        apply_colormap(values, "rainbow-unicorn")


def test_normalize_percentile_ignores_outliers_and_invalid_pixels():
    values = np.linspace(0.0, 1.0, 1001, dtype=np.float32).reshape(1, 1001)
    values[0, -1] = 1000.0  # one far outlier (sky)
    valid = np.ones_like(values, dtype=bool)
    valid[0, 0] = False
    scaled = normalize_percentile(values, valid, (0.0, 99.0))
    assert np.isnan(scaled[0, 0])
    assert scaled[0, 1] == pytest.approx(0.0) and scaled[0, -1] == pytest.approx(1.0)
    high = np.percentile(values[valid], 99.0)
    assert high < 2.0  # the outlier did not set the range
    assert scaled[0, 500] == pytest.approx((0.5 - 0.001) / (high - 0.001), rel=1e-4)
    assert np.isnan(normalize_percentile(values, np.zeros_like(valid))).all()


def test_normals_and_disagreement():
    normal = torch.tensor([[[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.0, 0.0, -3.0], [1.0, 0.0, 0.0]]])
    depth_normal = torch.tensor([[[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 2.0], [0.0, 1.0, 0.0]]])
    rgb = normals_to_rgb(normal)
    assert np.array_equal(rgb[0, 0], [128, 128, 0]) and np.array_equal(rgb[0, 1], [0, 0, 0])
    degrees = normal_disagreement_degrees(normal, depth_normal)[..., 0]
    assert degrees.shape == (1, 4)
    assert degrees[0, 0] == pytest.approx(0.0, abs=1e-3)
    assert np.isnan(degrees[0, 1])
    assert degrees[0, 2] == pytest.approx(180.0, abs=1e-3)  # length does not matter
    assert degrees[0, 3] == pytest.approx(90.0, abs=1e-3)


def test_visualize_every_output_of_the_demo_render():
    model = DemoModel()
    camera = DemoDataset(4).cameras[0].scaled(0.5)
    outputs = model.render_for_display(camera, RenderOptions())
    covered = outputs["alpha"][..., 0].numpy() > 0.5
    assert 0.2 < covered.mean() < 1.0  # the sky is not covered
    for name in OUTPUT_NAMES:
        image = visualize(outputs, RenderOptions(output=name))
        assert image.dtype == np.uint8 and image.shape == (camera.height, camera.width, 3), name
        assert image.std() > 5.0, f"{name} is flat"
        if name not in ("rgb", "alpha"):
            assert (image[~covered] == 0).all(), f"{name}: uncovered pixels must be black"
    # Identical normals: zero disagreement everywhere -> the colormap's first colour.
    same = {"normal": outputs["normal"], "depth_normal": outputs["normal"], "alpha": outputs["alpha"]}
    zero = visualize(same, RenderOptions(output="normal_disagreement"))
    assert (zero[covered] == apply_colormap(np.zeros(1))[0]).all()
    with pytest.raises(KeyError, match="depth_normal"):
        visualize({"normal": outputs["normal"]}, RenderOptions(output="normal_disagreement"))
    with pytest.raises(ValueError, match="output"):
        RenderOptions(output="nope")


def test_level_map_and_anchor_cloud_share_colours():
    levels = torch.tensor([[[0.0], [1.0], [3.0]]])
    image = visualize({"level": levels}, RenderOptions(output="level", num_levels=4))
    assert np.array_equal(image[0], level_colors(np.array([0, 1, 3]), 4))
    assert not np.array_equal(image[0, 0], image[0, 2])


def test_depth_to_normal_of_a_frontal_plane_faces_the_camera():
    K = torch.tensor([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]])
    normals = depth_to_normal(torch.full((24, 32), 3.0), K)
    assert torch.allclose(normals, torch.tensor([0.0, 0.0, -1.0]).expand(24, 32, 3), atol=1e-5)


# ---------------------------------------------------------------------------------------- stats panel
def test_format_stats_markdown_orders_known_keys_and_hides_learning_rates():
    text = format_stats_markdown(
        {"loss/rgb": 0.12345, "step": 1200, "it_per_s": 3.456, "lr/anchor": 0.01, "eval/psnr": 24.5, "num_gaussians": 51200.0},
        anchors_per_level=[10, 200, 3000],
    )
    lines = text.splitlines()
    assert lines[2] == "| step | 1,200 |" and lines[3] == "| it/s | 3.456 |"
    assert "| last eval PSNR | 24.5 |" in lines and "| Gaussians | 51,200 |" in lines
    assert "| loss/rgb | 0.1235 |" in lines and "| anchors per level | 10 / 200 / 3,000 |" in lines
    assert "lr/anchor" not in text
    assert format_stats_markdown({}) == "_no statistics yet_"


def test_plot_series_forward_fills_and_drops_empty_series():
    history = {"step": np.array([0.0, 1, 2, 3]), "loss": np.array([1.0, 0.8, 0.7, 0.6]), "psnr": np.array([np.nan, 20.0, np.nan, 22.0])}
    steps, series = plot_series(history)
    assert steps.tolist() == [0, 1, 2, 3]
    assert series["psnr"].tolist() == [20.0, 20.0, 20.0, 22.0]
    _, only_loss = plot_series({**history, "psnr": np.full(4, np.nan)})
    assert list(only_loss) == ["loss"]


# ---------------------------------------------------------------------------------------- state adapter
class _FakeTrainer:
    def __init__(self):
        self.lock = threading.RLock()
        self.is_paused = False
        self.checkpoints = 0

    def pause(self):
        self.is_paused = True

    def resume_training(self):
        self.is_paused = False

    def request_checkpoint(self):
        self.checkpoints += 1


def test_run_viewer_state_follows_a_trainer():
    dataset = DemoDataset(30)
    state = RunViewerState(DemoModel(), dataset, max_history=8)
    assert not state.is_training and state.stats()["num_anchors"] == 2700
    trainer = _FakeTrainer()
    state.on_train_start(trainer, 0)
    assert state.render_lock is trainer.lock and state.is_training
    state.set_paused(True)
    assert trainer.is_paused and state.is_paused
    state.request_checkpoint()
    assert trainer.checkpoints == 1
    for step in range(20):
        state.on_step_end(step, {"loss": 1.0 / (step + 1), "psnr": 10.0 + step, "it_per_s": 5.0})
    state.on_eval(19, {"psnr": 25.0, "image": object()})
    assert state.step == 20 and state.stats()["eval/psnr"] == 25.0
    history = state.history()
    assert len(history["step"]) <= 9 and history["step"][0] == 0 and history["step"][-1] >= 16  # span kept
    assert np.all(np.diff(history["step"]) > 0)
    state.on_train_end(19)
    assert not state.is_training


def test_training_cameras_are_capped_with_small_thumbnails():
    state = RunViewerState(DemoModel(), DemoDataset(30))
    training = state.training_cameras(max_cameras=7)
    assert len(training.cameras) == len(training.indices) == 7
    assert training.indices[0] == 0 and training.indices[-1] == 29
    assert torch.equal(training.cameras.viewmats[1], state.dataset.cameras.viewmats[training.indices[1]])
    thumbnail = state.thumbnail(training.indices[1], 40)
    assert thumbnail.dtype == np.uint8 and thumbnail.shape == (30, 40, 3)
    assert evenly_spaced(3, 10) == [0, 1, 2]
    assert make_thumbnail(np.ones((10, 20, 3), np.float32), 8).shape == (4, 8, 3)


def test_model_render_fn_renders_the_requested_output():
    render = model_render_fn(DemoModel())
    camera = DemoDataset(4).cameras[1].scaled(0.25)
    image = render(camera, RenderOptions(output="depth"))
    assert image.shape == (camera.height, camera.width, 3) and image.dtype == np.uint8
    assert not np.array_equal(image, render(camera, RenderOptions(output="rgb")))
    # LOD override: keeping only level 3 removes most surfaces (sky colour fills in).
    coverage_all = (render(camera, RenderOptions(output="alpha", colormap="gray")) > 127).mean()
    coverage_fine = (render(camera, RenderOptions(output="alpha", colormap="gray", level_range=(3, 3))) > 127).mean()
    assert coverage_fine < coverage_all

