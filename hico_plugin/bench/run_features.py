"""The paper's cross-level feature analysis (supplementary "Cross-Level Feature Incoherence Analysis").

For anchor features f [N, d] and octree levels l [N]: d(l_a, l_b) = 1 - mean_{i in A_a, j in A_b} cos(f_i, f_j) =
1 - u_a . u_b, with u_a the mean unit-normalised feature of level a (the double mean factorises), so the [L, L]
matrix costs one pass. For CLCA runs it is also computed on f_hat = context(f), the features the decoder sees.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from hico_plugin.errors import HicoError


def cross_level_distance(features: Tensor, levels: Tensor, num_levels: int | None = None) -> Tensor:
    """Mean pairwise cosine distance between levels. features [N, d], levels [N] long -> [L, L]
    (NaN rows/columns for levels without anchors)."""
    num_levels = int(levels.max()) + 1 if num_levels is None else num_levels
    unit = F.normalize(features.double(), dim=1)
    sums = torch.zeros(num_levels, features.shape[1], dtype=unit.dtype).index_add_(0, levels, unit)
    counts = torch.bincount(levels, minlength=num_levels).to(unit.dtype)
    means = sums / counts[:, None]  # NaN for empty levels, by design
    return (1.0 - means @ means.T).float()


def adjacent_distances(distance: Tensor) -> Tensor:
    """d(l, l+1) for l = 0..L-2: distance [L, L] -> [L-1]."""
    return distance.diagonal(offset=1)


def stratified_sample(levels: Tensor, per_level: int, generator: torch.Generator | None = None) -> Tensor:
    """Indices of at most ``per_level`` random anchors of every level (all of a smaller level).
    levels [N] long -> indices [M] long, grouped by level."""
    perm = torch.randperm(len(levels), generator=generator)
    order = perm[torch.argsort(levels[perm], stable=True)]
    counts = torch.bincount(levels)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(len(levels)) - starts[levels[order]]
    return order[rank < per_level]


def pair_pca(features: Tensor, levels: Tensor, level: int, per_level: int = 3000,
             generator: torch.Generator | None = None) -> dict[str, Any] | None:
    """PCA of the anchors of ``level`` and ``level + 1`` (each subsampled to ``per_level``).

    Returns {"projection": [M, 2], "levels": [M], "explained": [PC1, PC2] variance ratios,
    "cos_sim": cosine similarity of the two levels' mean features}, or None when a level is empty.
    """
    mask = (levels == level) | (levels == level + 1)
    ids = mask.nonzero().squeeze(1)
    sub_levels = levels[ids]
    if (sub_levels == level).sum() == 0 or (sub_levels == level + 1).sum() == 0:
        return None
    ids = ids[stratified_sample(sub_levels - level, per_level, generator)]
    x = features[ids].double()
    x = x - x.mean(0)
    _, singular, vh = torch.linalg.svd(x, full_matrices=False)
    variance = singular ** 2
    explained = (variance / variance.sum().clamp_min(1e-30))[:2]
    mean_a, mean_b = features[levels == level].double().mean(0), features[levels == level + 1].double().mean(0)
    return {"projection": (x @ vh[:2].T).float(), "levels": levels[ids],
            "explained": [float(v) for v in explained],
            "cos_sim": float(F.cosine_similarity(mean_a, mean_b, dim=0))}


def feature_numbers(features: Tensor, levels: Tensor, num_levels: int, per_level: int, seed: int) -> dict[str, Any]:
    """Distance matrix, adjacent distances and per-pair PCA summaries (projections under "_pca")."""
    distance = cross_level_distance(features, levels, num_levels)
    generator = torch.Generator().manual_seed(seed)
    pcas = [pair_pca(features, levels, level, per_level, generator) for level in range(num_levels - 1)]
    return {"distance": _nan_to_none(distance.tolist()), "adjacent": _nan_to_none(adjacent_distances(distance).tolist()),
            "pca": [None if p is None else {"pair": [i, i + 1], "explained": p["explained"], "cos_sim": p["cos_sim"]}
                    for i, p in enumerate(pcas)],
            "_pca": pcas}


def _nan_to_none(values: Any) -> Any:
    if isinstance(values, list):
        return [_nan_to_none(v) for v in values]
    return None if isinstance(values, float) and math.isnan(values) else values


def run_features(run_dir: Path) -> dict[str, Any]:
    """Anchor features of a trained run: {"method", "f", "f_hat" (None without CLCA), "levels", "num_levels",
    "lookup" (the per-level CLCA lookup table over the test views, field/lookup_stats.py)}."""
    from hico_plugin.engine.loading import load_run
    from hico_plugin.field.lookup_stats import lookup_table

    config_path = run_dir / "config.yml"
    if not config_path.is_file():
        raise HicoError(f"{run_dir}: not a training run (expected {config_path})")
    run = load_run(config_path, device="cpu")
    config, model, dataset = run.config, run.model, run.dataset
    field = model.field
    with torch.no_grad():
        features = field.anchor_features.detach().float()
        levels = field.levels.detach()
        if field.context.reads_context:  # every anchor counted as visible
            every = torch.arange(field.num_anchors)
            f_hat = field.context(features, field.context.graph(levels, field.anchors, every, field.grid)).float()
        else:
            f_hat = None
    views = dataset.test_indices.tolist() or dataset.train_indices.tolist()
    lookup = lookup_table(field, [dataset.cameras[i] for i in views])
    return {"method": config.method_name, "f": features, "f_hat": f_hat, "levels": levels,
            "num_levels": int(field.grid.num_levels), "lookup": lookup}


def analyze_features(features: Tensor, levels: Tensor, num_levels: int, f_hat: Tensor | None = None,
                     per_level: int = 3000, seed: int = 0) -> dict[str, Any]:
    """Numbers of one run: {"anchors_per_level", "f": numbers, "f_hat": numbers or None,
    "adjacent_reduction": relative drop of d(l, l+1) from f to f_hat (None without f_hat)}."""
    out: dict[str, Any] = {"anchors_per_level": torch.bincount(levels, minlength=num_levels).tolist(),
                           "f": feature_numbers(features, levels, num_levels, per_level, seed), "f_hat": None,
                           "adjacent_reduction": None}
    if f_hat is not None:
        out["f_hat"] = feature_numbers(f_hat, levels, num_levels, per_level, seed)
        out["adjacent_reduction"] = [None if a is None or b is None or a == 0 else (a - b) / a
                                     for a, b in zip(out["f"]["adjacent"], out["f_hat"]["adjacent"])]
    return out
