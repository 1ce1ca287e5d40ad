"""Trainer end to end on the toy model: run directory, resume, Ctrl-C, non-finite losses, callbacks."""

import json
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest
import torch

from hico_plugin.engine import TrainerCallback, load_config, load_run
from hico_plugin.engine.checkpoints import latest_checkpoint, list_checkpoints, load_checkpoint
from hico_plugin.engine.data import batch_positions, make_batch, rank_slice
from hico_plugin.errors import HicoError
from helpers_toy_model import ToyDataset, ToyModelConfig, toy_config

TESTS_DIR = Path(__file__).resolve().parents[1]  # tests/, where the helpers live


def final_state(trainer):
    return {k: v.detach().clone() for k, v in trainer.model.state_dict().items()}


def assert_states_close(a, b, atol=1e-6):
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].shape == b[key].shape, key
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=atol, msg=key)


def test_batches_cover_each_epoch_without_replacement():
    positions = torch.cat([batch_positions(10, 2, seed=3, step=s) for s in range(5)])
    assert sorted(positions.tolist()) == list(range(10))
    assert torch.equal(batch_positions(10, 4, 3, 7), batch_positions(10, 4, 3, 7))
    assert not torch.equal(batch_positions(10, 10, 3, 0), batch_positions(10, 10, 4, 0))
    # The global batch split over 2 ranks is the 1-rank batch.
    whole = batch_positions(10, 4, 3, 2)
    assert torch.equal(torch.cat([rank_slice(whole, r, 2) for r in range(2)]), whole)


def test_training_batches_carry_only_the_ground_truth_the_model_reads():
    dataset = ToyDataset(num_views=4, size=8, seed=0, with_depth=True)
    assert set(make_batch(dataset, [0, 1], torch.device("cpu")).gt) == {"depth"}  # default: everything
    assert make_batch(dataset, [0, 1], torch.device("cpu"), gt_keys=("mask",)).gt == {}


def test_train_writes_run_directory_and_learns(tmp_path):
    trainer = toy_config(tmp_path, eval_every=10).setup()
    result = trainer.train()
    run = tmp_path / "run"
    assert result.step == 24 and not result.interrupted
    # save_every=10 gives 10, 20 and the final 24; keep_checkpoints=2 keeps the newest two.
    assert [p.name for p in list_checkpoints(run / "checkpoints")] == ["step-000000020.ckpt", "step-000000024.ckpt"]
    lines = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    steps = [line for line in lines if "loss" in line]
    evals = [line for line in lines if "eval/psnr" in line]
    assert [line["step"] for line in steps] == list(range(24))
    assert {"psnr", "loss/mse", "lr/blobs", "lr/mlp", "num_anchors", "it_per_s"} <= steps[0].keys()
    assert sum(line["loss"] for line in steps[-4:]) / 4 < steps[0]["loss"] / 2
    assert len(evals) == 3  # steps 10, 20 and the end
    assert steps[-1]["num_anchors"] == 6 + 4  # densified at steps 4, 9, 14, 19: +1 blob each

    document = json.loads((run / "eval.json").read_text())
    assert document["experiment_name"] == "toy-scene" and document["method_name"] == "toy"
    assert document["checkpoint"].endswith("step-000000024.ckpt")
    results = document["results"]
    for key in ("psnr", "psnr_std", "fps", "num_anchors", "num_gaussians", "train_seconds", "depth_abs_rel"):
        assert isinstance(results[key], float), key
    assert results["lpips"] is None and "rgb" not in results
    assert results["depth_abs_rel"] == pytest.approx(0.2)
    assert results["num_views"] == 3

    # config.yml reloads the run exactly, and load_run gives the trained model back.
    assert load_config(run / "config.yml") == trainer.config
    loaded = load_run(run / "config.yml")
    model = loaded.model
    assert not model.training and model.features.shape == trainer.model.features.shape
    assert_states_close(final_state(trainer), {k: v for k, v in model.state_dict().items()}, atol=0)


