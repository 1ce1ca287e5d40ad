"""How far the cameras are from what they see: whether the views stand at different distances, and
the octree level count the points' distance span calls for (the LOD effect's finding, which reports both).
"""

from __future__ import annotations

import numpy as np

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding, group_median
from hico_plugin.field.octree import level_count

# multi-distance: the cameras' median distances to the points they see spread by more than this
# (95th / 5th percentile over views): one octree level (fork 2) or more apart. Single-orbit captures
# measure ~1.2; the pagoda's three rings at one range ~1.5; the city-block's near-to-far rings ~3.
MULTI_DISTANCE_MIN_RATIO = 2.0

# lod: octree levels = round(log2(d_max / d_min)) + 1 (the octree's own rule, fork 2), with the
# distances' 0.1 / 99.9 % quantiles; more than one level means the points span distances. Whether the
# views themselves stand at different distances is reported beside it (the LOD effect's measured rule).
LOD_MIN_LEVELS = 2


def multi_distance_finding(evidence: DatasetEvidence) -> EffectFinding:
    """Whether the views stand at different distances (measured once per evidence: the lod finding reads it)."""
    return evidence.memo("multi_distance", lambda: _multi_distance(evidence))


def _multi_distance(evidence: DatasetEvidence) -> EffectFinding:
    dataset, tracks = evidence.dataset, evidence.tracks
    centres = dataset.cameras.centers.double().numpy()
    distance = np.linalg.norm(tracks.points[tracks.obs_point] - centres[tracks.obs_view], axis=1)
    medians = group_median(tracks.obs_view, distance[:, None], len(dataset))[:, 0]
    medians = medians[np.bincount(tracks.obs_view, minlength=len(dataset)) > 0]
    if len(medians) < 2:
        return EffectFinding(False, "fewer than 2 views see sparse points", {})
    near, far = np.percentile(medians, [5, 95])
    ratio = float(far / max(near, 1e-12))
    present = ratio > MULTI_DISTANCE_MIN_RATIO
    reason = (f"views' median point distances span {ratio:.2f}x (5-95 %; threshold {MULTI_DISTANCE_MIN_RATIO}x)")
    return EffectFinding(bool(present), reason, {"distance_ratio": round(ratio, 4), "threshold_ratio": MULTI_DISTANCE_MIN_RATIO})


def lod_finding(evidence: DatasetEvidence) -> EffectFinding:
    dist_min, dist_max = evidence.dataset.camera_distance_range()
    levels = level_count(dist_min, dist_max)
    ratio = dist_max / max(dist_min, 1e-12)
    views = multi_distance_finding(evidence)
    present = levels >= LOD_MIN_LEVELS
    reason = (f"camera-to-point distances span {ratio:.3g}x ({dist_min:.3g} .. {dist_max:.3g}) -> {levels} "
              f"octree level{'s' if levels != 1 else ''}; {views.reason}")
    return EffectFinding(bool(present), reason, {"dist_min": dist_min, "dist_max": dist_max, "levels": levels,
                                                 "views_multi_distance": views.present})
