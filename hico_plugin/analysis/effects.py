"""Which image-formation effects a capture has, measured from its data (``hico-inspect``, the run dir).

The model simulates only what this finds (``--model.effects auto``):

- **exposure** — per-image exposure and white-balance gains from the colours of the *same* sparse
  point in different photos. COLMAP tracks say which photos see a point (occlusion already solved by
  SfM); each observation's colour is read at the point's projection into the loaded (downscaled,
  undistorted) image. ``log colour[i, p, c] = gain[i, c] + albedo[p, c]`` is solved robustly
  (alternating medians, mean gain 0) per channel. Formats without tracks: every point is projected
  into every view and kept where it is the nearest point of its coarse depth-buffer cell.
- **sky** — image cells (``SKY_CELL_PX`` square) with no sparse point projected into them, above
  the horizon of the scene's up vector, smooth and bright: open sky or an unbounded background
  the Gaussians cannot represent. A point occluded in a view still projects onto a surface pixel,
  never onto sky, so this test needs no visibility.
- **noise** — per-image sensor noise (Immerkær's Laplacian estimator on the smoothest cells).
  Reported only: the L1 loss averages zero-mean noise, no model component is needed.
- **distortion** — from the camera model; distorted cameras are undistorted at load.
- **lod** — the spread of camera-to-point distances, which sets the octree's level count.

Every threshold is a named constant below, with why it has its value.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import cv2
import numpy as np
import torch

from hico_plugin.data.transform import scene_up
from hico_plugin.data.undistort import PINHOLE_MODELS

# exposure: a photo whose exposure differs from the mean by more than this (robust std over photos,
# in stops) is an appearance change worth modelling. Consistent-exposure captures measure <= 0.03
# stops here (texture sampling and sensor noise); the built-in pagoda's effect has a 0.35-stop std.
EXPOSURE_STD_STOPS = 0.1
# white balance: per-channel deviation from the photo's exposure, robust std in stops. Neutral
# captures measure <= 0.02; the generator's white-balance std is 0.06 natural-log = 0.087 stops.
WHITE_BALANCE_STD_STOPS = 0.05
# a colour sample is used only unclipped: all channels inside (LOW, HIGH) of the 0..1 range.
UNCLIPPED = (4 / 255, 250 / 255)
# least observations per photo for its gain to count (fewer -> the photo is reported as unknown).
MIN_OBSERVATIONS = 20
MAX_POINTS = 20_000  # points used for the gains (strided); thousands already pin a gain to ~0.01 stop

# sky: image cells of 1/SKY_CELLS_PER_SIDE of the shorter image side (>= 4 px), so a thin band of sky
# still fills whole cells at low resolution; a cell is sky-like when no sparse point falls in it,
SKY_CELLS_PER_SIDE = 30
# it is connected through such cells to the image edge facing the scene's up vector (edge
# cells whose centre ray lies above the view's median elevation) — not "elevation > 0": a finite
# ground lets sky show below the true horizon (city-block's top rows look 8 degrees down at sky),
# its mean absolute colour gradient, after a sigma-1.5 px blur that removes sensor noise, is below
# this (sky is smooth; textured surfaces are not),
SKY_MAX_GRADIENT = 0.03
# and its mean luminance is above this: a black fill is the model's constant background already.
SKY_MIN_LUMINANCE = 0.2
# a capture has sky when more than this share of all cells is sky-like (city-block: ~25 %).
SKY_MIN_FRACTION = 0.02
SKY_MAX_VIEWS = 32  # views analysed (evenly spaced); sky is a property of the whole capture

# noise: Immerkær's estimate over the smoothest 10 % of cells, median over photos, in 8-bit levels.
# Clean renders measure < 1 level (quantisation); the built-in sensor noise is ~3-4 levels.
NOISE_MIN_LEVELS = 1.5
NOISE_UNCLIPPED = (2, 253)
NOISE_MIN_FLAT_SHARE = 0.05  # fewer flat unclipped cells than this share: noise not measurable
NOISE_FLAT_GRADIENT = 2.0  # 8-bit levels per pixel of the blurred image: flat cells only  # 8-bit levels a noise cell must stay strictly between

# distortion: a camera counts as distorted when undistortion moves its corner pixel by > this.
DISTORTION_MIN_PX = 0.5

# multi-distance: the cameras' median distances to the points they see spread by more than this
# (95th / 5th percentile over views): one octree level (fork 2) or more apart. Single-orbit captures
# measure ~1.2; the pagoda's three rings at one range ~1.5; the city-block's near-to-far rings ~3.
MULTI_DISTANCE_MIN_RATIO = 2.0

# lod: octree levels = round(log2(d_max / d_min)) + 1 (the octree's own rule, fork 2), with the
# distances' 0.1 / 99.9 % quantiles; more than one level means the capture spans distances.
LOD_MIN_LEVELS = 2


@dataclass
class EffectFinding:
    """One effect: whether the data shows it, the measured figure and why."""

    present: bool
    reason: str
    figures: dict[str, Any] = field(default_factory=dict)


@dataclass
class EffectsReport:
    """What ``analyze_effects`` found, by effect name; ``per_image`` holds the exposure gains."""

    effects: dict[str, EffectFinding]
    per_image: list[dict[str, Any]]

    def lines(self) -> list[str]:
        return [f"{name:<15}{'yes' if f.present else 'no '} — {f.reason}" for name, f in self.effects.items()]

    def to_json(self) -> dict[str, Any]:
        return {"effects": {name: asdict(f) for name, f in self.effects.items()}, "per_image": self.per_image}

    def present(self, name: str) -> bool:
        return name in self.effects and self.effects[name].present

    def log2_gains(self, views: list[int]) -> np.ndarray:
        """Measured per-channel log2 gains [len(views), 3] of those dataset views (NaN where a view
        had too few shared observations): exposure plus white balance, mean zero over the photos."""
        out = np.full((len(views), 3), np.nan)
        for row, view in enumerate(views):
            entry = self.per_image[view]
            if entry["exposure_stops"] is not None:
                out[row] = entry["exposure_stops"] + np.asarray(entry["white_balance_stops"])
        return out


def analyze_effects(dataset: Any, tracks: "Tracks | None" = None) -> EffectsReport:
    """Analyse ``dataset`` (a ``hico_plugin.data.Dataset``); ``tracks`` default: read from its
    COLMAP model when there is one, else visibility by depth buffer."""
    if tracks is None:
        tracks = read_tracks(dataset)
    gains, per_image = exposure_gains(dataset, tracks)
    effects = {
        "exposure": _exposure_finding(gains),
        "sky": _sky_finding(dataset),
        "noise": _noise_finding(dataset),
        "distortion": _distortion_finding(dataset),
        "multi_distance": _multi_distance_finding(dataset, tracks),
        "lod": _lod_finding(dataset),
    }
    return EffectsReport(effects, per_image)


# ----- observations -----------------------------------------------------------------------------


@dataclass
class Tracks:
    """Which view sees which point: points [P,3] (normalised frame), obs_view [O], obs_point [O]."""

    points: np.ndarray
    obs_view: np.ndarray
    obs_point: np.ndarray
    source: str  # "colmap tracks" or "depth buffer"


def read_tracks(dataset: Any) -> Tracks:
    """COLMAP tracks of ``dataset.data_dir/sparse/0`` when readable, else visibility by depth buffer."""
    model_dir = dataset.data_dir / "sparse" / "0"
    try:
        import pycolmap

        reconstruction = pycolmap.Reconstruction(str(model_dir))
    except Exception:  # noqa: BLE001 -- no COLMAP model (another format): fall back below
        return depth_buffer_tracks(dataset)
    view_of_image = {}
    index = {name: i for i, name in enumerate(dataset.image_names)}
    for image_id, image in reconstruction.images.items():
        if image.name in index:
            view_of_image[image_id] = index[image.name]
    ids = sorted(reconstruction.points3D)[:: max(1, -(-len(reconstruction.points3D) // MAX_POINTS))]
    xyz, obs_view, obs_point = [], [], []
    for p, point_id in enumerate(ids):
        point = reconstruction.points3D[point_id]
        xyz.append(point.xyz)
        for element in point.track.elements:
            view = view_of_image.get(element.image_id)
            if view is not None:
                obs_view.append(view)
                obs_point.append(p)
    points = dataset.transform.points_from_colmap(torch.as_tensor(np.array(xyz).reshape(-1, 3))).numpy()
    return Tracks(points, np.array(obs_view, np.int64), np.array(obs_point, np.int64), "colmap tracks")


def depth_buffer_tracks(dataset: Any, cell_px: int = 8, tolerance: float = 0.05) -> Tracks:
    """Visibility without tracks: a point is seen by a view when it projects inside the image and is
    within ``tolerance`` (relative depth) of the nearest point in its ``cell_px`` cell — a coarse
    depth buffer of the sparse points themselves, so a point behind a wall is dropped."""
    points = dataset.points.double().numpy()[:: max(1, -(-len(dataset.points) // MAX_POINTS))]
    obs_view, obs_point = [], []
    for view in range(len(dataset)):
        pixels, depth, inside = _project(dataset, view, points)
        ids = np.nonzero(inside)[0]
        cells = (pixels[ids, 1] // cell_px).astype(np.int64) * 100_000 + (pixels[ids, 0] // cell_px).astype(np.int64)
        nearest = np.full(cells.max() + 1 if len(cells) else 1, np.inf)
        np.minimum.at(nearest, cells, depth[ids])
        keep = depth[ids] <= nearest[cells] * (1.0 + tolerance)
        obs_view += [view] * int(keep.sum())
        obs_point += ids[keep].tolist()
    return Tracks(points, np.array(obs_view, np.int64), np.array(obs_point, np.int64), "depth buffer")


def _project(dataset: Any, view: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """points [P,3] -> (pixels [P,2] (x, y), depth [P], inside [P] bool) in view ``view``."""
    viewmat = dataset.cameras.viewmats[view].double().numpy()
    K = dataset.cameras.Ks[view].double().numpy()
    width, height = int(dataset.cameras.widths[view]), int(dataset.cameras.heights[view])
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    depth = cam[:, 2]
    safe = np.where(depth > 1e-9, depth, 1.0)
    pixels = np.stack([K[0, 0] * cam[:, 0] / safe + K[0, 2], K[1, 1] * cam[:, 1] / safe + K[1, 2]], axis=1)
    inside = (depth > 1e-9) & (pixels[:, 0] >= 0) & (pixels[:, 0] < width) & (pixels[:, 1] >= 0) & (pixels[:, 1] < height)
    return pixels, depth, inside


# ----- exposure -----------------------------------------------------------------------------------


def exposure_gains(dataset: Any, tracks: Tracks) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """Per-view log2 gains [V,3] (NaN where a view has too few observations) and a per-image list."""
    num_views = len(dataset)
    samples = np.full((len(tracks.obs_view), 3), np.nan)
    for view in range(num_views):
        rows = np.nonzero(tracks.obs_view == view)[0]
        if len(rows) == 0:
            continue
        pixels, _, inside = _project(dataset, view, tracks.points[tracks.obs_point[rows]])
        image = dataset.image(view).numpy().astype(np.float64) / 255.0
        colour = _box3(image, pixels[inside])
        ok = ((colour > UNCLIPPED[0]) & (colour < UNCLIPPED[1])).all(axis=1)
        samples[rows[inside][ok]] = colour[ok]
    valid = np.isfinite(samples).all(axis=1)
    views, point_ids, logs = tracks.obs_view[valid], tracks.obs_point[valid], np.log2(samples[valid])
    # only points seen unclipped in two or more views tie gains together
    counts = np.bincount(point_ids, minlength=len(tracks.points))
    multi = counts[point_ids] >= 2
    views, point_ids, logs = views[multi], point_ids[multi], logs[multi]
    gains = np.zeros((num_views, 3))
    per_view_count = np.bincount(views, minlength=num_views)
    for _ in range(8):  # alternating medians: albedo given gains, gains given albedo
        albedo = _group_median(point_ids, logs - gains[views], len(tracks.points))
        gains = _group_median(views, logs - albedo[point_ids], num_views)
        known = per_view_count >= MIN_OBSERVATIONS
        if known.any():
            gains -= gains[known].mean(axis=0)
    gains[per_view_count < MIN_OBSERVATIONS] = np.nan
    per_image = []
    for view in range(num_views):
        g = gains[view]
        exposure = float(g.mean()) if np.isfinite(g).all() else None
        per_image.append({
            "image": dataset.image_names[view],
            "observations": int(per_view_count[view]),
            "exposure_stops": None if exposure is None else round(exposure, 4),
            "white_balance_stops": None if exposure is None else [round(float(x - exposure), 4) for x in g],
        })
    return gains, per_image


def _box3(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Mean colour [N,3] of the 3x3 pixels around each pixel position [N,2] (x, y)."""
    height, width = image.shape[:2]
    x = np.clip(pixels[:, 0].astype(np.int64), 0, width - 1)
    y = np.clip(pixels[:, 1].astype(np.int64), 0, height - 1)
    total = np.zeros((len(x), 3))
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            total += image[np.clip(y + dy, 0, height - 1), np.clip(x + dx, 0, width - 1)]
    return total / 9.0


