"""Generate a built-in scene as a COLMAP dataset with exact ground truth, cached on disk.

Layout (read by hico_plugin.data): ``DIR/images/<name>.png``, ``DIR/sparse/0/{cameras,images,points3D}.bin``,
``DIR/ground_truth/depth/<stem>.npy`` (float32 [H, W] camera z, 0 = no surface),
``ground_truth/normal/<stem>.npy`` (float32 [H, W, 3] unit camera-frame normals facing the camera),
``ground_truth/surface_points.npy`` (float32 [M, 3] dense visible-surface samples, world frame),
``DIR/scene.json`` (name, parameters, declared + enabled effects, timings).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from hico_plugin.errors import HicoError
from hico_plugin.scenes import capture_effects as fx
from hico_plugin.scenes.base import SCENES, Scene, SceneConfig
from hico_plugin.scenes.render import View, render_view
from hico_plugin.scenes.sparse import FeatureSampler, SparsePoints
from hico_plugin.storage import cache_dir, write_text_atomic

if TYPE_CHECKING:
    import pycolmap

GENERATOR_VERSION = 1  # bump when output for the same parameters changes, to invalidate caches
# The generator's working buffers, in array elements: its memory is bounded by them and by one view,
# not by the number of views.
SURFACE_BUFFER = 1 << 18  # surface samples gathered before they are merged into the thinned set
VISIBILITY_CHUNK = 1 << 18  # (view, point) pairs and depth pixels per chunk of the sparse points' visibility


def scene_config(name: str, **overrides: Any) -> SceneConfig:
    """The config of scene ``name`` with field overrides; ``effects`` may be a dict of switches."""
    config = SCENES.get(name)()
    valid = {f.name for f in dataclasses.fields(config)}
    unknown = sorted(set(overrides) - valid)
    if unknown:
        raise HicoError(f"scene '{name}' has no parameter {unknown[0]!r}; expected one of {', '.join(sorted(valid))}")
    effects = overrides.pop("effects", None)
    if isinstance(effects, dict):
        declared = config.effects.declared()
        bad = sorted(set(effects) - set(declared))
        if bad:
            raise HicoError(
                f"scene '{name}' does not declare effect {bad[0]!r}; declared: {', '.join(declared) or '(none)'}"
            )
        effects = dataclasses.replace(config.effects, **effects)
    if effects is not None:
        overrides["effects"] = effects
    config = dataclasses.replace(config, **overrides)
    validate_config(name, config)
    return config


def validate_config(name: str, config: SceneConfig) -> None:
    for field, minimum in (("num_views", 2), ("width", 8), ("height", 8), ("sparse_points", 1),
                           ("pixel_samples", 1)):
        if getattr(config, field) < minimum:
            raise HicoError(f"scene '{name}': {field} must be >= {minimum}, got {getattr(config, field)}")
    if not 1.0 <= config.fov_x_deg <= 170.0:
        raise HicoError(f"scene '{name}': fov_x_deg must be in [1, 170], got {config.fov_x_deg}")
    if config.surface_spacing <= 0:
        raise HicoError(f"scene '{name}': surface_spacing must be > 0, got {config.surface_spacing}")


def scene_key(name: str, config: SceneConfig) -> str:
    """Cache key: hash of the scene name, every parameter and the generator version."""
    blob = json.dumps(
        {"scene": name, "parameters": dataclasses.asdict(config), "version": GENERATOR_VERSION}, sort_keys=True
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def generate_scene(name: str, out_dir: str | Path | None = None, **overrides: Any) -> Path:
    """Generate scene ``name`` (with parameter ``overrides``) and return its dataset directory.

    With ``out_dir`` None the dataset lives in the cache (``storage.cache_dir("scenes")/<name>-<key>``) and is reused
    when already there. Output is written to a temporary directory and renamed into place, so an
    interrupted run never leaves a partial dataset.
    """
    config = scene_config(name, **overrides)
    views = f"{config.num_views} views at {config.width}x{config.height}"
    if out_dir is None:
        final = cache_dir("scenes") / f"{name}-{scene_key(name, config)}"
        if (final / "scene.json").is_file():
            return final
        _say(f"hico: rendering the built-in scene {name} ({views}), first run only; cached in {final.parent}")
    else:
        final = Path(out_dir).expanduser().resolve()
        if final.exists() and (not final.is_dir() or (any(final.iterdir()) and not (final / "scene.json").is_file())):
            raise HicoError(f"--out {final}: exists and is not a generated scene; expected an empty or new directory")
        _say(f"hico: rendering the built-in scene {name} ({views}) into {final}")
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.partial-", dir=final.parent))
    try:
        write_scene(config.setup(name), tmp, key=scene_key(name, config), progress=view_progress(config.num_views))
        _move_into_place(tmp, final, replace=out_dir is not None)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final


def _move_into_place(tmp: Path, final: Path, replace: bool) -> None:
    if not final.exists():
        try:
            os.rename(tmp, final)
            return
        except OSError:
            if not (final / "scene.json").is_file():  # lost a race to a half-made dir? not possible
                raise
    if not replace:  # another process cached the same scene first: keep theirs
        return
    if not any(final.iterdir()):
        final.rmdir()
        os.rename(tmp, final)
        return
    old = final.with_name(f".{final.name}.old-{os.getpid()}")
    os.rename(final, old)
    os.rename(tmp, final)
    shutil.rmtree(old, ignore_errors=True)


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def view_progress(total: int, stream=None) -> Callable[[int], None]:
    """A reporter of views rendered: one line rewritten in place on a terminal, else a line at every
    tenth of the views (and the last), so a log shows the generation moving without a line per view."""
    stream = stream or sys.stderr
    every = max(1, total // 10)

    def report(done: int) -> None:
        text = f"  rendered {done}/{total} views"
        if stream.isatty():
            print(f"\r{text}", end="\n" if done == total else "", file=stream, flush=True)
        elif done % every == 0 or done == total:
            print(text, file=stream, flush=True)
    return report


def image_name(index: int) -> str:
    return f"view_{index:04d}.png"


def write_scene(scene: Scene, out: Path, key: str = "", progress: Callable[[int], None] | None = None) -> dict:
    """Render every view of ``scene`` and write the dataset into ``out``; returns the scene.json dict.
    ``progress(done)`` is called after each view."""
    # The caster's matrix products are tall and skinny ([rays, 3] x [3, k]); multithreaded BLAS
    # makes them 10x slower in CPU time (and worse on a busy machine), so run single-threaded.
    with threadpool_limits(limits=1, user_api="blas"):
        return _write_scene(scene, out, key, progress)


def _write_scene(scene: Scene, out: Path, key: str, progress: Callable[[int], None] | None) -> dict:
    config = scene.config
    enabled = set(scene.enabled_effects)
    t_start = time.perf_counter()
    for sub in ("images", "sparse/0", "ground_truth/depth", "ground_truth/normal"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    num_views, H, W = len(scene.viewmats), scene.height, scene.width
    gains = fx.exposure_gains(num_views, config.seed) if "exposure" in enabled else None
    noise_rng = np.random.default_rng([config.seed, 6]) if "sensor_noise" in enabled else None
    # each view goes to disk as it is rendered: memory holds one view, the sparse points' proposals and
    # the surface samples merged so far, whatever the number of views
    sampler = FeatureSampler(scene.viewmats, scene.K, config.sparse_points, config.sparse_noise, config.seed,
                             min_gradient=config.min_feature_gradient, chunk_elements=VISIBILITY_CHUNK)
    surface = _SurfaceSamples(config.surface_spacing, merge_at=SURFACE_BUFFER)
    depth_range = [np.inf, -np.inf]
    for i, viewmat in enumerate(scene.viewmats):
        view = render_view(scene.caster, viewmat, scene.K, W, H, scene.sun, config.ambient, config.shadows)
        rgb = _pixel_colour(scene, viewmat, view, "sky" in enabled)
        if gains is not None:
            rgb = fx.apply_exposure(rgb, gains[i])
        if noise_rng is not None:
            rgb = fx.apply_sensor_noise(rgb, noise_rng)
        image = np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)
        depth = view.depth.astype(np.float32)
        stem = Path(image_name(i)).stem
        if not cv2.imwrite(str(out / "images" / image_name(i)), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
            raise HicoError(f"{out / 'images' / image_name(i)}: could not write image")
        np.save(out / "ground_truth" / "depth" / f"{stem}.npy", depth)
        np.save(out / "ground_truth" / "normal" / f"{stem}.npy", view.normal.astype(np.float32))
        sampler.propose(i, image, depth)
        # dense surface samples: every other pixel, thinned to one point per surface_spacing voxel
        surface.add(view.points[::2, ::2][view.hit[::2, ::2]])
        hit_depths = depth[depth > 0]
        if hit_depths.size:
            depth_range = [min(depth_range[0], float(hit_depths.min())), max(depth_range[1], float(hit_depths.max()))]
        if progress is not None:
            progress(i + 1)
    t_render = time.perf_counter() - t_start

    surface_points = surface.points()
    np.save(out / "ground_truth" / "surface_points.npy", surface_points)

    t_sparse = time.perf_counter()

    def depths_of(views: np.ndarray) -> np.ndarray:
        return np.stack([np.load(out / "ground_truth" / "depth" / f"{Path(image_name(v)).stem}.npy") for v in views])

    def image_of(view: int) -> np.ndarray:
        return cv2.cvtColor(cv2.imread(str(out / "images" / image_name(view))), cv2.COLOR_BGR2RGB)

    sparse = sampler.finish(depths_of, image_of)
    reconstruction = build_reconstruction(scene, sparse)
    reconstruction.write_binary(str(out / "sparse" / "0"))
    t_sparse = time.perf_counter() - t_sparse
    sfm_stats, t_sfm = None, time.perf_counter()
    if config.sfm:
        from hico_plugin.scenes.sfm import run_sfm

        sfm_stats = run_sfm(out, reconstruction, scene.K, config.seed)
    t_sfm = time.perf_counter() - t_sfm

    meta = {
        "scene": scene.name,
        "key": key,
        "generator_version": GENERATOR_VERSION,
        "parameters": dataclasses.asdict(config),
        "declared_effects": config.effects.declared(),
        "enabled_effects": sorted(enabled),
        "num_views": num_views,
        "width": W,
        "height": H,
        "camera": {"model": "PINHOLE", "params": [scene.K[0, 0], scene.K[1, 1], scene.K[0, 2], scene.K[1, 2]]},
        "sun_direction": scene.sun.tolist(),
        "num_primitives": len(scene.primitives),
        "poses": "sfm" if config.sfm else "known",
        "sfm": sfm_stats,
        "num_points3D": sfm_stats["num_points3D"] if sfm_stats else reconstruction.num_points3D(),
        "mean_track_length": (
            sfm_stats["mean_track_length"] if sfm_stats else reconstruction.compute_mean_track_length()
        ),
        "mean_reprojection_error_px": (
            sfm_stats["mean_reprojection_error_px"] if sfm_stats else reconstruction.compute_mean_reprojection_error()
        ),
        "num_surface_points": len(surface_points),
        "depth_range": depth_range if np.isfinite(depth_range[0]) else [0.0, 0.0],
        "camera_distance_range": _camera_distance_range(scene),
        "exposure_gains": gains.tolist() if gains is not None else None,
        "timings_s": {
            "render": round(t_render, 3),
            "sparse": round(t_sparse, 3),
            "sfm": round(t_sfm, 3),
            "total": round(time.perf_counter() - t_start, 3),
        },
    }
    write_text_atomic(out / "scene.json", json.dumps(meta, indent=2))
    return meta


def _pixel_colour(scene: Scene, viewmat: np.ndarray, centre: View, sky: bool) -> np.ndarray:
    """Colour [H, W, 3] of each pixel: the mean over config.pixel_samples^2 rays spread evenly over
    the pixel (``centre`` is the view of the pixel-centre rays, the only one when pixel_samples is 1),
    sky included; sensor effects (exposure, noise) act on the integrated value and come after."""
    def colour(view: View) -> np.ndarray:
        return fx.apply_sky(view.rgb, view.hit, view.dirs_world) if sky else view.rgb

    n = scene.config.pixel_samples
    if n == 1:
        return colour(centre)
    offsets = (np.arange(n) + 0.5) / n - 0.5
    total = np.zeros((scene.height, scene.width, 3))
    for dy in offsets:
        for dx in offsets:
            # the ray through (u + 0.5 + dx, v + 0.5 + dy) is the centre ray of a shifted principal point
            K = scene.K.copy()
            K[0, 2] -= dx
            K[1, 2] -= dy
            total += colour(render_view(scene.caster, viewmat, K, scene.width, scene.height, scene.sun,
                                        scene.config.ambient, scene.config.shadows))
    return total / (n * n)


class _SurfaceSamples:
    """Surface samples thinned to one point per voxel of side ``spacing``, the first one added. The
    views' samples are merged into the thinned set once they outnumber it (and ``merge_at``), so
    memory holds about twice the thinned set, not every view's samples."""

    def __init__(self, spacing: float, merge_at: int):
        self.spacing, self.merge_at = spacing, merge_at
        self.keys: list[np.ndarray] = []
        self.samples: list[np.ndarray] = []
        self.merged = self.pending = 0

    def add(self, points: np.ndarray) -> None:
        keys, first = np.unique(_voxel_keys(points, self.spacing), return_index=True)
        self.keys.append(keys)
        self.samples.append(points[first].astype(np.float32))
        self.pending += len(keys)
        if self.pending >= max(self.merge_at, self.merged):
            self._merge()

    def _merge(self) -> None:
        keys, first = np.unique(np.concatenate(self.keys), return_index=True)  # first: earlier views win
        self.keys, self.samples = [keys], [np.concatenate(self.samples)[first]]
        self.merged, self.pending = len(keys), 0

    def points(self) -> np.ndarray:
        """float32 [M, 3], sorted by voxel."""
        self._merge()
        return self.samples[0]


