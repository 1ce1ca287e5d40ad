"""``hico-export gaussians``: the neural Gaussians decoded for one view, as an Inria-layout 3DGS PLY."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from hico_plugin.engine.loading import LoadedRun
from hico_plugin.errors import HicoError
from hico_plugin.export.exporters.base import EXPORTERS, Exporter, output_path
from hico_plugin.export.gaussians import (
    facing_normals,
    gaussians_to_colmap,
    inria_vertices,
)
from hico_plugin.export.ply import write_ply


@EXPORTERS.register("gaussians")
@dataclass
class ExportGaussians(Exporter):
    """The neural Gaussians decoded for one camera (at evaluation LOD) as an Inria-layout 3DGS PLY."""

    camera_index: int = 0
    """Dataset view whose decoding is exported (the Gaussians are view-dependent)."""
    output: Path | None = None
    """PLY to write (default RUN/exports/gaussians_view<I>.ply)."""

    @torch.no_grad()
    def run(self, run: LoadedRun) -> Path:
        model, dataset = run.model, run.dataset
        if not 0 <= self.camera_index < len(dataset.cameras):
            raise HicoError(f"--camera-index: {self.camera_index} is out of range "
                            f"(the run has views 0..{len(dataset.cameras) - 1})")
        _, gaussians = model.render(dataset.cameras[self.camera_index], ("alpha",))
        camera = dataset.cameras[self.camera_index].to(gaussians.means.device)
        normals = facing_normals(gaussians.means, gaussians.quats, gaussians.scales, camera.center)
        normals = dataset.transform.directions_to_colmap(normals)
        means, quats, scales = gaussians_to_colmap(gaussians.means, gaussians.quats, gaussians.scales, dataset.transform)
        rows, dropped = inria_vertices(means, quats, scales, gaussians.opacities, gaussians.colors, normals)
        path = output_path(self.output, run, f"gaussians_view{self.camera_index}.ply")
        write_ply(path, rows)
        print(f"gaussians: wrote {dropped.kept} of {len(gaussians)} decoded for view {self.camera_index} to {path}; "
              f"dropped {dropped.dropped} (non-finite {dropped.non_finite}, zero quaternion {dropped.zero_quaternion}, "
              f"opacity < 1/255 {dropped.transparent})")
        return path
