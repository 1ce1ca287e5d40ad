"""Files a user hands us never run code: crafted checkpoints and config tags are refused in one line."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from hico_plugin.engine.checkpoints import load_checkpoint, newest_readable_checkpoint, save_checkpoint
from hico_plugin.engine.config_io import load_config
from hico_plugin.errors import HicoError


class _CreatesFile:
    """Unpickling this calls Path.touch(marker): what an attacker's payload would do."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_pickle_checkpoint_is_refused_without_running(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "checkpoints" / "step-000000001.ckpt"
    path.parent.mkdir()
    torch.save({"step": 1, "model": {"w": torch.zeros(2)}, "extra": _CreatesFile(marker)}, path)
    with pytest.raises(HicoError) as info:
        load_checkpoint(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)
    assert "refused without running" in str(info.value)
    assert not marker.exists()


def test_unreadable_newest_checkpoint_is_skipped_with_a_warning(tmp_path, capsys):
    folder = tmp_path / "checkpoints"
    good = save_checkpoint(folder, 5, {"step": 5, "model": {"w": torch.ones(2)}}, keep_last=0)
    truncated = save_checkpoint(folder, 6, {"step": 6, "model": {"w": torch.ones(2)}}, keep_last=0)
    truncated.write_bytes(truncated.read_bytes()[:50])
    (folder / "step-000000007.ckpt").write_bytes(bytes(range(256)) * 4)  # random bytes
    path, payload = newest_readable_checkpoint(folder)
    assert path == good and payload["step"] == 5
    err = capsys.readouterr().err
    assert "step-000000007.ckpt" in err and "step-000000006.ckpt" in err and err.count("\n") == 2
    good.write_bytes(b"junk")
    with pytest.raises(HicoError, match="none of the 3 checkpoints is readable"):
        newest_readable_checkpoint(folder)


def test_checkpoint_write_error_is_one_line_and_keeps_earlier(tmp_path, monkeypatch):
    folder = tmp_path / "checkpoints"
    first = save_checkpoint(folder, 1, {"step": 1, "model": {}}, keep_last=3)

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(HicoError, match=r"step-000000002\.ckpt: cannot write the checkpoint \(No space left"):
        save_checkpoint(folder, 2, {"step": 2, "model": {}}, keep_last=1)
    assert [p.name for p in folder.iterdir()] == [first.name]  # no temp file left, the earlier one intact


def test_disk_filling_up_inside_torch_save_is_one_line(tmp_path, monkeypatch):
    """The real torch.save on a file that runs out of space mid-write: torch reports "unexpected pos"
    (a RuntimeError) and the disk's ENOSPC is only its context; the line names the latter."""
    import errno
    import io

    from hico_plugin.engine import checkpoints

    folder = tmp_path / "checkpoints"
    first = save_checkpoint(folder, 1, {"step": 1, "model": {}}, keep_last=3)

    class FillsUp(io.FileIO):
        def write(self, data):
            if self.tell() + len(data) > 2000:
                raise OSError(errno.ENOSPC, "No space left on device")
            return super().write(data)

    monkeypatch.setattr(checkpoints, "open", lambda path, mode: FillsUp(path, "wb"), raising=False)
    with pytest.raises(HicoError, match=r"step-000000002\.ckpt: cannot write the checkpoint \(No space left"):
        save_checkpoint(folder, 2, {"step": 2, "model": {"w": torch.zeros(10_000)}}, keep_last=1)
    assert [p.name for p in folder.iterdir()] == [first.name]


@pytest.mark.parametrize("module", ["this", "hico_evil_module"])
def test_config_tag_naming_a_module_is_refused_without_importing(tmp_path, monkeypatch, module):
    marker = tmp_path / "imported"
    (tmp_path / "hico_evil_module.py").write_text(f"open({str(marker)!r}, 'w').close()\nclass Something: pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, module, raising=False)
    path = tmp_path / "config.yml"
    path.write_text(f"!dataclass:{module}.Something\nmax_steps: 1\n")
    with pytest.raises(HicoError, match=rf"'{module}.Something' is not a registered config class; refused"):
        load_config(path)
    assert module not in sys.modules and not marker.exists()


def test_python_object_yaml_tags_are_refused(tmp_path):
    path = tmp_path / "config.yml"
    path.write_text("!!python/object/apply:os.system ['touch pwned']\n")
    with pytest.raises(HicoError, match="not valid YAML"):
        load_config(path)