def _voxel_keys(points: np.ndarray, spacing: float) -> np.ndarray:
    """One int64 per voxel of side ``spacing`` (21 bits per axis, wraps only beyond ~1e6 voxels)."""
    cells = np.floor(points / spacing).astype(np.int64) & ((1 << 21) - 1)
    return (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]


def _camera_distance_range(scene: Scene) -> list[float]:
    centers = -np.einsum("cji,cj->ci", scene.viewmats[:, :3, :3], scene.viewmats[:, :3, 3])
    distance = np.linalg.norm(centers, axis=1)
    return [float(distance.min()), float(distance.max())]


def build_reconstruction(scene: Scene, sparse: SparsePoints) -> pycolmap.Reconstruction:
    """A pycolmap model: one PINHOLE camera, one posed image per view, points with tracks. pycolmap is
    imported here, not with the module: training on a scene already generated never loads it."""
    import pycolmap

    K = scene.K
    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera(
        model="PINHOLE", width=scene.width, height=scene.height,
        params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=1,
    )
    reconstruction.add_camera_with_trivial_rig(camera)
    # observations sorted by image: their rank within an image is their point2D index
    obs_image, obs_pixel = sparse.obs_image, sparse.obs_pixel
    order = np.argsort(obs_image, kind="stable")
    counts = np.bincount(obs_image, minlength=len(scene.viewmats))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    point2d_index = np.empty(len(order), np.int64)
    point2d_index[order] = np.arange(len(order)) - np.repeat(starts, counts)
    for i, viewmat in enumerate(scene.viewmats):  # one pycolmap Image per view
        keypoints = obs_pixel[order[starts[i]: starts[i] + counts[i]]].astype(np.float64)
        image = pycolmap.Image(name=image_name(i), keypoints=keypoints.reshape(-1, 2), camera_id=1, image_id=i + 1)
        reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(viewmat[:3, :4]))
    track_bounds = np.searchsorted(sparse.obs_point, np.arange(len(sparse.xyz) + 1))
    for p in range(len(sparse.xyz)):  # pycolmap takes points one at a time
        lo, hi = track_bounds[p], track_bounds[p + 1]
        track = pycolmap.Track(
            [pycolmap.TrackElement(int(obs_image[k]) + 1, int(point2d_index[k])) for k in range(lo, hi)]
        )
        reconstruction.add_point3D(sparse.xyz[p], track, sparse.rgb[p])
    reconstruction.update_point_3d_errors()
    return reconstruction
