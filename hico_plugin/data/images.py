"""Reading, checking and resizing image files (OpenCV; RGB uint8 in, RGB uint8 out)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from hico_plugin.errors import HicoError
from hico_plugin.storage import write_bytes_atomic

# The bytes a complete file of each format ends with (trailing padding aside): OpenCV decodes a
# truncated JPEG into a partly grey image with only a warning, so completeness is checked here.
_JPEG_END = b"\xff\xd9"
_PNG_END = b"IEND\xaeB`\x82"

MAX_LONG_SIDE = 1600
"""Longest image side, in pixels, training loads a photo at by default (nerfstudio's): a larger photo
is loaded at the smallest power-of-two downscale that fits (``downscale_factor``). SIFT reads photos at
that size too, in hico-process and in seed triangulation: finer features than a training pixel do not
help that training, and SIFT's time grows with the pixels."""


def downscale_factor(long_side: int, max_long_side: int = MAX_LONG_SIDE) -> int:
    """The smallest power of two that brings ``long_side`` to ``max_long_side`` or below."""
    factor = 1
    while long_side / factor > max_long_side:
        factor *= 2
    return factor


def read_file_bytes(path: Path, what: str) -> np.ndarray:
    try:
        return np.fromfile(path, dtype=np.uint8)
    except OSError as err:
        raise HicoError(f"{what} {path}: cannot be read ({err.strerror or err})") from None


def _is_truncated(data: np.ndarray) -> bool:
    raw = data.tobytes()
    if raw[:2] == b"\xff\xd8":
        return _JPEG_END not in raw[-64:]
    if raw[:8] == b"\x89PNG\r\n\x1a\n":
        return _PNG_END not in raw[-64:]
    return False


def decode(path: Path, flags: int, what: str) -> np.ndarray:
    """The decoded file (``cv2.imdecode`` with ``flags``), or a HicoError for an unreadable,
    truncated or non-image file."""
    data = read_file_bytes(path, what)
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None or _is_truncated(data):
        raise HicoError(f"{what} {path}: unreadable or truncated image file (expected a complete PNG/JPEG)")
    return image


# Pixels as stored, the EXIF orientation tag ignored: COLMAP's poses and intrinsics and nerfstudio's
# loader (PIL without exif_transpose) refer to the stored pixel grid, and so do the header sizes the
# loaders check. OpenCV would otherwise turn a tagged photo and break its camera (hico-process writes
# upright copies, so its datasets carry no turning tags).
_STORED = cv2.IMREAD_IGNORE_ORIENTATION


def read_rgb(path: Path, what: str = "image") -> np.ndarray:
    """uint8 [H, W, 3] RGB of the stored pixels (grey and 16-bit files are converted; alpha is dropped)."""
    return cv2.cvtColor(decode(path, cv2.IMREAD_COLOR | _STORED, what), cv2.COLOR_BGR2RGB)


def read_mask(path: Path) -> np.ndarray:
    """bool [H, W]: True where the (8-bit grey) mask is above half intensity."""
    return decode(path, cv2.IMREAD_GRAYSCALE | _STORED, "mask") > 127


def resize(image: np.ndarray, width: int, height: int, nearest: bool = False) -> np.ndarray:
    """``image`` [H, W, ...] resized to [height, width, ...]; area averaging for colours, nearest for
    masks and geometry (averaging would invent depths and normals across silhouettes)."""
    if image.shape[1] == width and image.shape[0] == height:
        return image
    interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
    out = cv2.resize(image, (width, height), interpolation=interpolation)
    return out.reshape(height, width, *image.shape[2:])


def is_downscale_of(size: tuple[int, int], full: tuple[int, int]) -> bool:
    """Whether ``size`` (w, h) is ``full`` (w, h) divided by a whole factor (floor or ceil)."""
    width, height = size
    full_width, full_height = full
    if width <= 0 or height <= 0 or width > full_width:
        return False
    factor = round(full_width / width)
    return factor >= 1 and all(
        s in (n // factor, -(-n // factor)) for s, n in ((width, full_width), (height, full_height))
    )


def write_png_atomic(path: Path, rgb: np.ndarray) -> None:
    """Write uint8 [H, W, 3] RGB as PNG through a temporary file and a rename."""
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise HicoError(f"cache file {path}: PNG encoding failed")
    write_bytes_atomic(path, encoded.tobytes())
