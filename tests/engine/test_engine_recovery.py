"""Every stop is recoverable: one trainer per run, resume without duplicate log lines, a bad file found
late keeps the model, write errors are one line, an interrupted hico-train exits 130."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from helpers_toy_model import ToyDataConfig, ToyDataset
from helpers_toy_model import toy_config

from hico_plugin.engine.checkpoints import latest_checkpoint
from hico_plugin.engine.run_dir import run_directory, trim_metrics
from hico_plugin.engine.stopping import EXIT_INTERRUPTED
from hico_plugin.errors import HicoError

TESTS_DIR = Path(__file__).resolve().parents[1]  # tests/, where the helpers live


def test_second_trainer_on_a_run_refuses_in_one_line(tmp_path):
    first = toy_config(tmp_path, max_steps=2).setup()
    with pytest.raises(HicoError, match=r"run: another trainer \(pid \d+\) is writing this run") as info:
        toy_config(tmp_path, max_steps=2, overwrite=True).setup()
    assert "\n" not in str(info.value)
    first.train()  # releases the lock: the run can be continued afterwards
    toy_config(tmp_path, max_steps=4, resume=True).setup().train()


def test_lock_of_a_killed_trainer_does_not_block(tmp_path):
    script = textwrap.dedent(f"""
        import os, sys
        sys.path.insert(0, {str(TESTS_DIR)!r})
        from pathlib import Path
        from helpers_toy_model import toy_config
        toy_config(Path({str(tmp_path)!r}), max_steps=2).setup()
        os._exit(9)  # dies holding the lock, as a SIGKILL would leave it
    """)
    subprocess.run([sys.executable, "-c", script], check=False, timeout=120)
    assert (tmp_path / "run" / ".lock").exists()
    toy_config(tmp_path, max_steps=2).setup().train()


def test_resume_trims_metrics_to_the_checkpoint(tmp_path):
    toy_config(tmp_path, max_steps=8, save_every=5, log_every=1, keep_checkpoints=0).setup().train()
    metrics = tmp_path / "run" / "metrics.jsonl"
    for path in sorted((tmp_path / "run" / "checkpoints").iterdir())[1:]:
        path.unlink()  # as if killed after step 5's checkpoint but with steps 5..7 logged
    with metrics.open("a") as stream:
        stream.write('{"step": 7, "tr')  # a half-written line of a killed run
    toy_config(tmp_path, max_steps=8, save_every=5, log_every=1, resume=True).setup().train()
    steps = [json.loads(line)["step"] for line in metrics.read_text().splitlines()
             if not any(k.startswith("eval/") for k in json.loads(line))]
    assert steps == list(range(8))


def test_trim_metrics_keeps_earlier_lines(tmp_path):
    path = tmp_path / "metrics.jsonl"
    path.write_text("".join(json.dumps({"step": s, "loss": 1.0}) + "\n" for s in range(6)))
    assert trim_metrics(path, 4) == 2
    assert [json.loads(line)["step"] for line in path.read_text().splitlines()] == [0, 1, 2, 3]


class _BrokenTestView(ToyDataset):
    def image(self, i):
        if i in {int(t) for t in self.test_indices}:
            raise HicoError(f"image view_{i:03d}.png: unreadable or truncated image file")
        return super().image(i)


class BrokenTestDataConfig(ToyDataConfig):
    def setup(self, **kwargs):
        dataset = super().setup(**kwargs)
        dataset.__class__ = _BrokenTestView
        return dataset


def test_bad_test_image_at_final_eval_keeps_the_model(tmp_path):
    trainer = toy_config(tmp_path, max_steps=6, save_every=0, data=BrokenTestDataConfig()).setup()
    with pytest.raises(HicoError) as info:
        trainer.train()
    message = str(info.value)
    assert "\n" not in message and "unreadable or truncated" in message
    assert "model of step 6 is saved in" in message and "hico-eval --load-config" in message
    assert latest_checkpoint(tmp_path / "run" / "checkpoints").name == "step-000000006.ckpt"


def test_checkpoint_write_error_during_training_is_one_line(tmp_path, monkeypatch):
    trainer = toy_config(tmp_path, max_steps=12, save_every=5).setup()

    original = torch.save
    calls = []

    def fill_disk(obj, stream, *args, **kwargs):
        calls.append(1)
        if len(calls) > 1:
            raise OSError(28, "No space left on device")
        return original(obj, stream, *args, **kwargs)

    monkeypatch.setattr(torch, "save", fill_disk)
    with pytest.raises(HicoError, match=r"step-000000010\.ckpt: cannot write the checkpoint \(No space left on device\)"):
        trainer.train()
    assert [p.name for p in (tmp_path / "run" / "checkpoints").iterdir()] == ["step-000000005.ckpt"]


def test_run_directory_follows_nerfstudio(tmp_path):
    base = tmp_path / "outputs" / "scene" / "hico-gs"
    fresh = run_directory(base, "", resume=False)
    assert fresh.parent == base and len(fresh.name) == len("2026-01-01_120000")
    assert run_directory(base, "mine", resume=False) == base / "mine"
    with pytest.raises(HicoError, match="--resume: no run under"):
        run_directory(base, "", resume=True)
    for name in ("2026-01-01_120000", "2026-02-01_120000"):
        (base / name).mkdir(parents=True)
        (base / name / "config.yml").write_text("")
    assert run_directory(base, "", resume=True) == base / "2026-02-01_120000"
    with pytest.raises(HicoError, match="--timestamp"):
        run_directory(base, "../x", resume=False)


def test_interrupted_hico_train_exits_130_with_the_resume_command(tmp_path):
    """hico-train on a built-in tiny scene, SIGTERM after a few steps: checkpoint, exit 130."""
    script = textwrap.dedent(f"""
        import os, signal, sys
        from hico_plugin.cli import train as train_cli
        from hico_plugin.engine import TrainerCallback
        from hico_plugin.engine.trainer import Trainer

        class Kill(TrainerCallback):
            def on_step_end(self, step, metrics):
                if step == 2:
                    os.kill(os.getpid(), signal.SIGTERM)

        setup = Trainer.__init__
        def with_kill(self, *args, **kwargs):
            setup(self, *args, **kwargs)
            self.add_callback(Kill())
        Trainer.__init__ = with_kill
        train_cli.entrypoint(["hico-gs-lite", "--scene", "tiny", "--max-steps", "50", "--vis", "none",
                              "--output-dir", {str(tmp_path / "run")!r}])
    """)
    env = {**os.environ, "HICO_NO_FUSED": "1"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == EXIT_INTERRUPTED, done.stderr[-2000:]
    assert "SIGTERM: saving a checkpoint" in done.stderr
    assert "continue with: hico-train" in done.stderr and "--resume" in done.stderr
    assert latest_checkpoint(tmp_path / "run" / "checkpoints").name == "step-000000003.ckpt"


def test_a_checkpoint_loads_in_its_own_frame_and_one_from_another_scene_frame_is_refused(tiny_run, tmp_path):
    """Checkpoints record the dataset's frame (the scene normalisation). One whose heading differs from
    today's (seed points triangulated again) loads and resumes in its own frame; loading or resuming one
    whose cameras sit elsewhere today (a changed rule, other settings) would be silently wrong."""
    import shutil

    from hico_plugin.cli.train import parse, train
    from hico_plugin.data.transform import SceneTransform, rotation_about_z
    from hico_plugin.engine.loading import load_run

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    config = run / "config.yml"
    config.write_text(config.read_text().replace(str(tiny_run), str(run)))
    checkpoint = sorted((run / "checkpoints").glob("*.ckpt"))[-1]
    payload = torch.load(checkpoint, weights_only=True)
    assert load_run(config).dataset.frame() == payload["frame"]  # recorded, and today's matches
    turned = SceneTransform.from_dict(payload["frame"])
    turned.rotation = rotation_about_z(0.004) @ turned.rotation
    payload["frame"] = turned.to_dict()
    torch.save(payload, checkpoint)
    assert load_run(config).dataset.frame() == payload["frame"]
    args = ["hico-gs-lite", "--scene", "tiny", "--max-steps", "3", "--vis", "none", "--progress", "none",
            "--output-dir", str(run), "--resume", "--model.eval-lpips", "none", "--model.renderer.no-use-compile"]
    train(parse(args))
    checkpoint = sorted((run / "checkpoints").glob("*.ckpt"))[-1]
    resumed = torch.load(checkpoint, weights_only=True)
    assert resumed["step"] == 3 and resumed["frame"] == payload["frame"]
    payload = resumed
    payload["frame"]["scale"] *= 2.0
    torch.save(payload, checkpoint)
    with pytest.raises(HicoError, match=r"another scene frame than the dataset is loaded in now \(scale differ\)"):
        load_run(config)
    with pytest.raises(HicoError, match="another scene frame"):
        train(parse(args))
