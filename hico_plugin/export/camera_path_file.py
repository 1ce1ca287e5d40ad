"""nerfstudio's ``camera_path.json`` (its render panel's file, ``ns-render camera-path``'s input), same keys.

Read: ``render_width`` / ``render_height`` (pixels), ``fps``, per frame ``camera_to_world`` (4x4, 16 numbers row
by row, OpenGL axes) and ``fov`` (vertical, degrees; focal ``render_height / 2 / tan(fov / 2)``, principal point
the centre); ``camera_type`` must be ``perspective``. Poses are in the dataset's source frame;
``nerfstudio_transform`` (``dataparser_transforms.json``: ``x_ns = scale * (transform @ [x; 1])``) maps a
nerfstudio-frame file there. Untrusted: JSON only; a missing or malformed key is a HicoError naming it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from hico_plugin.cameras import Cameras
from hico_plugin.data.transform import SceneTransform
from hico_plugin.errors import HicoError
from hico_plugin.storage import write_text_atomic

MAX_FILE_BYTES = 64 * 1024 * 1024
"""A camera path of 100,000 frames is about 40 MB; anything larger is not a camera path."""

_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))  # flips y and z (an involution)


def _number(value: Any, where: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise HicoError(f"{where}: expected a finite number, got {json.dumps(value)[:40]}")
    if positive and value <= 0:
        raise HicoError(f"{where}: expected a number > 0, got {value}")
    return float(value)


def _matrix(value: Any, where: str, rows: int, cols: int) -> Tensor:
    """A rows x cols matrix given flat (nerfstudio's camera_to_world) or as nested rows."""
    flat = [x for row in value for x in row] if isinstance(value, list) and value and isinstance(value[0], list) else value
    if not isinstance(flat, list) or len(flat) != rows * cols:
        size = len(flat) if isinstance(flat, list) else type(value).__name__
        raise HicoError(f"{where}: expected {rows * cols} numbers ({rows}x{cols}), got {size}")
    return torch.tensor([_number(x, f"{where}[{i}]") for i, x in enumerate(flat)], dtype=torch.float64).view(rows, cols)


def _load_json(path: Path, what: str) -> dict[str, Any]:
    try:
        size = path.stat().st_size
    except OSError as err:
        raise HicoError(f"{path}: cannot read the {what} ({err.strerror})") from None
    if size > MAX_FILE_BYTES:
        raise HicoError(f"{path}: {size} bytes is too large for a {what} (at most {MAX_FILE_BYTES})")
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise HicoError(f"{path}: not a {what} (invalid JSON: {err})") from None
    if not isinstance(document, dict):
        raise HicoError(f"{path}: expected a JSON object, got {type(document).__name__}")
    return document


def nerfstudio_transform(path: Path) -> tuple[Tensor, float]:
    """(transform [3, 4] float64, scale) of nerfstudio's ``dataparser_transforms.json``."""
    document = _load_json(path, "nerfstudio dataparser_transforms.json")
    name = path.name
    if "transform" not in document or "scale" not in document:
        raise HicoError(f"{name}: expected the keys 'transform' and 'scale'")
    return _matrix(document["transform"], f"{name}: transform", 3, 4), _number(document["scale"], f"{name}: scale", True)


def _source_c2w(entries: list[Any], key: str, where: str, nerfstudio: tuple[Tensor, float] | None) -> tuple[Tensor, Tensor]:
    """(camera->world [N, 4, 4] float64 in the source frame with OpenCV axes, vertical fov [N] in
    degrees) of the file entries' ``key`` matrices (OpenGL axes) and ``fov`` values."""
    c2ws, fovs = [], []
    for i, entry in enumerate(entries):
        here = f"{where}[{i}]"
        if not isinstance(entry, dict) or key not in entry or "fov" not in entry:
            raise HicoError(f"{here}: expected an object with '{key}' and 'fov'")
        c2w = _matrix(entry[key], f"{here}.{key}", 4, 4)
        rotation = c2w[:3, :3]
        if (rotation @ rotation.T - torch.eye(3, dtype=torch.float64)).abs().max() > 1e-3 or torch.det(rotation) < 0:
            raise HicoError(f"{here}.{key}: its 3x3 part is not a rotation")
        fov = _number(entry["fov"], f"{here}.fov")
        if not 0 < fov < 180:
            raise HicoError(f"{here}.fov: expected a vertical field of view in degrees in (0, 180), got {fov}")
        c2ws.append(c2w)
        fovs.append(fov)
    c2w = torch.stack(c2ws) @ _GL_TO_CV
    if nerfstudio is not None:  # nerfstudio's frame -> the source frame
        ns, scale = nerfstudio
        inverse = torch.linalg.inv(torch.cat([ns, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)]))
        c2w[:, :3, 3] = c2w[:, :3, 3] / scale
        c2w = inverse @ c2w
    return c2w, torch.tensor(fovs, dtype=torch.float64)


