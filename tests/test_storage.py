"""The cache root and the atomic writes every layer uses."""

from __future__ import annotations

import pytest

from hico_plugin.storage import (CACHE_KINDS, atomic_path, cache_dir, cache_root, write_bytes_atomic,
                                 write_text_atomic)


def test_the_cache_root_is_hico_cache_dir_then_xdg_then_home(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.delenv("HICO_CACHE_DIR", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    assert cache_root() == tmp_path / "home" / ".cache" / "hico_plugin"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_root() == tmp_path / "xdg" / "hico_plugin"
    monkeypatch.setenv("HICO_CACHE_DIR", str(tmp_path / "hico"))
    assert cache_root() == tmp_path / "hico"
    assert [cache_dir(kind) for kind in CACHE_KINDS] == [tmp_path / "hico" / kind for kind in CACHE_KINDS]
    assert not (tmp_path / "hico").exists()  # named, not created
    with pytest.raises(ValueError, match="unknown cache kind 'scene'"):
        cache_dir("scene")


def test_text_and_bytes_round_trip_readable_by_all(tmp_path):
    text = tmp_path / "new" / "folder" / "notes.json"
    assert write_text_atomic(text, '{"name": "façade"}\n') == text
    assert text.read_text(encoding="utf-8") == '{"name": "façade"}\n'
    data = bytes(range(256)) * 3
    assert write_bytes_atomic(tmp_path / "blob.bin", data) == tmp_path / "blob.bin"
    assert (tmp_path / "blob.bin").read_bytes() == data
    write_bytes_atomic(tmp_path / "blob.bin", b"again")  # an existing file is replaced
    assert (tmp_path / "blob.bin").read_bytes() == b"again"
    assert {path.stat().st_mode & 0o777 for path in (text, tmp_path / "blob.bin")} == {0o644}
    assert sorted(path.name for path in tmp_path.rglob("*")) == ["blob.bin", "folder", "new", "notes.json"]


def test_a_writer_that_raises_leaves_the_old_file_and_no_temp(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text("old")
    with pytest.raises(OSError, match="No space left"):
        with atomic_path(path) as tmp:
            tmp.write_text("half")
            raise OSError(28, "No space left on device")
    assert path.read_text() == "old" and list(tmp_path.iterdir()) == [path]
    with pytest.raises(KeyboardInterrupt):  # an interrupted writer too
        with atomic_path(path):
            raise KeyboardInterrupt
    assert path.read_text() == "old" and list(tmp_path.iterdir()) == [path]


def test_the_temp_path_lies_beside_the_file_and_keeps_its_suffix(tmp_path):
    """Writers that pick the format by the name (np.savez adds .npz to any other name) write the file asked for."""
    import numpy as np

    target = tmp_path / "points.npz"
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".points.npz.") and tmp.suffix == ".npz"
        assert tmp.is_file() and not target.exists()  # nothing under the final name until the block ends
        np.savez(tmp, points=np.arange(3))
    with np.load(target) as loaded:
        assert loaded["points"].tolist() == [0, 1, 2]
    assert list(tmp_path.iterdir()) == [target]


def test_writes_to_a_missing_file_leave_nothing_when_they_fail(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "out" / "frame.png") as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("encoder died")
    assert list((tmp_path / "out").iterdir()) == []