def test_existing_run_needs_resume_or_overwrite(tmp_path):
    toy_config(tmp_path, max_steps=2).setup().train()
    with pytest.raises(HicoError, match="--resume"):
        toy_config(tmp_path, max_steps=2).setup()
    toy_config(tmp_path, max_steps=3, overwrite=True).setup().train()
    assert [p.name for p in list_checkpoints(tmp_path / "run" / "checkpoints")] == ["step-000000003.ckpt"]


class StopAt(TrainerCallback):
    """Asks the trainer to stop after ``step`` (what Ctrl-C does)."""

    def __init__(self, step):
        self.step = step
        self.trainer = None

    def on_train_start(self, trainer, step):
        self.trainer = trainer

    def on_step_end(self, step, metrics):
        if step == self.step:
            self.trainer.request_stop()


def test_resume_equals_uninterrupted_run_across_resizes(tmp_path):
    # noise > 0 draws from the global RNG every step, so RNG restoration is exercised too.
    model = ToyModelConfig(noise=0.01)
    straight = toy_config(tmp_path / "a", model=model, save_every=0).setup()
    straight.train()

    stop = StopAt(11)  # stops after 12 steps: densified twice (shapes changed), more to come
    first = toy_config(tmp_path / "b", model=model, save_every=0).setup(callbacks=[stop])
    result = first.train()
    assert result.interrupted and result.step == 12
    assert result.checkpoint.name == "step-000000012.ckpt"
    assert not (tmp_path / "b" / "run" / "eval.json").exists()
    torch.manual_seed(12345)  # the resumed run must not depend on the RNG it starts with
    resumed = toy_config(tmp_path / "b", model=model, save_every=0, resume=True).setup()
    assert resumed.step == 12 and resumed.model.features.shape[0] == 8
    resumed.train()
    assert_states_close(final_state(straight), final_state(resumed), atol=1e-6)


def test_a_complete_run_releases_the_adam_moments_its_last_checkpoint_holds(tmp_path):
    trainer = toy_config(tmp_path, save_every=0).setup()
    trainer.train()
    assert all(not optimizer.state for optimizer in trainer.optimizers.optimizers.values())
    saved = load_checkpoint(latest_checkpoint(tmp_path / "run" / "checkpoints"))["optimizers"]
    moments = [entry for group in saved.values() for entry in group["state"].values()]
    assert moments and all(entry["exp_avg"].abs().sum() > 0 for entry in moments)


def test_nonfinite_losses_skip_then_stop_without_touching_the_last_checkpoint(tmp_path):
    config = toy_config(tmp_path, model=ToyModelConfig(nan_steps=(3,) + tuple(range(5, 40))),
                        save_every=5, max_nonfinite_steps=4)
    trainer = config.setup()
    with pytest.raises(HicoError, match="4 non-finite losses in a row"):
        trainer.train()
    lines = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [line["step"] for line in lines if line.get("skipped")] == [3, 5, 6, 7, 8]
    assert all(torch.isfinite(p).all() for p in trainer.model.parameters())
    # The checkpoint after 5 steps is the state the skipped steps 5..8 left untouched.
    checkpoint = latest_checkpoint(tmp_path / "run" / "checkpoints")
    assert checkpoint.name == "step-000000005.ckpt"
    payload = load_checkpoint(checkpoint)
    assert_states_close(payload["model"], final_state(trainer), atol=0)


def test_request_checkpoint_pause_and_lock(tmp_path):
    trainer = toy_config(tmp_path, max_steps=6, save_every=0, keep_checkpoints=0).setup()
    seen, steps_while_paused = [], []

    def checkpoint_while_paused():
        steps_while_paused.append(trainer.step)
        trainer.request_checkpoint()

    def resume():
        steps_while_paused.append(trainer.step)
        trainer.resume_training()

    class Controls(TrainerCallback):
        def on_step_end(self, step, metrics):
            seen.append(step)
            if step == 1:
                trainer.request_checkpoint()
            if step == 2:
                trainer.pause()
                threading.Timer(0.1, checkpoint_while_paused).start()
                threading.Timer(0.4, resume).start()

    trainer.add_callback(Controls())
    trainer.train()
    assert seen == list(range(6))
    assert steps_while_paused == [3, 3]
    names = [p.name for p in list_checkpoints(tmp_path / "run" / "checkpoints")]
    assert names == ["step-000000002.ckpt", "step-000000003.ckpt", "step-000000006.ckpt"]
    assert trainer.lock.acquire(timeout=1)
    trainer.lock.release()


