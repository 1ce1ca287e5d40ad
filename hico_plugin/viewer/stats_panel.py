"""The stats panel: its text and the loss / PSNR plot series (pure functions), and the panel that shows them."""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

# Keys shown first, in this order, with their labels; the rest follow sorted.
_KNOWN_STATS = (
    ("step", "step"),
    ("it_per_s", "it/s"),
    ("loss", "loss"),
    ("psnr", "train PSNR"),
    ("eval/psnr", "last eval PSNR"),
    ("num_anchors", "anchors"),
    ("num_gaussians", "Gaussians"),
    ("dngc_weight", "DNGC warmup weight"),
)
# Bookkeeping the panel leaves out: learning rates and wall-clock counters clutter it.
_HIDDEN_PREFIXES = ("lr/", "train_seconds", "skipped", "eval/step", "eval/train_seconds")


def _format_value(value: Any) -> str:
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if math.isnan(value):
            return "–"
        if value.is_integer() and abs(value) < 1e15:
            return f"{int(value):,}"
        return f"{value:.4g}"
    return str(value)


def format_stats_markdown(stats: Mapping[str, Any], anchors_per_level: Sequence[int] = ()) -> str:
    """A markdown table of the training figures, the per-level anchor counts last."""
    rows = [(label, stats[key]) for key, label in _KNOWN_STATS if key in stats]
    known = {key for key, _ in _KNOWN_STATS}
    rows += [
        (key, stats[key])
        for key in sorted(stats)
        if key not in known and not key.startswith(_HIDDEN_PREFIXES) and isinstance(stats[key], (int, float, str))
    ]
    if len(anchors_per_level):
        rows.append(("anchors per level", " / ".join(f"{int(n):,}" for n in anchors_per_level)))
    if not rows:
        return "_no statistics yet_"
    lines = ["| | |", "|---|---|"] + [f"| {label} | {_format_value(value)} |" for label, value in rows]
    return "\n".join(lines)


def plot_series(history: Mapping[str, np.ndarray], names: Sequence[str] = ("loss", "psnr")) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """x = history["step"] and the named series that hold any finite value, gaps forward-filled
    (uPlot draws a line through a NaN as a break; PSNR is often reported only every few steps)."""
    steps = np.asarray(history.get("step", ()), dtype=np.float64)
    series: dict[str, np.ndarray] = {}
    for name in names:
        values = np.asarray(history.get(name, ()), dtype=np.float64)
        if len(values) != len(steps) or not np.isfinite(values).any():
            continue
        finite = np.isfinite(values)
        last_finite = np.maximum.accumulate(np.where(finite, np.arange(len(values)), -1))
        first = values[finite][0]
        series[name] = np.where(last_finite >= 0, values[np.maximum(last_finite, 0)], first)
    return steps, series


_PLOT_COLORS = {"loss": "#d9480f", "psnr": "#1c7ed6"}


class StatsPanel:
    """The stats markdown and the training plot in the viewer's "Stats" folder."""

    def __init__(self, gui_api: Any, folder: Any, text: Any):
        self.gui_api, self.folder, self.text = gui_api, folder, text
        self.plot: Any = None
        self.plot_names: tuple[str, ...] = ()

    def update(self, stats: Mapping[str, Any], history: Mapping[str, np.ndarray],
               anchors_per_level: np.ndarray) -> None:
        self.text.content = format_stats_markdown(stats, anchors_per_level)
        steps, series = plot_series(history)
        if len(steps) < 2 or not series:
            return
        names = tuple(series)
        data = (steps, *series.values())
        if names == self.plot_names:
            self.plot.data = data
            return
        if self.plot is not None:  # a series appeared (e.g. PSNR): new plot layout
            self.plot.remove()
        self.plot_names = names
        with self.folder:
            self.plot = self.gui_api.add_uplot(
                data,
                ({"label": "step"}, *({"label": n, "stroke": _PLOT_COLORS.get(n, "#495057"), "scale": n} for n in names)),
                axes=({}, *({"scale": n, "side": 3 if i == 0 else 1, "label": n} for i, n in enumerate(names))),
                aspect=1.6,
            )
