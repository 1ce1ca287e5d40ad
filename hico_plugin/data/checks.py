"""Checks every dataset format runs at load time, so bad input fails before training, not after.

Each check raises one HicoError naming the file or entry and what was expected.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from hico_plugin.data.images import is_downscale_of
from hico_plugin.errors import HicoError

MIN_IMAGE_SIZE = 16
"""Smallest width / height (pixels) of a camera as the dataset states it."""
MIN_LOADED_SIZE = 11
"""Smallest width / height of a view after --downscale: SSIM's 11-px Gaussian window needs it."""

# How far outside the image a principal point may sit, in image sizes: a crop can move it off-centre,
# but a point many widths away is a mis-scaled or corrupt camera.
_PRINCIPAL_POINT_SLACK = 1.0


def check_intrinsics(what: str, width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> None:
    """A pinhole camera of ``width`` x ``height`` px: positive size of at least ``MIN_IMAGE_SIZE``,
    positive finite focal lengths and a principal point near the image."""
    values = (fx, fy, cx, cy)
    if not all(v == v and abs(v) != float("inf") for v in values):
        raise HicoError(f"{what}: non-finite intrinsics fx={fx} fy={fy} cx={cx} cy={cy}")
    if fx <= 0 or fy <= 0:
        raise HicoError(f"{what}: focal length fx={fx:g}, fy={fy:g}; expected positive focal lengths (pixels)")
    if width < MIN_IMAGE_SIZE or height < MIN_IMAGE_SIZE:
        raise HicoError(f"{what}: image size {width}x{height}; expected at least {MIN_IMAGE_SIZE}x{MIN_IMAGE_SIZE} px")
    slack_x, slack_y = _PRINCIPAL_POINT_SLACK * width, _PRINCIPAL_POINT_SLACK * height
    if not (-slack_x <= cx <= width + slack_x and -slack_y <= cy <= height + slack_y):
        raise HicoError(f"{what}: principal point ({cx:g}, {cy:g}) lies far outside the {width}x{height} image "
                        "(expected it within one image size of the image)")


def image_header_size(path: Path, what: str) -> tuple[int, int]:
    """(width, height) from the file's header only (Pillow reads no pixels); HicoError naming the
    file when it is not a readable image."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, UnidentifiedImageError, ValueError):
        raise HicoError(f"{what} {path}: unreadable or truncated image file (no readable PNG/JPEG header)") from None


def check_image_sizes(paths: Sequence[Path], full_sizes: Sequence[tuple[int, int]], what: str = "image") -> None:
    """Every image (train and test) has its camera's size or an exact downscale of it, read from the
    header; one HicoError naming the first bad file and how many are bad."""
    bad = []
    for path, full in zip(paths, full_sizes):
        size = image_header_size(path, what)
        if not is_downscale_of(size, full):
            bad.append(f"{what} {path}: size {size[0]}x{size[1]} disagrees with its camera ({full[0]}x{full[1]}; "
                       "expected that size or an exact downscale)")
    if bad:
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        raise HicoError(bad[0] + more)
