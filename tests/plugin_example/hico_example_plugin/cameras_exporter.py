"""An exporter from outside: ``hico-export camera-poses`` writes the run's cameras as JSON.

Registering the dataclass is all it takes: ``hico-export`` lists it as a subcommand and its fields
(``--output``) as options.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from hico_plugin.engine.loading import LoadedRun
from hico_plugin.export.exporters.base import EXPORTERS, Exporter, output_path
from hico_plugin.storage import write_text_atomic


@EXPORTERS.register("camera-poses")
@dataclass
class ExportCameraPoses(Exporter):
    """Every view's world->camera matrix (COLMAP's frame, OpenCV axes), intrinsics and size, as JSON."""

    output: Path | None = None
    """JSON to write (default RUN/exports/camera_poses.json)."""

    def run(self, run: LoadedRun) -> Path:
        cameras, transform = run.dataset.cameras, run.dataset.transform
        viewmats = transform.viewmats_to_colmap(cameras.viewmats.double())  # [N, 4, 4]
        views = [{"index": i, "viewmat": viewmats[i].tolist(), "K": cameras.Ks[i].tolist(),
                  "width": int(cameras.widths[i]), "height": int(cameras.heights[i])} for i in range(len(cameras))]
        path = output_path(self.output, run, "camera_poses.json")
        write_text_atomic(path, json.dumps({"views": views}, indent=1) + "\n")
        print(f"camera-poses: wrote {len(views)} views to {path}")
        return path