def _group_median(groups: np.ndarray, values: np.ndarray, num_groups: int) -> np.ndarray:
    """Per-group, per-channel median: groups [N], values [N,3] -> [num_groups,3] (0 for empty groups)."""
    out = np.zeros((num_groups, values.shape[1]))
    order = np.argsort(groups, kind="stable")
    groups, values = groups[order], values[order]
    bounds = np.searchsorted(groups, np.arange(num_groups + 1))
    for g in range(num_groups):
        lo, hi = bounds[g], bounds[g + 1]
        if hi > lo:
            out[g] = np.median(values[lo:hi], axis=0)
    return out


def _robust_std(values: np.ndarray) -> float:
    """1.4826 x median absolute deviation (the std for a normal distribution, blind to outliers)."""
    values = values[np.isfinite(values)]
    if len(values) < 2:
        return 0.0
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def _exposure_finding(gains: np.ndarray) -> EffectFinding:
    known = np.isfinite(gains).all(axis=1)
    if known.sum() < 2:
        return EffectFinding(False, "fewer than 2 photos share enough unclipped sparse points to compare",
                             {"photos_compared": int(known.sum())})
    exposure = gains[known].mean(axis=1)
    balance = gains[known] - exposure[:, None]
    exposure_std = _robust_std(exposure)
    balance_std = max(_robust_std(balance[:, c]) for c in range(3))
    spread = float(exposure.max() - exposure.min())
    figures = {"photos_compared": int(known.sum()), "exposure_std_stops": round(exposure_std, 4),
               "exposure_range_stops": round(spread, 4), "white_balance_std_stops": round(balance_std, 4),
               "thresholds": {"exposure_std_stops": EXPOSURE_STD_STOPS, "white_balance_std_stops": WHITE_BALANCE_STD_STOPS}}
    present = exposure_std > EXPOSURE_STD_STOPS or balance_std > WHITE_BALANCE_STD_STOPS
    reason = (f"photos differ by up to {spread:.2f} stops (std {exposure_std:.2f}, threshold "
              f"{EXPOSURE_STD_STOPS}), white balance std {balance_std:.3f} stops (threshold "
              f"{WHITE_BALANCE_STD_STOPS}) over {int(known.sum())} photos")
    return EffectFinding(bool(present), reason, figures)


