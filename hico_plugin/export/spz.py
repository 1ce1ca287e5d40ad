"""Niantic's SPZ, the compressed splat file web viewers open, from the Inria PLY's rows (SH degree 0).

Version 3 (nianticlabs/spz), gzipped: a 16-byte header (magic 0x5053474e), then each attribute in turn: positions
24-bit signed fixed point; alphas (sigmoid of the logit), colours (``dc * 0.15 * 255 + 127.5``), scales (``(log
scale + 10) * 16``) 8 bits; rotations the smallest three quaternion components (10 bits: sign, 9-bit magnitude
scaled by 1/sqrt(2)), the largest's index in the top 2 bits of 32. Axes: the PLY's, as PlayCanvas's
splat-transform reads SPZ (Niantic's spec says right-up-back, a half turn about x from the PLY's
right-down-forward).
"""

from __future__ import annotations

import gzip
import os
import struct
from pathlib import Path

import numpy as np

from hico_plugin.errors import HicoError
from hico_plugin.export.gaussians import INRIA_FIELDS
from hico_plugin.storage import write_bytes_atomic

SPZ_MAGIC = 0x5053474E
SPZ_VERSION = 3
COLOR_SCALE = 0.15


def _uint8(values: np.ndarray) -> np.ndarray:
    return np.clip(np.round(values), 0, 255).astype(np.uint8)


def fractional_bits(positions: np.ndarray) -> int:
    """The most fractional bits (at most 12, SPZ's default) with which every coordinate fits 24 bits."""
    largest = float(np.abs(positions).max()) if len(positions) else 0.0
    bits = 12
    while bits > 0 and largest * (1 << bits) >= (1 << 23) - 1:
        bits -= 1
    if largest * (1 << bits) >= (1 << 23) - 1:
        raise ValueError(f"SPZ: a coordinate of {largest:g} does not fit 24-bit fixed point")
    return bits


