"""hico-train refuses before anything slow: a held run lock, too little disk space, a checkpoint from
another scene frame and a bad argument each print one error line, and neither the dataset (for the
checks that do not need it) nor the model (whose analysis of the data takes minutes on large
captures) is built first."""

from __future__ import annotations

import shutil

import pytest

from hico_plugin.cli.train import entrypoint
from hico_plugin.data.sources import DataSourceConfig
from hico_plugin.engine import run_dir
from hico_plugin.engine.run_dir import RunLock
from hico_plugin.errors import HicoError
from hico_plugin.model.hico import HiCoModelConfig

QUIET = ["--vis", "none", "--progress", "none", "--model.eval-lpips", "none"]


def _never(what: str):
    def called(*args, **kwargs):
        raise AssertionError(f"{what} was built before the refusal")
    return called


def _refusal(capsys, argv: list[str]) -> str:
    """The one line hico-train prints before exiting with status 2."""
    with pytest.raises(SystemExit) as exit_info:
        entrypoint(argv)
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    lines = (captured.out + captured.err).splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("error: ")
    return lines[0]


def test_held_run_lock_refuses_before_the_dataset(tmp_path, monkeypatch, capsys):
    run = tmp_path / "run"
    lock = RunLock(run)
    lock.acquire()  # another trainer writing the run (flock is per open file, so this process counts)
    monkeypatch.setattr(DataSourceConfig, "setup", _never("the dataset"))
    monkeypatch.setattr(HiCoModelConfig, "setup", _never("the model"))
    try:
        line = _refusal(capsys, ["hico-gs-lite", "--scene", "tiny", "--output-dir", str(run), *QUIET])
    finally:
        lock.release()
    assert "another trainer (pid" in line and str(run) in line


def test_too_little_disk_space_refuses_before_the_dataset(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(run_dir, "free_bytes", lambda folder: 300 * 2**20)
    monkeypatch.setattr(DataSourceConfig, "setup", _never("the dataset"))
    monkeypatch.setattr(HiCoModelConfig, "setup", _never("the model"))
    run = tmp_path / "run"
    line = _refusal(capsys, ["hico-gs-lite", "--scene", "tiny", "--output-dir", str(run), *QUIET])
    assert f"{run}: 0.29 GiB free" in line and "at least 1 GiB" in line
    # The floor is a flag; 0 turns the check off and the run goes on to its dataset.
    def reached(*args, **kwargs):
        raise HicoError("reached the dataset")

    monkeypatch.setattr(DataSourceConfig, "setup", reached)
    line = _refusal(capsys, ["hico-gs-lite", "--scene", "tiny", "--output-dir", str(run), "--min-free-gb", "0",
                             *QUIET])
    assert line == "error: reached the dataset"


def test_checkpoint_from_another_frame_refuses_before_the_model(tiny_run, tmp_path, monkeypatch, capsys):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    monkeypatch.setattr(HiCoModelConfig, "setup", _never("the model"))
    line = _refusal(capsys, ["hico-gs-lite", "--scene", "tiny", "--output-dir", str(run), "--resume",
                             "--no-orient", *QUIET])
    assert "another scene frame" in line and "rotation" in line
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == \
        sorted(p.name for p in (tiny_run / "checkpoints").iterdir())


def test_bad_argument_refuses_before_the_run_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(DataSourceConfig, "setup", _never("the dataset"))
    run = tmp_path / "run"
    line = _refusal(capsys, ["hico-gs-lite", "--scene", "tiny", "--output-dir", str(run), "--max-steps", "-1",
                             *QUIET])
    assert line == "error: config.max_steps: expected >= 0, got -1"
    assert not run.exists()