def test_bad_config_is_one_clear_error(tmp_path):
    with pytest.raises(HicoError, match="config.batch_size"):
        toy_config(tmp_path, batch_size=0).setup()
    with pytest.raises(HicoError, match="config file not found"):
        load_config(tmp_path / "missing.yml")


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM", "SIGHUP"])
def test_stop_signals_save_a_checkpoint_and_exit_cleanly(tmp_path, signame):
    script = textwrap.dedent(f"""
        import os, signal, sys
        sys.path.insert(0, {str(TESTS_DIR)!r})
        from pathlib import Path
        from hico_plugin.engine import TrainerCallback, TrainerConfig
        from helpers_toy_model import ToyDataConfig, ToyModelConfig, toy_config

        # as a terminal starts a command (this test may run as a background job or under nohup, whose
        # ignored SIGINT / SIGHUP the trainer keeps ignored)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGHUP, signal.SIG_DFL)

        class Interrupt(TrainerCallback):
            def on_step_end(self, step, metrics):
                if step == 4:
                    os.kill(os.getpid(), signal.{signame})  # Ctrl-C, kill, a closed terminal

        config = TrainerConfig(output_dir=Path({str(tmp_path / "run")!r}), data=ToyDataConfig(),
                               model=ToyModelConfig(), max_steps=1000, device="cpu", progress="none",
                               vis="none", save_every=0)
        result = config.setup(callbacks=[Interrupt()]).train()
        print("stopped at", result.step, result.interrupted)
    """)
    completed = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert completed.returncode == 0, completed.stderr
    assert "stopped at 5 True" in completed.stdout
    assert f"{signame}: saving a checkpoint" in completed.stderr
    assert latest_checkpoint(tmp_path / "run" / "checkpoints").name == "step-000000005.ckpt"


def test_unreadable_checkpoint_and_missing_checkpoint_are_clear_errors(tmp_path):
    config = toy_config(tmp_path, max_steps=2)
    config.setup()  # writes config.yml, no checkpoint yet
    with pytest.raises(HicoError, match="no checkpoint found"):
        load_run(tmp_path / "run" / "config.yml")
    checkpoints = tmp_path / "run" / "checkpoints"
    checkpoints.mkdir()
    (checkpoints / ".step-000000009.ckpt.abc.tmp").write_bytes(b"torn")  # an interrupted write: ignored
    (checkpoints / "step-000000005.ckpt").write_bytes(b"not a checkpoint")
    assert latest_checkpoint(checkpoints).name == "step-000000005.ckpt"
    with pytest.raises(HicoError, match=r"none of the 1 checkpoints is readable \(.*step-000000005.ckpt: not a readable"):
        toy_config(tmp_path, max_steps=2, resume=True).setup()


def test_run_length_follows_the_photos_past_steps_photos(tmp_path):
    """steps_photos: max_steps for captures up to that many training photos, proportionally more
    beyond (each photo seen as often); the sized config is written and a resume keeps it."""
    config = toy_config(tmp_path, max_steps=4, save_every=0)  # the toy has 9 training views
    assert config.sized_for(9) is config
    assert toy_config(tmp_path, max_steps=4, steps_photos=9).sized_for(9).max_steps == 4
    sized = toy_config(tmp_path, max_steps=4, steps_photos=3).sized_for(9)
    assert (sized.max_steps, sized.steps_photos) == (12, 9) and sized.sized_for(9) == sized
    assert toy_config(tmp_path, max_steps=10, steps_photos=4).sized_for(9).max_steps == 23  # ceil(22.5)
    trainer = toy_config(tmp_path, max_steps=4, steps_photos=3, save_every=0).setup()
    assert trainer.config.max_steps == 12
    assert trainer.train().step == 12
    assert load_config(tmp_path / "run" / "config.yml").max_steps == 12
    resumed = toy_config(tmp_path, max_steps=4, steps_photos=3, save_every=0, resume=True).setup()
    assert resumed.step == 12 and resumed.config.max_steps == 12
