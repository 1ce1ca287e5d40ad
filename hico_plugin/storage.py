"""Where hico keeps its caches, and how it writes a file so that a crash never leaves a torn one.

Every cache lives under one root, ``$HICO_CACHE_DIR`` (default ``$XDG_CACHE_HOME/hico_plugin``, else
``~/.cache/hico_plugin``), a folder per kind; every file is written to a temp file beside it and renamed onto it.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

CACHE_ENV = "HICO_CACHE_DIR"
CACHE_KINDS = ("datasets", "kernels", "lpips", "scenes", "triangulation")
"""The folders under the cache root: undistorted images, compiled kernels, LPIPS weights, built-in scenes
and triangulated seed points."""
FILE_MODE = 0o644
"""Mode of every file written here: readable by all, as a plain write under the usual umask is (a temp
file is created 0600)."""


def cache_root() -> Path:
    """The root of all hico caches: ``$HICO_CACHE_DIR``, else ``$XDG_CACHE_HOME/hico_plugin``, else
    ``~/.cache/hico_plugin``."""
    root = os.environ.get(CACHE_ENV)
    if root:
        return Path(root).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "hico_plugin"


def cache_dir(kind: str) -> Path:
    """The cache folder of ``kind`` (one of ``CACHE_KINDS``), not created."""
    if kind not in CACHE_KINDS:
        raise ValueError(f"unknown cache kind {kind!r}; expected one of {', '.join(CACHE_KINDS)}")
    return cache_root() / kind


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temp path in ``path``'s folder (created if missing) for a writer that needs a file name; renamed
    onto ``path`` when the block ends, removed when it raises. The temp name keeps ``path``'s suffix, so
    writers that choose the format by it (OpenCV, ``np.savez``) write the same file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=f".tmp{path.suffix}")
    os.close(fd)
    tmp = Path(name)
    try:
        tmp.chmod(FILE_MODE)
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temp file and a rename; returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through a temp file and a rename; returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
