"""COLMAP's text model files (cameras.txt, images.txt, points3D.txt), read as COLMAP reads them:
lines split at newlines only, blank and ``#`` lines skipped, an image's header line followed by its
2D-point line whatever that holds (the 2D points themselves are not needed), a name being the
header's tenth field. Lines are streamed and their numbers kept in typed arrays, so a million
points take seconds and little more memory than their arrays."""

from __future__ import annotations

from array import array
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from hico_plugin.data.camera_model import NUM_PARAMS, Camera
from hico_plugin.data.colmap_files import ModelFiles
from hico_plugin.errors import HicoError


def read_text_model(model_dir: Path) -> ModelFiles:
    """cameras.txt, images.txt and points3D.txt of ``model_dir``; one HicoError naming the file and
    line of a malformed entry."""
    return ModelFiles(_read_cameras(model_dir / "cameras.txt"), *_read_images(model_dir / "images.txt"),
                      *_read_points(model_dir / "points3D.txt"))


def _lines(path: Path) -> Iterator[tuple[int, str]]:
    """(line number, line stripped of surrounding white space) of every line, as std::getline splits them."""
    try:
        with open(path, encoding="utf-8", newline="\n") as file:
            for number, line in enumerate(file, 1):
                yield number, line.strip()
    except (OSError, UnicodeDecodeError) as err:
        raise HicoError(f"{path}: cannot be read as COLMAP's text format ({err})") from None


def _data(path: Path) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields) of the lines that are neither blank nor comments."""
    for number, line in _lines(path):
        if line and line[0] != "#":
            yield number, line.split()


def _read_cameras(path: Path) -> dict[int, Camera]:
    cameras = {}
    for number, fields in _data(path):
        where = f"{path}: line {number}"
        try:
            camera_id, model, width, height = int(fields[0]), fields[1], int(fields[2]), int(fields[3])
            params = [float(value) for value in fields[4:]]
        except (IndexError, ValueError):
            raise HicoError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]") from None
        if model not in NUM_PARAMS:
            raise HicoError(f"{where}: unknown camera model {model[:40]!r}")
        if len(params) != NUM_PARAMS[model]:
            raise HicoError(f"{where}: {model} takes {NUM_PARAMS[model]} parameters, found {len(params)}")
        if camera_id in cameras:
            raise HicoError(f"{where}: camera id {camera_id} listed twice")
        cameras[camera_id] = Camera(camera_id=camera_id, model=model, width=width, height=height, params=params)
    return cameras


def _read_images(path: Path) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
    """(image ids [I], names [I], camera ids [I], cam_from_world [I, 7])."""
    ids, names, camera_ids, poses = array("q"), [], array("q"), array("d")
    lines = _lines(path)
    for number, line in lines:
        if not line or line[0] == "#":
            continue
        if next(lines, None) is None:  # no 2D-point line: COLMAP stops there, without this image
            break
        fields = line.split()
        try:
            ids.append(int(fields[0]))
            poses.extend(float(value) for value in fields[1:8])
            camera_ids.append(int(fields[8]))
            names.append(fields[9])
        except (IndexError, ValueError, OverflowError):
            raise HicoError(f"{path}: line {number}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME") from None
    return np.array(ids, np.int64), names, np.array(camera_ids, np.int64), np.array(poses).reshape(-1, 7)


def _read_points(path: Path) -> tuple[np.ndarray, ...]:
    """(point ids [P], xyz [P, 3], colours [P, 3], track lengths [P], track image ids [T])."""
    ids, xyz, rgb, lengths, track = array("Q"), array("d"), array("q"), array("q"), array("q")
    for number, fields in _data(path):
        pairs = (len(fields) - 8) // 2  # (IMAGE_ID, POINT2D_IDX) pairs; an odd last field is ignored
        try:
            if pairs < 0:
                raise ValueError
            ids.append(int(fields[0]))
            xyz.extend(map(float, fields[1:4]))
            rgb.extend(map(int, fields[4:7]))
            track.extend(map(int, fields[8:8 + 2 * pairs:2]))
        except (ValueError, OverflowError):
            raise HicoError(f"{path}: line {number}: expected POINT3D_ID X Y Z R G B ERROR TRACK[]") from None
        lengths.append(pairs)
    # COLMAP casts R, G, B to 8 bits without a check: so does numpy's int64 -> uint8
    return (np.array(ids, np.uint64), np.array(xyz).reshape(-1, 3), np.array(rgb).astype(np.uint8).reshape(-1, 3),
            np.array(lengths, np.int64), np.array(track, np.int64))
