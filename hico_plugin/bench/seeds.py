"""Seed statistics of a benchmark: mean +- std over seeds and a two-standard-error significance mark.

A difference between two presets on one scene counts as significant only when |mean_a - mean_b| >
2 * sqrt(s_a^2 / n_a + s_b^2 / n_b) (s = sample std over seeds); with fewer than two seeds on either
side nothing is marked, as one seed cannot show the spread.
"""

from __future__ import annotations

import math
from typing import Any, Sequence


def mean_std(values: Sequence[float]) -> tuple[float, float | None]:
    """(mean, sample std) of values; std None for a single value."""
    mean = sum(values) / len(values)
    if len(values) < 2:
        return mean, None
    return mean, math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1))


def difference(a: Sequence[float], b: Sequence[float]) -> tuple[float, float | None, bool]:
    """(mean(a) - mean(b), its standard error, significant beyond two standard errors)."""
    (mean_a, std_a), (mean_b, std_b) = mean_std(a), mean_std(b)
    if std_a is None or std_b is None:
        return mean_a - mean_b, None, False
    se = math.sqrt(std_a**2 / len(a) + std_b**2 / len(b))
    diff = mean_a - mean_b
    return diff, se, abs(diff) > 2 * se


def values_of(cells: list[dict[str, Any]], key: str) -> list[float]:
    return [c[key] for c in cells if c.get(key) is not None]


def format_mean_std(values: Sequence[float], digits: int = 2) -> str:
    if not values:
        return "–"
    mean, std = mean_std(values)
    return f"{mean:.{digits}f}" if std is None else f"{mean:.{digits}f} ± {std:.{digits}f}"


def format_difference(a: Sequence[float], b: Sequence[float], digits: int = 2) -> str:
    """"+0.40 ± 0.22 *" (difference ± standard error, * = beyond two standard errors)."""
    if not a or not b:
        return "–"
    diff, se, significant = difference(a, b)
    if se is None:
        return f"{diff:+.{digits}f}"
    return f"{diff:+.{digits}f} ± {se:.{digits}f}" + (" *" if significant else "")
