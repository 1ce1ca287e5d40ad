"""A structural walk of COLMAP's binary model files before pycolmap reads them.

pycolmap trusts the counts in the file: a flipped byte in a count (images, 2D points of an image,
track length of a point) makes it loop or allocate for minutes. This walk reads only the counts and
skips the records, checking that each declared array fits in what remains of the file -- linear in the
file size, no allocation per record.
"""

from __future__ import annotations

import struct
from pathlib import Path

from hico_plugin.errors import HicoError

# Parameters per COLMAP camera model id (colmap/src/colmap/sensor/models.h).
_NUM_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 0}


class _Reader:
    def __init__(self, path: Path):
        self.path, self.data, self.pos = path, path.read_bytes(), 0

    def fail(self, what: str) -> HicoError:
        return HicoError(f"{self.path}: {what} at byte {self.pos} (file truncated or corrupt; expected COLMAP's binary format)")

    def unpack(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise self.fail(f"{what} runs past the end")
        values = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return values

    def skip(self, count: int, item_size: int, what: str) -> None:
        if count < 0 or count * item_size > len(self.data) - self.pos:
            raise self.fail(f"{what}: {count} entries do not fit in the remaining {len(self.data) - self.pos} bytes")
        self.pos += count * item_size

    def skip_name(self, what: str) -> None:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise self.fail(f"{what} has no terminating NUL")
        self.pos = end + 1

    def done(self) -> None:
        if self.pos != len(self.data):
            raise self.fail(f"{len(self.data) - self.pos} trailing bytes after the last record")


def check_binary_model(model_dir: Path) -> None:
    """HicoError naming the file and byte when cameras.bin / images.bin / points3D.bin cannot hold
    what their counts declare. Files from COLMAP versions with rigs/frames are checked the same way."""
    cameras = _Reader(model_dir / "cameras.bin")
    (count,) = cameras.unpack("<Q", "camera count")
    cameras.skip(count, 24, "cameras")  # each camera is at least 24 bytes: checks the count first
    cameras.pos = 8
    for i in range(count):
        _, model_id, _, _ = cameras.unpack("<iiQQ", f"camera {i}")
        if model_id not in _NUM_PARAMS:
            raise cameras.fail(f"camera {i}: unknown camera model id {model_id}")
        cameras.skip(_NUM_PARAMS[model_id], 8, f"camera {i} parameters")
    cameras.done()

    images = _Reader(model_dir / "images.bin")
    (count,) = images.unpack("<Q", "image count")
    images.skip(count, 70, "images")  # 4 + 56 + 4 + 1 (name) + 8 bytes at least each
    images.pos = 8
    for i in range(count):
        images.unpack("<I7dI", f"image {i}")
        images.skip_name(f"image {i} name")
        (points,) = images.unpack("<Q", f"image {i} 2D point count")
        images.skip(points, 24, f"image {i} 2D points")
    images.done()

    points3d = _Reader(model_dir / "points3D.bin")
    (count,) = points3d.unpack("<Q", "point count")
    points3d.skip(count, 51, "points")  # 8 + 24 + 3 + 8 + 8 bytes at least each
    points3d.pos = 8
    for i in range(count):
        track = points3d.unpack("<Q3d3BdQ", f"point {i}")[-1]
        points3d.skip(track, 8, f"point {i} track")
    points3d.done()
