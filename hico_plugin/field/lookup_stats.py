"""How CLCA's lookup fares per octree level over the visible anchors of a set of views: ``lookup_table(field,
cameras)`` -> [{level, visible, parent_found, ...}, ...].

Per level: ``visible`` (anchor-views), ``parent_found`` / ``child_found`` (share found; parent None at level 0,
child at the finest level), ``parent_pooled`` / ``child_pooled`` (mean anchors pooled, over the found ones) and
``adjustment`` = ||f_hat - f|| / ||f|| over the level's visible anchors (Frobenius; None while f is zero).
"""

from __future__ import annotations

from typing import Any, Iterable

import torch
from torch import Tensor

from hico_plugin.cameras import Camera

SUMS = ("visible", "parent_found", "child_found", "parent_pooled", "child_pooled", "diff_sq", "feat_sq")


@torch.no_grad()
def view_lookup_sums(field, camera: Camera, step: int | None = None) -> Tensor:
    """Per-level sums of one view's lookup: [num_levels, len(SUMS)] float64 (see SUMS)."""
    ids = field.select(camera, step)
    features = field.anchor_features.index_select(0, ids)
    levels = field.levels.index_select(0, ids)
    graph = field.context.graph(field.levels, field.anchors, ids, field.grid)
    found = field.context.lookup(features, graph)
    enhanced = field.context(features, graph)
    columns = (torch.ones_like(levels), found.parent_found, found.child_found,
               found.parent_pooled, found.child_pooled,
               (enhanced - features).square().sum(1), features.square().sum(1))
    sums = torch.zeros(field.grid.num_levels, len(SUMS), dtype=torch.float64)
    for j, column in enumerate(columns):
        sums[:, j].index_add_(0, levels.cpu(), column.detach().double().cpu())
    return sums


def summarise(sums: Tensor) -> list[dict[str, Any]]:
    """Rows of the per-level table from summed columns [L, len(SUMS)]."""
    rows, last = [], sums.shape[0] - 1
    for level, values in enumerate(sums.tolist()):
        total = dict(zip(SUMS, values))
        seen = total["visible"]
        share = lambda key: total[key] / seen if seen else None  # noqa: E731
        mean = lambda key, over: total[key] / total[over] if total[over] else None  # noqa: E731
        rows.append({
            "level": level, "visible": int(seen),
            "parent_found": share("parent_found") if level > 0 else None,
            "child_found": share("child_found") if level < last else None,
            "parent_pooled": mean("parent_pooled", "parent_found"),
            "child_pooled": mean("child_pooled", "child_found"),
            "adjustment": (total["diff_sq"] / total["feat_sq"]) ** 0.5 if total["feat_sq"] > 0 else None,
        })
    return rows


def lookup_table(field, cameras: Iterable[Camera], step: int | None = None) -> list[dict[str, Any]]:
    """The per-level lookup table summed over ``cameras`` (LOD + frustum selection as in rendering)."""
    sums = torch.zeros(field.grid.num_levels, len(SUMS), dtype=torch.float64)
    for camera in cameras:
        sums += view_lookup_sums(field, camera, step)
    return summarise(sums)


def format_table(rows: list[dict[str, Any]]) -> str:
    """The table as aligned text (percent for shares, None as '-')."""
    def cell(value, fmt):
        return "-".rjust(int(fmt.split(".")[0])) if value is None else format(value, fmt)

    def percent(value, width):
        return "-".rjust(width + 1) if value is None else f"{100 * value:{width}.1f}%"

    lines = ["level  visible  parent found  child found  parent pooled  child pooled  |f^-f|/|f|"]
    for row in rows:
        lines.append(f"{row['level']:>5}  {row['visible']:>7}  {percent(row['parent_found'], 11)}"
                     f"  {percent(row['child_found'], 10)}"
                     f"  {cell(row['parent_pooled'], '13.2f')}  {cell(row['child_pooled'], '12.2f')}"
                     f"  {cell(row['adjustment'], '10.4f')}")
    return "\n".join(lines)


def flat_metrics(rows: list[dict[str, Any]]) -> dict[str, float | None]:
    """The table as flat scalars for eval.json: ``clca_l<level>_<column>`` (None where undefined)."""
    return {f"clca_l{row['level']}_{key}": row[key] for row in rows
            for key in ("visible", "parent_found", "child_found", "parent_pooled", "child_pooled", "adjustment")}
