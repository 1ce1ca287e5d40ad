"""Plug-ins from outside: a real distribution declaring ``hico_plugin.components`` entry points adds
an aggregator and a preset that ``hico-train`` lists and trains, a loss that ``hico-train`` offers
and logs, and an exporter that ``hico-export`` runs; a broken one is one warning."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).parent / "plugin_example"
REPO = Path(__file__).resolve().parents[1]


def _run(args: list[str], site: Path, cwd: Path) -> subprocess.CompletedProcess:
    # The installed plug-in is visible only through PYTHONPATH, as a --target install would be.
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(site)]))
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def _cli(name: str) -> str:
    return str(Path(sys.executable).with_name(name))


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The example plug-in pip-installed (a real wheel build: dist-info with entry_points.txt)."""
    work = tmp_path_factory.mktemp("plugin")
    shutil.copytree(EXAMPLE, work / "src")  # setuptools writes build/ and egg-info beside the sources
    target = work / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--no-index", "--target", str(target), str(work / "src")], check=True, timeout=300)
    entry_points = next(target.glob("hico_example_plugin-*.dist-info")) / "entry_points.txt"
    assert "[hico_plugin.components]" in entry_points.read_text()
    return target


def test_plugin_components_are_registered_by_name(site, tmp_path):
    code = ("from hico_plugin.field.context import CONTEXT_AGGREGATORS; "
            "from hico_plugin.presets import all_presets; "
            "print(CONTEXT_AGGREGATORS.names(), sorted(all_presets()))")
    result = _run([sys.executable, "-c", code], site, tmp_path)
    assert result.returncode == 0, result.stderr
    assert "'gated-mean'" in result.stdout and "'example-gated'" in result.stdout
    without = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                             env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert without.returncode == 0 and "gated-mean" not in without.stdout


def test_hico_train_lists_and_trains_the_plugin_preset(site, tmp_path):
    listed = _run([_cli("hico-train"), "--help"], site, tmp_path)
    assert listed.returncode == 0, listed.stderr
    assert "example-gated" in listed.stdout

    out = tmp_path / "run"
    trained = _run([_cli("hico-train"), "example-gated", "--scene", "tiny", "--max-steps", "2", "--vis", "none",
                    "--progress", "none", "--output-dir", str(out), "--model.eval-lpips", "none",
                    "--model.renderer.no-use-compile"], site, tmp_path)
    assert trained.returncode == 0, trained.stderr
    text = (out / "config.yml").read_text()
    assert "kind: gated-mean" in text and "method_name: example-gated" in text
    assert json.loads((out / "eval.json").read_text())["results"]["step"] == 2
    assert "eval: psnr" in trained.stdout


def _train_tiny(site: Path, cwd: Path, out: Path, *flags: str, steps: int = 3) -> subprocess.CompletedProcess:
    return _run([_cli("hico-train"), "hico-gs-lite", "--scene", "tiny", "--max-steps", str(steps), "--log-every", "1",
                 "--vis", "none", "--progress", "none", "--output-dir", str(out), "--model.eval-lpips", "none",
                 "--model.renderer.no-use-compile", *flags], site, cwd)


def _logged_terms(run: Path) -> set[str]:
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    return {key for record in records for key in record if key.startswith("loss/")}


def test_a_plugin_loss_is_an_option_of_every_preset_and_adds_its_term(site, tmp_path):
    listed = _run([_cli("hico-train"), "hico-gs-lite", "--help"], site, tmp_path)
    assert listed.returncode == 0, listed.stderr
    assert "--model.losses.opacity-entropy.enabled" in listed.stdout
    assert "--model.losses.opacity-entropy.weight" in listed.stdout

    plain = _train_tiny(site, tmp_path, tmp_path / "plain")
    assert plain.returncode == 0, plain.stderr
    assert "loss/opacity_entropy" not in _logged_terms(tmp_path / "plain")  # offered, off unless asked for

    on = _train_tiny(site, tmp_path, tmp_path / "on", "--model.losses.opacity-entropy.enabled",
                     "--model.losses.opacity-entropy.weight", "0.5")
    assert on.returncode == 0, on.stderr
    assert {"loss/rgb_l1", "loss/rgb_dssim", "loss/opacity_entropy"} <= _logged_terms(tmp_path / "on")
    records = [json.loads(line) for line in (tmp_path / "on" / "metrics.jsonl").read_text().splitlines()]
    assert all(r["loss/opacity_entropy"] > 0 for r in records if "loss/opacity_entropy" in r)
    assert "weight: 0.5" in (tmp_path / "on" / "config.yml").read_text()


