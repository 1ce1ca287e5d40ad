"""Every refusal comes first: a bad argument, a run another trainer holds, a checkpoint of another scene
frame and too little disk space each end hico-train with one ``error:`` line (exit status 2) before any
image is decoded, the effects analysis runs or the model is built, even on a large dataset; hico-eval
(every command that loads a run) refuses a checkpoint of another frame before building the model."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from hico_plugin.cli import evaluate as eval_cli
from hico_plugin.cli import train as train_cli
from hico_plugin.engine import disk_space
from hico_plugin.engine.disk_space import OUTPUTS_BYTES, check_free_space, run_bytes_needed
from hico_plugin.errors import HicoError


@pytest.fixture
def slow_parts_forbidden(monkeypatch):
    """Decoding an image, the effects analysis and building the model fail the test if they run."""
    import hico_plugin.model.effects.base
    import hico_plugin.data.images
    from hico_plugin.model.hico import HiCoModelConfig

    def forbidden(what):
        def run(*args, **kwargs):
            raise AssertionError(f"{what} ran before the refusal")
        return run

    monkeypatch.setattr(hico_plugin.data.images, "decode", forbidden("decoding an image"))
    monkeypatch.setattr(hico_plugin.model.effects.base, "analyze_effects", forbidden("the effects analysis"))
    monkeypatch.setattr(HiCoModelConfig, "setup", forbidden("building the model"))


def only_line(entrypoint, argv: list[str], capfd) -> str:
    """The one line a refused command prints (stdout and stderr together); asserts exit status 2."""
    capfd.readouterr()
    with pytest.raises(SystemExit) as info:
        entrypoint(argv)
    out, err = capfd.readouterr()
    lines = (out + err).splitlines()
    assert info.value.code == 2, out + err
    assert len(lines) == 1 and lines[0].startswith("error: "), out + err
    return lines[0]


def train_args(data: Path, run: Path, *more: str) -> list[str]:
    return ["hico-gs-lite", "--data", str(data), "--output-dir", str(run), "--vis", "none", "--progress", "none",
            "--max-steps", "10", *more]


def test_a_run_another_trainer_holds_is_refused_first(large_colmap_dataset, tmp_path, capfd, slow_parts_forbidden):
    run = tmp_path / "run"
    script = ("import sys; from pathlib import Path; from hico_plugin.engine.run_dir import RunLock; "
              f"lock = RunLock(Path({str(run)!r})); lock.acquire(); print('locked', flush=True); sys.stdin.read()")
    holder = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        line = only_line(train_cli.entrypoint, train_args(large_colmap_dataset, run), capfd)
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)
    assert line == (f"error: {run}: another trainer (pid {holder.pid}) is writing this run; wait for it, "
                    "or choose another --output-dir")
    assert (run / ".lock").read_text() == f"pid {holder.pid}"  # the holder's run is left as it was


def test_resuming_a_checkpoint_of_another_frame_is_refused_first(large_colmap_dataset, tmp_path, capfd,
                                                                 slow_parts_forbidden):
    run = tmp_path / "run"
    checkpoint = run / "checkpoints" / "step-000000100.ckpt"
    checkpoint.parent.mkdir(parents=True)
    torch.save({"step": 100, "model": {}, "frame": {"centre": [0.0, 0.0, 0.0], "scale": 99.0,
                                                     "rotation": torch.eye(3).tolist()}}, checkpoint)
    line = only_line(train_cli.entrypoint, train_args(large_colmap_dataset, run, "--resume"), capfd)
    assert line.startswith(f"error: {checkpoint}: the model was trained in another scene frame")
    assert "(centre, scale differ)" in line
    assert checkpoint.is_file()  # the run it did not resume is kept


@pytest.mark.parametrize("resume", [[], ["--resume"]])  # resuming a run without checkpoints starts afresh
def test_too_little_disk_space_is_refused_first(large_colmap_dataset, tmp_path, capfd, slow_parts_forbidden,
                                                monkeypatch, resume):
    run = tmp_path / "run"
    monkeypatch.setattr(disk_space, "free_bytes", lambda folder: 2**20)
    line = only_line(train_cli.entrypoint, train_args(large_colmap_dataset, run, *resume), capfd)
    assert line.startswith(f"error: {run}: not enough disk space for the run: 1.0 MB free, about ")
    assert "choose another --output-dir" in line
    assert not run.exists()  # a refused run leaves no empty folder behind


@pytest.mark.parametrize("flag, value, field", [("--keep-checkpoints", "-1", "config.keep_checkpoints"),
                                                ("--model.effects", "sky=maybe", "--model.effects"),
                                                ("--test-every", "-3", "--test-every"),
                                                ("--downscale", "-2", "--downscale")])
def test_a_bad_argument_is_refused_first(large_colmap_dataset, tmp_path, capfd, slow_parts_forbidden, flag, value,
                                         field):
    run = tmp_path / "run"
    line = only_line(train_cli.entrypoint, train_args(large_colmap_dataset, run, flag, value), capfd)
    assert line.startswith(f"error: {field}: expected")
    assert not run.exists()  # refused before the run directory was made


def test_a_missing_dataset_folder_is_refused_before_the_run_directory_is_made(tmp_path, capfd):
    run = tmp_path / "run"
    line = only_line(train_cli.entrypoint, train_args(tmp_path / "no-such-data", run), capfd)
    assert line.startswith(f"error: data directory {tmp_path / 'no-such-data'}: not found")
    assert not run.exists()


def test_hico_eval_refuses_a_checkpoint_of_another_frame_before_the_analysis(tiny_run, tmp_path, capfd,
                                                                           slow_parts_forbidden):
    checkpoint = sorted((tiny_run / "checkpoints").glob("*.ckpt"))[-1]
    payload = torch.load(checkpoint, weights_only=True)
    payload["frame"]["scale"] *= 2.0
    moved = tmp_path / "step-000000002.ckpt"
    torch.save(payload, moved)
    line = only_line(eval_cli.entrypoint, ["--load-config", str(tiny_run / "config.yml"), "--checkpoint", str(moved)],
                     capfd)
    assert line.startswith(f"error: {moved}: the model was trained in another scene frame") and "(scale differ)" in line


def test_disk_space_rule_counts_kept_checkpoints_and_the_one_being_written(tmp_path, monkeypatch):
    # keep 3 of 7 saves (6 periodic + the final one): 3 kept + 1 temporary file at once
    assert run_bytes_needed(100, keep_checkpoints=3, max_steps=3_000, save_every=500) == 4 * 100 + OUTPUTS_BYTES
    # keep all: every save exists at the end, plus the temporary file of the last one
    assert run_bytes_needed(100, keep_checkpoints=0, max_steps=3_000, save_every=500) == 8 * 100 + OUTPUTS_BYTES
    # only the final checkpoint
    assert run_bytes_needed(100, keep_checkpoints=3, max_steps=3_000, save_every=0) == 2 * 100 + OUTPUTS_BYTES
    monkeypatch.setattr(disk_space, "free_bytes", lambda folder: 500)
    check_free_space(tmp_path, 500)
    check_free_space(tmp_path, 800, reclaimable=300)  # a resumed run's own checkpoints count as free
    with pytest.raises(HicoError, match=r"500 B free \(\+299 B of its old checkpoints\), about 800 B needed"):
        check_free_space(tmp_path, 800, reclaimable=299)


def test_free_bytes_reads_the_nearest_existing_folder(tmp_path):
    import shutil

    assert abs(disk_space.free_bytes(tmp_path / "not" / "yet") - shutil.disk_usage(tmp_path).free) < 2**30


def test_the_datasets_notes_are_printed_once_the_checks_pass(large_colmap_dataset, tmp_path, capfd, monkeypatch):
    from hico_plugin.model.hico import HiCoModelConfig

    class ModelSetup(Exception):
        pass

    def setup(self, **kwargs):
        out, err = capfd.readouterr()
        assert out == "" and err.splitlines() == [
            "downscale: images have a 1600 px long side; loading at 1/2 (--max-long-side 800; --downscale 1 keeps "
            "full resolution)"]
        raise ModelSetup

    monkeypatch.setattr(HiCoModelConfig, "setup", setup)
    capfd.readouterr()
    with pytest.raises(ModelSetup):
        train_cli.entrypoint(train_args(large_colmap_dataset, tmp_path / "run", "--max-long-side", "800"))
