"""``hico-export anchors``: the anchor points (position, octree level, feature) as a PLY point cloud."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from hico_plugin.engine.loading import LoadedRun
from hico_plugin.export.exporters.base import EXPORTERS, Exporter, output_path
from hico_plugin.export.gaussians import anchor_vertices
from hico_plugin.export.ply import write_ply
from hico_plugin.visualization.visualize import level_colors


@EXPORTERS.register("anchors")
@dataclass
class ExportAnchors(Exporter):
    """The anchor points (position, octree level, feature; coloured by level) as a PLY point cloud."""

    output: Path | None = None
    """PLY to write (default RUN/exports/anchors.ply)."""

    @torch.no_grad()
    def run(self, run: LoadedRun) -> Path:
        field, transform = run.model.field, run.dataset.transform
        positions, levels = field.anchor_points()
        colors = level_colors(levels, field.grid.num_levels)
        rows = anchor_vertices(transform.points_to_colmap(positions), levels, field.anchor_features, colors)
        path = output_path(self.output, run, "anchors.ply")
        write_ply(path, rows)
        counts = torch.bincount(levels.cpu(), minlength=field.grid.num_levels).tolist()
        print(f"anchors: wrote {len(rows)} anchors (per level {counts}, "
              f"{field.anchor_features.shape[1]} features) to {path}")
        return path