# ----- sky ----------------------------------------------------------------------------------------


def up_vector(dataset: Any) -> np.ndarray:
    """The scene's up direction [3] (data.transform.scene_up) in the dataset's (normalised, so z-up when oriented) frame."""
    return scene_up(dataset.cameras.viewmats).numpy()


def sky_cells(dataset: Any, view: int, points: np.ndarray, up: np.ndarray) -> np.ndarray:
    """bool [H/cell, W/cell]: the sky-like cells of ``view`` (see the module docstring)."""
    image = dataset.image(view).numpy().astype(np.float32) / 255.0
    height, width = image.shape[:2]
    size = max(4, min(height, width) // SKY_CELLS_PER_SIDE)
    rows, cols = height // size, width // size
    if rows == 0 or cols == 0:
        return np.zeros((0, 0), bool)
    image = image[: rows * size, : cols * size]
    pixels, _, inside = _project(dataset, view, points)
    occupied = np.zeros((rows, cols), bool)
    occupied[np.clip((pixels[inside, 1] // size).astype(np.int64), 0, rows - 1),
             np.clip((pixels[inside, 0] // size).astype(np.int64), 0, cols - 1)] = True
    blurred = cv2.GaussianBlur(image, (0, 0), 1.5)
    gradient = np.zeros(image.shape[:2], np.float32)
    gradient[:, :-1] += np.abs(np.diff(blurred, axis=1)).mean(axis=2)
    gradient[:-1, :] += np.abs(np.diff(blurred, axis=0)).mean(axis=2)
    cell = lambda a: a.reshape(rows, size, cols, size).mean(axis=(1, 3))  # noqa: E731
    smooth = cell(gradient) < SKY_MAX_GRADIENT
    bright = cell(image.mean(axis=2)) > SKY_MIN_LUMINANCE
    # centre ray of each cell, world frame
    K = dataset.cameras.Ks[view].double().numpy()
    R = dataset.cameras.viewmats[view, :3, :3].double().numpy()
    u = (np.arange(cols) + 0.5) * size
    v = (np.arange(rows) + 0.5) * size
    uu, vv = np.meshgrid(u, v)
    dirs = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], axis=-1) @ R
    elevation = (dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)) @ up
    candidate = ~occupied & smooth & bright
    edge = np.zeros_like(candidate)
    edge[[0, -1], :] = True
    edge[:, [0, -1]] = True
    upper_edge = edge & (elevation > np.median(elevation)) & candidate
    _, labels = cv2.connectedComponents(candidate.astype(np.uint8), connectivity=4)
    keep = np.unique(labels[upper_edge])
    return candidate & np.isin(labels, keep[keep > 0])


def _sky_finding(dataset: Any) -> EffectFinding:
    points = dataset.points.double().numpy()
    up = up_vector(dataset)
    views = np.unique(np.linspace(0, len(dataset) - 1, min(SKY_MAX_VIEWS, len(dataset))).round().astype(int))
    sky, total, views_with_sky = 0, 0, 0
    for view in views:
        cells = sky_cells(dataset, int(view), points, up)
        sky += int(cells.sum())
        total += cells.size
        views_with_sky += int(cells.mean() > SKY_MIN_FRACTION) if cells.size else 0
    fraction = sky / max(total, 1)
    present = fraction > SKY_MIN_FRACTION
    figures = {"sky_fraction": round(fraction, 4), "views_analysed": len(views), "views_with_sky": views_with_sky,
               "threshold_fraction": SKY_MIN_FRACTION, "up": [round(float(x), 4) for x in up]}
    if present:
        reason = (f"{100 * fraction:.1f} % of image cells are point-free, smooth, bright and reach the "
                  f"upward image edge ({views_with_sky}/{len(views)} views; threshold {100 * SKY_MIN_FRACTION:.0f} %)")
    else:
        reason = (f"no open sky found ({100 * fraction:.1f} % of image cells sky-like; threshold "
                  f"{100 * SKY_MIN_FRACTION:.0f} %)")
    return EffectFinding(bool(present), reason, figures)


# ----- noise --------------------------------------------------------------------------------------

_LAPLACE = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float64)


def noise_levels(image: np.ndarray, cell: int = 8) -> float | None:
    """Sensor noise std of ``image`` [H,W,3] uint8 in 8-bit levels (Immerkær 1996: the mean |L * I|
    times sqrt(pi/2)/6 is the std of white noise), over the smoothest 10 % of flat, unclipped cells;
    None when too few such cells exist (textured everywhere, or a clipped black background)."""
    gray = image.astype(np.float64).mean(axis=2)
    h, w = gray.shape
    response = np.zeros((h - 2, w - 2))
    for dy in range(3):
        for dx in range(3):
            response += _LAPLACE[dy, dx] * gray[dy : dy + h - 2, dx : dx + w - 2]
    rows, cols = (h - 2) // cell, (w - 2) // cell
    if rows == 0 or cols == 0:
        return 0.0
    blocks = np.abs(response[: rows * cell, : cols * cell]).reshape(rows, cell, cols, cell).mean(axis=(1, 3))
    # clipped cells (black background, blown highlights) lose their noise: leave them out
    level = gray[1 : 1 + rows * cell, 1 : 1 + cols * cell].reshape(rows, cell, cols, cell)
    unclipped = ((level.min(axis=(1, 3)) > NOISE_UNCLIPPED[0]) & (level.max(axis=(1, 3)) < NOISE_UNCLIPPED[1])).ravel()
    # and textured cells inflate it: keep cells that are flat once blurred past the noise
    blurred = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.5)
    grad = np.abs(np.diff(blurred, axis=1))[1 : 1 + rows * cell, 1 : 1 + cols * cell]
    flat = (grad.reshape(rows, cell, cols, cell).mean(axis=(1, 3)) < NOISE_FLAT_GRADIENT).ravel()
    blocks = blocks.ravel()[unclipped & flat]
    if blocks.size < NOISE_MIN_FLAT_SHARE * rows * cols:
        return None
    smooth = np.sort(blocks)[: max(1, blocks.size // 10)]
    # a gray pixel averages three channels with independent noise: scale back to one channel
    return float(smooth.mean() * math.sqrt(math.pi / 2) / 6.0 * math.sqrt(3.0))


def _noise_finding(dataset: Any) -> EffectFinding:
    views = np.unique(np.linspace(0, len(dataset) - 1, min(SKY_MAX_VIEWS, len(dataset))).round().astype(int))
    measured = [x for v in views if (x := noise_levels(dataset.image(int(v)).numpy())) is not None]
    if not measured:
        return EffectFinding(False, "not measurable: no flat, unclipped image region (reported only, no model "
                             "component)", {"noise_std_levels": None, "threshold_levels": NOISE_MIN_LEVELS})
    levels = float(np.median(measured))
    present = levels > NOISE_MIN_LEVELS
    reason = (f"noise std {levels:.2f} of 255 levels (threshold {NOISE_MIN_LEVELS}); "
              + ("the L1 loss averages it, no model component" if present else "clean images"))
    return EffectFinding(bool(present), reason, {"noise_std_levels": round(levels, 3), "threshold_levels": NOISE_MIN_LEVELS})


# ----- distortion ---------------------------------------------------------------------------------


def _distortion_finding(dataset: Any) -> EffectFinding:
    worst, models = 0.0, set()
    for source in dataset.sources.values():
        models.add(source.model)
        if source.model in PINHOLE_MODELS:
            continue
        camera = source.distorted
        corner = np.array([[0.0, 0.0], [camera.width - 1.0, camera.height - 1.0]])
        rays = camera.cam_from_img(corner)  # undistorted normalised coordinates
        ideal = np.stack([camera.focal_length_x * rays[:, 0] + camera.principal_point_x,
                          camera.focal_length_y * rays[:, 1] + camera.principal_point_y], axis=1)
        worst = max(worst, float(np.abs(ideal - corner).max()))
    present = worst > DISTORTION_MIN_PX
    reason = (f"camera model {', '.join(sorted(models))}; corner displacement {worst:.1f} px (threshold "
              f"{DISTORTION_MIN_PX} px)" + ("; undistorted to PINHOLE at load" if present else ""))
    return EffectFinding(bool(present), reason, {"models": sorted(models), "corner_displacement_px": round(worst, 3)})


# ----- lod ----------------------------------------------------------------------------------------


def _multi_distance_finding(dataset: Any, tracks: Tracks) -> EffectFinding:
    centres = dataset.cameras.centers.double().numpy()
    distance = np.linalg.norm(tracks.points[tracks.obs_point] - centres[tracks.obs_view], axis=1)
    medians = _group_median(tracks.obs_view, distance[:, None], len(dataset))[:, 0]
    medians = medians[np.bincount(tracks.obs_view, minlength=len(dataset)) > 0]
    if len(medians) < 2:
        return EffectFinding(False, "fewer than 2 views see sparse points", {})
    near, far = np.percentile(medians, [5, 95])
    ratio = float(far / max(near, 1e-12))
    present = ratio > MULTI_DISTANCE_MIN_RATIO
    reason = (f"views' median point distances span {ratio:.2f}x (5-95 %; threshold {MULTI_DISTANCE_MIN_RATIO}x)")
    return EffectFinding(bool(present), reason, {"distance_ratio": round(ratio, 4), "threshold_ratio": MULTI_DISTANCE_MIN_RATIO})


def lod_levels(dist_min: float, dist_max: float) -> int:
    """The octree's level count for a distance range (fork 2): round(log2(max / min)) + 1."""
    return round(math.log2(dist_max / dist_min)) + 1 if dist_min > 0 and dist_max > dist_min else 1


def _lod_finding(dataset: Any) -> EffectFinding:
    dist_min, dist_max = dataset.camera_distance_range()
    levels = lod_levels(dist_min, dist_max)
    ratio = dist_max / max(dist_min, 1e-12)
    present = levels >= LOD_MIN_LEVELS
    reason = (f"camera-to-point distances span {ratio:.3g}x ({dist_min:.3g} .. {dist_max:.3g}) -> {levels} "
              f"octree level{'s' if levels != 1 else ''}")
    return EffectFinding(bool(present), reason, {"dist_min": dist_min, "dist_max": dist_max, "levels": levels})