def _size_and_fps(document: dict[str, Any], name: str) -> tuple[int, int, float]:
    for key in ("render_width", "render_height", "fps"):
        if key not in document:
            raise HicoError(f"{name}: missing key '{key}' (expected nerfstudio's camera_path.json)")
    camera_type = document.get("camera_type", "perspective")
    if camera_type != "perspective":
        raise HicoError(f"{name}: camera_type: only 'perspective' is rendered, got {json.dumps(camera_type)[:40]}")
    width = _number(document["render_width"], f"{name}: render_width", True)
    height = _number(document["render_height"], f"{name}: render_height", True)
    if width != int(width) or height != int(height):
        raise HicoError(f"{name}: render_width / render_height: expected whole pixels, got {width} x {height}")
    return int(width), int(height), _number(document["fps"], f"{name}: fps", True)


def _normalised_cameras(c2w: Tensor, fovs: Tensor, width: int, height: int, transform: SceneTransform) -> Cameras:
    viewmats = transform.viewmats_from_colmap(torch.linalg.inv(c2w)).float()
    return _cameras(viewmats, height / 2 / torch.tan(torch.deg2rad(fovs) / 2), width, height)


def read_camera_path(path: str | Path, transform: SceneTransform,
                     nerfstudio: tuple[Tensor, float] | None = None) -> tuple[Cameras, float]:
    """(cameras [N] in the run's normalised frame, frames per second) of the camera_path.json ``path``.
    ``nerfstudio``: a ``nerfstudio_transform`` when the file was written by nerfstudio (its frame)."""
    path = Path(path)
    document = _load_json(path, "camera_path.json")
    name = path.name
    width, height, fps = _size_and_fps(document, name)
    if "camera_path" not in document:
        raise HicoError(f"{name}: missing key 'camera_path' (expected nerfstudio's camera_path.json)")
    frames = document["camera_path"]
    if not isinstance(frames, list) or not frames:
        raise HicoError(f"{name}: camera_path: expected a non-empty list of frames")
    c2w, fovs = _source_c2w(frames, "camera_to_world", f"{name}: camera_path", nerfstudio)
    return _normalised_cameras(c2w, fovs, width, height, transform), fps


