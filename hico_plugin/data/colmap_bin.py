"""COLMAP's binary model files (cameras.bin, images.bin, points3D.bin) read in one checked walk.

A flipped byte in a count (images, 2D points of an image, track length of a point) must not make the
reader loop or allocate for minutes: every declared array is checked to fit in what remains of the
file before it is read or skipped -- linear in the file size. The walk over points3D.bin only finds
where each record starts; the fields are then gathered with numpy, so a million points read in
about a second.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from hico_plugin.data.camera_model import MODEL_NAMES, NUM_PARAMS, Camera
from hico_plugin.data.colmap_files import ModelFiles
from hico_plugin.errors import HicoError

_POINT_HEADER = 51  # point3D_id u64, xyz 3 f64, rgb 3 u8, error f64, track length u64
_TRACK_ELEMENT = 8  # image_id u32, point2D_idx u32


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

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise self.fail(f"{what} has no terminating NUL")
        try:
            name = self.data[self.pos:end].decode()
        except UnicodeDecodeError:
            raise self.fail(f"{what} is not UTF-8 text") from None
        self.pos = end + 1
        return name

    def done(self) -> None:
        if self.pos != len(self.data):
            raise self.fail(f"{len(self.data) - self.pos} trailing bytes after the last record")


def read_binary_model(model_dir: Path) -> ModelFiles:
    """cameras.bin, images.bin and points3D.bin of ``model_dir``; a HicoError naming the file and byte
    when one cannot hold what its counts declare."""
    return ModelFiles(_read_cameras(model_dir / "cameras.bin"), *_read_images(model_dir / "images.bin"),
                      *_read_points(model_dir / "points3D.bin"))


def _read_cameras(path: Path) -> dict[int, Camera]:
    reader = _Reader(path)
    (count,) = reader.unpack("<Q", "camera count")
    reader.skip(count, 24, "cameras")  # each camera is at least 24 bytes: checks the count first
    reader.pos = 8
    cameras = {}
    for i in range(count):
        camera_id, model_id, width, height = reader.unpack("<IiQQ", f"camera {i}")
        if not 0 <= model_id < len(MODEL_NAMES):
            raise reader.fail(f"camera {i}: unknown camera model id {model_id}")
        model = MODEL_NAMES[model_id]
        params = reader.unpack(f"<{NUM_PARAMS[model]}d", f"camera {i} parameters")
        if camera_id in cameras:
            raise reader.fail(f"camera {i}: camera id {camera_id} listed twice")
        cameras[camera_id] = Camera(camera_id=camera_id, model=model, width=width, height=height, params=params)
    reader.done()
    return cameras


def _read_images(path: Path) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
    """(image ids [I], names [I], camera ids [I], cam_from_world [I, 7]); the 2D points are skipped."""
    reader = _Reader(path)
    (count,) = reader.unpack("<Q", "image count")
    reader.skip(count, 70, "images")  # 4 + 56 + 4 + 1 (name) + 8 bytes at least each
    reader.pos = 8
    ids, names, camera_ids, poses = [], [], [], []
    for i in range(count):
        image_id, *pose, camera_id = reader.unpack("<I7dI", f"image {i}")
        names.append(reader.name(f"image {i} name"))
        (points,) = reader.unpack("<Q", f"image {i} 2D point count")
        reader.skip(points, 24, f"image {i} 2D points")
        ids.append(image_id)
        camera_ids.append(camera_id)
        poses.append(pose)
    reader.done()
    return (np.array(ids, np.int64), names, np.array(camera_ids, np.int64),
            np.array(poses, np.float64).reshape(-1, 7))


def _read_points(path: Path) -> tuple[np.ndarray, ...]:
    """(point ids [P], xyz [P, 3], colours [P, 3], track lengths [P], track image ids [T])."""
    reader = _Reader(path)
    (count,) = reader.unpack("<Q", "point count")
    reader.skip(count, _POINT_HEADER, "points")  # checks the count before anything is allocated for it
    data, end, pos = reader.data, len(reader.data), 8
    track_length = struct.Struct("<Q").unpack_from
    starts, lengths = [], []
    for i in range(count):
        if pos + _POINT_HEADER > end:
            reader.pos = pos
            raise reader.fail(f"point {i} runs past the end")
        (length,) = track_length(data, pos + _POINT_HEADER - 8)
        starts.append(pos)
        lengths.append(length)
        pos += _POINT_HEADER
        if length * _TRACK_ELEMENT > end - pos:
            reader.pos = pos
            raise reader.fail(f"point {i} track: {length} entries do not fit in the remaining {end - pos} bytes")
        pos += length * _TRACK_ELEMENT
    reader.pos = pos
    reader.done()
    buffer = np.frombuffer(data, np.uint8)
    starts, lengths = np.array(starts, np.int64), np.array(lengths, np.int64)
    # byte offset of every track element: its point's track start, plus its rank in the track
    before = np.cumsum(lengths) - lengths  # elements of the points before
    elements = (np.repeat(starts + _POINT_HEADER - _TRACK_ELEMENT * before, lengths)
                + _TRACK_ELEMENT * np.arange(int(lengths.sum())))
    return (_gather(buffer, starts, np.dtype("<u8"))[:, 0], _gather(buffer, starts + 8, np.dtype("<f8"), 3),
            buffer[starts[:, None] + 32 + np.arange(3)], lengths,
            _gather(buffer, elements, np.dtype("<u4"))[:, 0].astype(np.int64))


def _gather(buffer: np.ndarray, offsets: np.ndarray, dtype: np.dtype, count: int = 1) -> np.ndarray:
    """[N, count] values of ``dtype`` stored one after another at the byte ``offsets`` [N] of
    ``buffer`` (any alignment): read through one view of the buffer per alignment."""
    out = np.empty((len(offsets), count), dtype.newbyteorder("="))
    size = dtype.itemsize
    for shift in range(size):
        rows = np.flatnonzero(offsets % size == shift)
        if len(rows):
            view = buffer[shift: shift + (len(buffer) - shift) // size * size].view(dtype)
            out[rows] = view[(offsets[rows] - shift)[:, None] // size + np.arange(count)]
    return out
