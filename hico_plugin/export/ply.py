"""Binary little-endian PLY of one ``vertex`` element, as numpy structured arrays, written atomically.

The layout Inria's 3DGS, SuperSplat and most splat viewers read: ``ply``, ``format binary_little_endian 1.0``,
``element vertex N``, a ``property float x`` line per field, ``end_header``, then N packed little-endian records.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from hico_plugin.errors import HicoError
from hico_plugin.storage import atomic_path

# PLY property type <-> numpy little-endian dtype (both PLY spellings read, the short one written).
_PLY_TO_NUMPY = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}
_NUMPY_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
                 "f4": "float", "f8": "double"}


def ply_header(vertices: np.ndarray) -> bytes:
    """The header of a binary little-endian PLY holding ``vertices`` (a structured array)."""
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}"]
    for name in vertices.dtype.names:
        code = vertices.dtype[name].str.lstrip("<>|=")
        if code not in _NUMPY_TO_PLY or vertices.dtype[name].shape:
            raise ValueError(f"PLY: field '{name}' of dtype {vertices.dtype[name]} has no scalar PLY type")
        lines.append(f"property {_NUMPY_TO_PLY[code]} {name}")
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def write_ply(path: str | os.PathLike, vertices: np.ndarray) -> Path:
    """Write the structured array ``vertices`` [N] as a binary little-endian PLY, atomically and readable
    by all (``storage.atomic_path``). Returns the path."""
    little = vertices.astype(vertices.dtype.newbyteorder("<"), copy=False)
    with atomic_path(path) as tmp, tmp.open("wb") as stream:
        stream.write(ply_header(little))
        stream.write(np.ascontiguousarray(little).tobytes())
    return Path(path)


def read_ply(path: str | os.PathLike) -> np.ndarray:
    """The ``vertex`` element of a binary little-endian PLY as a structured array [N].

    Only single-element files with scalar properties (what ``write_ply`` and 3DGS write) are read;
    anything else is a HicoError naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise HicoError(f"{path}: PLY file not found")
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise HicoError(f"{path}: not a PLY file (expected 'ply' ... 'end_header')")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    count, fields, element = None, [], None
    for line in header[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and words[1:2] != ["binary_little_endian"]:
            raise HicoError(f"{path}: format '{' '.join(words[1:])}' (expected binary_little_endian 1.0)")
        if words[0] == "element":
            if element is not None:
                raise HicoError(f"{path}: more than one element (expected only 'vertex')")
            element, count = words[1], int(words[2])
        if words[0] == "property":
            if words[1] == "list" or words[1] not in _PLY_TO_NUMPY:
                raise HicoError(f"{path}: property '{' '.join(words[1:])}' is not a scalar PLY type")
            fields.append((words[2], _PLY_TO_NUMPY[words[1]]))
    if element != "vertex" or count is None:
        raise HicoError(f"{path}: expected one 'element vertex N'")
    dtype = np.dtype(fields)
    body = data[end + len(b"end_header\n"):]
    if len(body) != count * dtype.itemsize:
        raise HicoError(f"{path}: {len(body)} bytes of vertex data, expected {count} x {dtype.itemsize}")
    return np.frombuffer(body, dtype=dtype, count=count).copy()
