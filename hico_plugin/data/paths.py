"""Confining names read from dataset files to the dataset's own folders.

A dataset file (COLMAP ``images.bin``, ``transforms.json``, Mega-NeRF metadata...) names its images,
masks and depth maps. Those names are untrusted: an absolute path, a ``..`` component or a symlink
that leaves the folder would make the loader read (and the undistortion cache write beside) files
the user never handed over. Every reader resolves such names through ``resolve_inside``.
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath, PureWindowsPath

from hico_plugin.errors import HicoError


def resolve_inside(folder: Path, name: str, what: str) -> Path:
    """``folder / name``, refused unless it stays inside ``folder`` once symlinks are resolved.

    ``what`` names the entry for the error line, e.g. ``"sparse/0/images.bin: image 12"``. The path
    need not exist yet (a missing file is the caller's error to report)."""
    text = str(name)
    if not text or "\x00" in text:
        raise HicoError(f"{what}: empty or invalid file name {text!r}")
    # Both separators count: a dataset written on Windows may use backslashes, and a drive letter or
    # a leading separator makes the name absolute on one system or the other.
    posix, windows = PurePosixPath(text.replace("\\", "/")), PureWindowsPath(text)
    if posix.is_absolute() or windows.is_absolute() or windows.drive:
        raise HicoError(f"{what}: file name {text!r} is absolute; expected a name relative to {folder}")
    if ".." in posix.parts:
        raise HicoError(f"{what}: file name {text!r} climbs out of {folder} ('..'); expected a name inside it")
    root = folder.resolve()
    path = (root / posix).resolve()
    if not path.is_relative_to(root):
        raise HicoError(f"{what}: {text!r} resolves to {path}, outside {folder} (a symlink leaves the folder)")
    return folder / posix