def test_a_plugin_exporter_is_a_subcommand_of_hico_export(site, tmp_path):
    listed = _run([_cli("hico-export"), "--help"], site, tmp_path)
    assert listed.returncode == 0, listed.stderr
    assert "camera-poses" in listed.stdout and "gaussians" in listed.stdout

    run = tmp_path / "run"
    assert _train_tiny(site, tmp_path, run, steps=1).returncode == 0  # its config.yml names the plug-in's loss
    out = tmp_path / "poses.json"
    exported = _run([_cli("hico-export"), "--load-config", str(run / "config.yml"), "camera-poses",
                     "--output", str(out)], site, tmp_path)
    assert exported.returncode == 0, exported.stderr
    views = json.loads(out.read_text())["views"]
    config = subprocess.run([sys.executable, "-c", "from hico_plugin.engine import load_run; "
                             f"r = load_run({str(run / 'config.yml')!r}); print(len(r.dataset.cameras))"],
                            cwd=tmp_path, capture_output=True, text=True,
                            env=dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(site)])))
    assert config.returncode == 0, config.stderr
    assert len(views) == int(config.stdout.split()[-1]) and len(views[0]["viewmat"]) == 4


def test_a_broken_plugin_is_one_warning_not_a_crash(tmp_path):
    site = tmp_path / "site"
    (site / "broken_plugin-1.0.dist-info").mkdir(parents=True)
    (site / "broken_plugin-1.0.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: broken-plugin\nVersion: 1.0\n")
    (site / "broken_plugin-1.0.dist-info" / "entry_points.txt").write_text(
        "[hico_plugin.components]\nbroken = broken_plugin\n")
    (site / "broken_plugin.py").write_text("raise RuntimeError('this plug-in is broken')\n")
    result = _run([_cli("hico-train"), "--help"], site, tmp_path)
    assert result.returncode == 0, result.stderr
    assert "hico-gs-lite" in result.stdout
    warnings = [line for line in result.stderr.splitlines() if "Warning" in line]
    assert len(warnings) == 1, result.stderr
    assert "'broken'" in warnings[0] and "broken-plugin" in warnings[0] and "this plug-in is broken" in warnings[0]