def read_keyframes(path: str | Path, transform: SceneTransform,
                   nerfstudio: tuple[Tensor, float] | None = None) -> tuple[Cameras, Tensor, float, bool]:
    """The keyframes a render panel saved in ``path``: (cameras [K] in the normalised frame at the
    file's size, seconds [K] from each to the next, fps, loop). A keyframe without its own transition
    takes ``default_transition_sec`` (2 s when absent, nerfstudio's default)."""
    path = Path(path)
    document = _load_json(path, "camera_path.json")
    name = path.name
    width, height, fps = _size_and_fps(document, name)
    keyframes = document.get("keyframes")
    if not isinstance(keyframes, list) or not keyframes:
        raise HicoError(f"{name}: keyframes: expected a non-empty list (a path saved by a render panel)")
    default = _number(document.get("default_transition_sec", 2.0), f"{name}: default_transition_sec", True)
    seconds = []
    for i, entry in enumerate(keyframes):
        own = isinstance(entry, dict) and entry.get("override_transition_enabled") and "override_transition_sec" in entry
        seconds.append(_number(entry["override_transition_sec"], f"{name}: keyframes[{i}].override_transition_sec", True)
                       if own else default)
    c2w, fovs = _source_c2w(keyframes, "matrix", f"{name}: keyframes", nerfstudio)
    loop = document.get("is_cycle", False)
    if not isinstance(loop, bool):
        raise HicoError(f"{name}: is_cycle: expected true or false, got {json.dumps(loop)[:40]}")
    return _normalised_cameras(c2w, fovs, width, height, transform), torch.tensor(seconds), fps, loop


def _gl_entries(cameras: Cameras, transform: SceneTransform) -> list[tuple[list[float], float, float]]:
    """(camera->world flattened, OpenGL axes, source frame; vertical fov in degrees; aspect) of each camera."""
    c2w = torch.linalg.inv(transform.viewmats_to_colmap(cameras.viewmats.double())) @ _GL_TO_CV
    fovs = torch.rad2deg(2 * torch.atan(cameras.heights.double() / 2 / cameras.Ks[:, 1, 1].double()))
    aspects = cameras.widths.double() / cameras.heights.double()
    return [(m.flatten().tolist(), float(f), float(a)) for m, f, a in zip(c2w, fovs, aspects)]


def keyframe_entries(keyframes: Cameras, seconds: Tensor, transform: SceneTransform) -> list[dict[str, Any]]:
    """``keyframes`` [K] (normalised frame) with their transition ``seconds`` [K] as the render panel's
    ``keyframes`` entries (nerfstudio's keys)."""
    return [{"matrix": matrix, "fov": fov, "aspect": aspect, "override_transition_enabled": True,
             "override_transition_sec": float(sec)}
            for (matrix, fov, aspect), sec in zip(_gl_entries(keyframes, transform), seconds.tolist())]


def _cameras(viewmats: Tensor, focals: Tensor, width: int, height: int) -> Cameras:
    count = len(viewmats)
    Ks = torch.zeros(count, 3, 3)
    Ks[:, 0, 0] = Ks[:, 1, 1] = focals.float()
    Ks[:, 0, 2], Ks[:, 1, 2], Ks[:, 2, 2] = width / 2, height / 2, 1.0
    return Cameras(viewmats, Ks, torch.full((count,), width), torch.full((count,), height))


def camera_path_document(cameras: Cameras, transform: SceneTransform, fps: float,
                         keyframes: list[dict[str, Any]] | None = None, **settings: Any) -> dict[str, Any]:
    """The camera_path.json of ``cameras`` [N] (normalised frame, one size, square pixels assumed: the
    vertical field of view is written): poses in the source frame, OpenGL axes. ``keyframes`` (e.g.
    ``keyframe_entries``) and ``settings`` (e.g. ``is_cycle``) are stored as given for the viewer."""
    frames = [{"camera_to_world": matrix, "fov": fov, "aspect": aspect} for matrix, fov, aspect in _gl_entries(cameras, transform)]
    return {"camera_type": "perspective", "render_width": int(cameras.widths[0]), "render_height": int(cameras.heights[0]),
            "fps": float(fps), "seconds": len(frames) / float(fps), **settings, "keyframes": keyframes or [],
            "camera_path": frames}


def write_camera_path(path: str | Path, cameras: Cameras, transform: SceneTransform, fps: float,
                      keyframes: list[dict[str, Any]] | None = None, **settings: Any) -> Path:
    """Write ``camera_path_document`` to ``path`` atomically; returns the path."""
    path = Path(path)
    write_text_atomic(path, json.dumps(camera_path_document(cameras, transform, fps, keyframes, **settings), indent=1) + "\n")
    return path