def _smallest_three(quats_xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternions [N, 4] (x, y, z, w) -> [N, 4] bytes of the 32-bit smallest-three words."""
    largest = np.abs(quats_xyzw).argmax(axis=1)
    negate = np.take_along_axis(quats_xyzw, largest[:, None], 1)[:, 0] < 0
    words = largest.astype(np.uint32)
    for i in range(4):
        component = quats_xyzw[:, i]
        sign = ((component < 0) ^ negate).astype(np.uint32)
        magnitude = (511.0 * np.abs(component) / np.sqrt(0.5) + 0.5).astype(np.uint32)
        packed = (words << 10) | (sign << 9) | np.minimum(magnitude, 511)
        words = np.where(largest == i, words, packed)
    return words.astype("<u4").view(np.uint8).reshape(-1, 4)


def spz_bytes(rows: np.ndarray, antialiased: bool = False) -> bytes:
    """The SPZ file of Inria-layout ``rows`` (``export.gaussians.inria_vertices``: x y z, f_dc_0..2,
    opacity logit, log scale_0..2, rot_0..3 as w x y z), SH degree 0."""
    count = len(rows)
    positions = np.stack([rows["x"], rows["y"], rows["z"]], 1).astype(np.float64)
    bits = fractional_bits(positions)
    fixed = np.round(positions * (1 << bits)).astype(np.int64).reshape(-1)
    position_bytes = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], 1).astype(np.uint8)
    alphas = _uint8(255.0 / (1.0 + np.exp(-rows["opacity"].astype(np.float64))))
    dc = np.stack([rows[f"f_dc_{c}"] for c in range(3)], 1).astype(np.float64)
    colors = _uint8(dc * (COLOR_SCALE * 255.0) + 0.5 * 255.0)
    log_scales = np.stack([rows[f"scale_{c}"] for c in range(3)], 1).astype(np.float64)
    scales = _uint8((log_scales + 10.0) * 16.0)
    wxyz = np.stack([rows[f"rot_{c}"] for c in range(4)], 1).astype(np.float64)
    xyzw = np.concatenate([wxyz[:, 1:], wxyz[:, :1]], 1)
    xyzw /= np.linalg.norm(xyzw, axis=1, keepdims=True)
    header = struct.pack("<IIIBBBB", SPZ_MAGIC, SPZ_VERSION, count, 0, bits, 1 if antialiased else 0, 0)
    payload = b"".join([header, position_bytes.tobytes(), alphas.tobytes(), colors.tobytes(), scales.tobytes(),
                        _smallest_three(xyzw).tobytes()])
    return gzip.compress(payload, compresslevel=9, mtime=0)


def write_spz(path: str | os.PathLike, rows: np.ndarray) -> Path:
    """Write ``spz_bytes(rows)`` to ``path`` atomically, readable by all as the PLY is
    (``storage.write_bytes_atomic``). Returns the path."""
    return write_bytes_atomic(path, spz_bytes(rows))


def read_spz(path: str | os.PathLike) -> np.ndarray:
    """The Gaussians of an SPZ file (version 2 or 3, SH degree 0 read; higher degrees' coefficients
    skipped) as Inria-layout rows (normals zero). Anything else is a HicoError naming the file."""
    path = Path(path)
    try:
        data = gzip.decompress(path.read_bytes())
    except (OSError, EOFError, gzip.BadGzipFile) as err:
        raise HicoError(f"{path}: not an SPZ file ({err})") from None
    if len(data) < 16:
        raise HicoError(f"{path}: not an SPZ file (no 16-byte header)")
    magic, version, count, degree, bits, _, _ = struct.unpack("<IIIBBBB", data[:16])
    if magic != SPZ_MAGIC or version not in (2, 3):
        raise HicoError(f"{path}: not an SPZ file of version 2 or 3 (magic {magic:#x}, version {version})")
    rotation_bytes = 4 if version == 3 else 3
    sizes = [9 * count, count, 3 * count, 3 * count, rotation_bytes * count]
    if len(data) < 16 + sum(sizes):
        raise HicoError(f"{path}: {len(data) - 16} bytes of data, expected at least {sum(sizes)} for {count} points")
    parts, offset = [], 16
    for size in sizes:
        parts.append(np.frombuffer(data, np.uint8, size, offset))
        offset += size
    position_bytes, alphas, colors, scales, rotations = parts
    raw = position_bytes.reshape(-1, 3).astype(np.int32)
    fixed = raw[:, 0] | (raw[:, 1] << 8) | (raw[:, 2] << 16)
    fixed = np.where(fixed >= 1 << 23, fixed - (1 << 24), fixed)
    rows = np.zeros(count, dtype=[(name, "<f4") for name in INRIA_FIELDS])
    positions = (fixed / float(1 << bits)).reshape(-1, 3)
    for i, name in enumerate("xyz"):
        rows[name] = positions[:, i]
    alpha = np.clip(alphas / 255.0, 1e-6, 1 - 1e-6)
    rows["opacity"] = np.log(alpha / (1 - alpha))
    dc = (colors.reshape(-1, 3) / 255.0 - 0.5) / COLOR_SCALE
    log_scales = scales.reshape(-1, 3) / 16.0 - 10.0
    for c in range(3):
        rows[f"f_dc_{c}"], rows[f"scale_{c}"] = dc[:, c], log_scales[:, c]
    if version == 3:
        words = rotations.reshape(-1, 4).copy().view("<u4")[:, 0]
        largest = words >> 30
        xyzw = np.zeros((count, 4))
        shift = np.zeros(count, np.uint32)  # per row: the bits of the components read so far
        for i in (3, 2, 1, 0):  # the last packed component sits in the lowest bits
            stored = largest != i
            magnitude = ((words >> shift) & 511) / 511.0 * np.sqrt(0.5)
            negative = (words >> (shift + 9)) & 1
            xyzw[:, i] = np.where(stored, np.where(negative == 1, -magnitude, magnitude), 0.0)
            shift = shift + 10 * stored.astype(np.uint32)
        rest = 1.0 - (xyzw**2).sum(1)
        xyzw[np.arange(count), largest] = np.sqrt(np.clip(rest, 0.0, None))
    else:
        xyz = rotations.reshape(-1, 3) / 127.5 - 1.0
        xyzw = np.concatenate([xyz, np.sqrt(np.clip(1.0 - (xyz**2).sum(1), 0.0, None))[:, None]], 1)
    for c, column in enumerate((3, 0, 1, 2)):  # rows hold w, x, y, z
        rows[f"rot_{c}"] = xyzw[:, column]
    return rows