def _nerf_synthetic(root: Path) -> tuple[Path, int]:
    """The tiny scene in the NeRF-synthetic layout (every 4th view in transforms_test.json) and its
    number of test views."""
    import numpy as np
    import pycolmap

    from hico_plugin.scenes.generate import generate_scene

    scene = generate_scene("tiny", root / "scene")
    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    shutil.copytree(scene / "images", root / "blender" / "images")
    camera = next(iter(model.cameras.values()))
    fx, fy, cx, cy = camera.params[:4]
    splits: dict[str, list] = {"train": [], "test": []}
    for i, image in enumerate(sorted(model.images.values(), key=lambda im: im.name)):
        c2w = np.eye(4)
        c2w[:3, :] = image.cam_from_world().inverse().matrix()
        c2w[:, 1:3] *= -1  # OpenCV -> OpenGL camera axes, as Blender's files store them
        splits["test" if i % 4 == 0 else "train"].append(
            {"file_path": f"images/{image.name}", "transform_matrix": c2w.tolist()})
    for split, frames in splits.items():
        meta = {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": camera.width, "h": camera.height, "frames": frames}
        (root / "blender" / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root / "blender", len(splits["test"])


def test_a_plugin_dataset_format_is_named_on_the_command_line(site, tmp_path):
    data, num_test = _nerf_synthetic(tmp_path)
    for command in (["hico-train", "hico-gs-lite"], ["hico-inspect"], ["hico-bench", "quick"]):
        listed = _run([_cli(command[0]), *command[1:], "--help"], site, tmp_path)
        assert listed.returncode == 0, listed.stderr
        assert "nerf-synthetic" in listed.stdout and "transforms" in listed.stdout, command

    # the command's own options come before the format subcommand, the format's after it
    inspected = _run([_cli("hico-inspect"), "--no-effects", str(data), "nerf-synthetic", "--random-points", "500"],
                     site, tmp_path)
    assert inspected.returncode == 0, inspected.stderr
    assert f"{num_test} test" in inspected.stdout  # the layout's own test file, not --test-every
    without = _run([_cli("hico-inspect"), str(data), "nerf-synthetic"], tmp_path / "empty", tmp_path)
    assert without.returncode != 0 and "nerf-synthetic" in without.stderr  # the name exists only with the plug-in

    out = tmp_path / "run"
    trained = _train_tiny(site, tmp_path, out, "--data", str(data), "nerf-synthetic", "--random-points", "500", steps=2)
    assert trained.returncode == 0, trained.stderr
    assert "hico_example_plugin.nerf_synthetic.NerfSyntheticFormat" in (out / "config.yml").read_text()
    assert json.loads((out / "eval.json").read_text())["results"]["step"] == 2
    reloaded = _run([sys.executable, "-c", "from hico_plugin.engine import load_run; "
                     f"r = load_run({str(out / 'config.yml')!r}); print(len(r.dataset.test_indices))"], site, tmp_path)
    assert reloaded.returncode == 0, reloaded.stderr
    assert int(reloaded.stdout.split()[-1]) == num_test


def test_a_plugin_effect_is_detected_chosen_built_and_trained(site, tmp_path):
    """The example's ``vignetting`` effect: one file and one entry point. hico-inspect reports its
    finding, ``auto`` decides it from that finding, ``=on`` builds its module and trains its group."""
    from hico_plugin.scenes.generate import generate_scene

    inspected = _run([_cli("hico-inspect"), str(generate_scene("tiny"))], site, tmp_path)
    assert inspected.returncode == 0, inspected.stderr
    assert re.search(r"effect  vignetting +(yes|no ) — corners at [0-9.]+ of the centre's brightness", inspected.stdout)

    auto = _train_tiny(site, tmp_path, tmp_path / "auto", steps=1)
    assert auto.returncode == 0, auto.stderr
    assert re.search(r"effect  vignetting: (on|off) — corners at", auto.stdout)
    choices = json.loads((tmp_path / "auto" / "eval.json").read_text())["results"]["effects"]
    assert set(choices) == {"environment", "exposure", "lod", "vignetting"}

    on = _train_tiny(site, tmp_path, tmp_path / "on", "--model.effects", "auto,vignetting=on", steps=3)
    assert on.returncode == 0, on.stderr
    records = [json.loads(line) for line in (tmp_path / "on" / "metrics.jsonl").read_text().splitlines()]
    assert any(r.get("effect_parameters/vignetting") == 2.0 for r in records)
    assert any("lr/vignetting" in r for r in records)
    state = _run([sys.executable, "-c", "import torch; from hico_plugin.engine.checkpoints import list_checkpoints, "
                  f"load_checkpoint; from pathlib import Path; p = load_checkpoint(list_checkpoints(Path({str(tmp_path / 'on' / 'checkpoints')!r}))[-1]); "
                  "print(p['model']['effects.vignetting.k'].abs().sum().item())"], site, tmp_path)
    assert state.returncode == 0, state.stderr
    assert float(state.stdout.split()[-1]) > 0  # three steps moved the fall-off from zero
