"""Per-photo exposure and white balance, from the colours of the *same* sparse point in different photos.

The tracks say which photos see a point (occlusion already solved by SfM); each observation's colour is
read at the point's projection into the loaded (downscaled, undistorted) image.
``log colour[i, p, c] = gain[i, c] + albedo[p, c]`` is solved robustly (alternating medians, mean gain
0) per channel. Formats without tracks: every point is projected into every view and kept where it is
the nearest point of its coarse depth-buffer cell (``evidence.depth_buffer_tracks``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding, Tracks, group_median, project_points

# stops here (texture sampling and sensor noise); the built-in pagoda's effect has a 0.35-stop std.
EXPOSURE_STD_STOPS = 0.1
# white balance: per-channel deviation from the photo's exposure, robust std in stops. Neutral
# captures measure <= 0.02; the generator's white-balance std is 0.06 natural-log = 0.087 stops.
WHITE_BALANCE_STD_STOPS = 0.05
# a colour sample is used only unclipped: all channels inside (LOW, HIGH) of the 0..1 range.
UNCLIPPED = (4 / 255, 250 / 255)
# least observations per photo for its gain to count (fewer -> the photo is reported as unknown).
MIN_OBSERVATIONS = 20


def exposure_gains(dataset: Any, tracks: Tracks) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """Per-view log2 gains [V,3] (NaN where a view has too few observations) and a per-image list."""
    num_views = len(dataset)
    samples = np.full((len(tracks.obs_view), 3), np.nan)
    for view in range(num_views):
        rows = np.nonzero(tracks.obs_view == view)[0]
        if len(rows) == 0:
            continue
        pixels, _, inside = project_points(dataset, view, tracks.points[tracks.obs_point[rows]])
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
        albedo = group_median(point_ids, logs - gains[views], len(tracks.points))
        gains = group_median(views, logs - albedo[point_ids], num_views)
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



def photo_gains(evidence: DatasetEvidence) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """``exposure_gains`` of the evidence's dataset and tracks, measured once per analysis."""
    return evidence.memo("photo_gains", lambda: exposure_gains(evidence.dataset, evidence.tracks))


def exposure_finding(evidence: DatasetEvidence) -> EffectFinding:
    return _exposure_finding(photo_gains(evidence)[0])
