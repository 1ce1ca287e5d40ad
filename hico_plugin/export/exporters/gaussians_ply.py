"""``hico-export gaussians``: the model's neural Gaussians as an Inria-layout 3DGS PLY in the dataset's
source frame: the whole model baked (export/bake.py) with a size / quality report next to it, or, with
``--camera-index``, what one view decodes."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from hico_plugin.data.transform import SceneTransform
from hico_plugin.engine.loading import LoadedRun
from hico_plugin.errors import HicoError
from hico_plugin.export.bake import bake
from hico_plugin.export.bake_report import file_figures, write_bake_report
from hico_plugin.export.exporters.base import EXPORTERS, Exporter, output_path
from hico_plugin.export.gaussians import (
    DroppedRows,
    facing_normals,
    gaussians_to_colmap,
    inria_vertices,
)
from hico_plugin.export.ply import write_ply
from hico_plugin.export.spz import read_spz, write_spz


@EXPORTERS.register("gaussians")
@dataclass
class ExportGaussians(Exporter):
    """The model's Gaussians as an Inria-layout 3DGS PLY: by default the whole model, every anchor
    decoded once for its canonical view, with a size / quality report (JSON) next to it."""

    camera_index: int | None = None
    """Export only what this dataset view decodes (its LOD selection, seen from it) instead of the
    whole model."""
    levels: tuple[int, int] | None = None
    """Whole model: keep only the anchors of these octree levels (inclusive), e.g. --levels 0 1."""
    appearance_view: int | None = None
    """Whole model: bake this training photo's appearance (its exposure) instead of the neutral one."""
    spz: bool = True
    """Whole model: also write the compressed SPZ web viewers open (same name, .spz), with its size and
    PSNR in the report."""
    output: Path | None = None
    """PLY to write (default RUN/exports/gaussians.ply, or gaussians_view<I>.ply with --camera-index)."""

    @torch.no_grad()
    def run(self, run: LoadedRun) -> Path:
        if self.camera_index is None:
            return self._whole_model(run)
        if self.levels is not None or self.appearance_view is not None:
            raise HicoError("--levels and --appearance-view choose what the whole-model export bakes; "
                            "--camera-index exports one view's decoding as it is")
        return self._one_view(run)

    def _whole_model(self, run: LoadedRun) -> Path:
        model, dataset = run.model, run.dataset
        baked = bake(model, dataset, self.levels, self.appearance_view)
        # each Gaussian's normal faces the canonical view its anchor was decoded for
        normals = facing_normals(baked.means, baked.quats, baked.scales, baked.eyes)
        path = output_path(self.output, run, "gaussians.ply")
        dropped, rows = _write(path, baked.means, baked.quats, baked.scales, baked.opacities, baked.colors, normals,
                               dataset.transform)
        levels = self.levels or (0, model.field.grid.num_levels - 1)
        in_levels = (model.field.levels >= levels[0]) & (model.field.levels <= levels[1])
        appearance = "neutral" if self.appearance_view is None else f"training photo {self.appearance_view}"
        settings = {"num_anchors": int(in_levels.sum()), "levels": list(levels), "appearance": appearance}
        if self.spz:
            settings["spz"] = file_figures(write_spz(path.with_suffix(".spz"), rows), read_spz, model, dataset)
        report, report_path = write_bake_report(path, dropped.kept, baked, model, dataset, settings)
        print(f"gaussians: wrote {dropped.kept} of {len(baked)} baked from {settings['num_anchors']} anchors "
              f"(levels {levels[0]}..{levels[1]}, {appearance} appearance) to {path}; {_dropped(dropped)}")
        print(f"report: {report['file_bytes'] / 1e6:.2f} MB, {dropped.kept:,} Gaussians; "
              f"{_psnr_line(report)} -> {report_path}")
        if self.spz:
            spz = report["spz"]
            psnr = "" if spz["psnr"] is None else f", test-view PSNR {spz['psnr']:.2f} dB"
            print(f"spz: {spz['file_bytes'] / 1e6:.2f} MB ({report['file_bytes'] / spz['file_bytes']:.1f}x smaller)"
                  f"{psnr} -> {path.with_suffix('.spz')}")
        return path

    def _one_view(self, run: LoadedRun) -> Path:
        model, dataset = run.model, run.dataset
        if not 0 <= self.camera_index < len(dataset.cameras):
            raise HicoError(f"--camera-index: {self.camera_index} is out of range "
                            f"(the run has views 0..{len(dataset.cameras) - 1})")
        _, gaussians = model.render(dataset.cameras[self.camera_index], ("alpha",))
        camera = dataset.cameras[self.camera_index].to(gaussians.means.device)
        normals = facing_normals(gaussians.means, gaussians.quats, gaussians.scales, camera.center)
        path = output_path(self.output, run, f"gaussians_view{self.camera_index}.ply")
        dropped, _ = _write(path, gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                            gaussians.colors, normals, dataset.transform)
        print(f"gaussians: wrote {dropped.kept} of {len(gaussians)} decoded for view {self.camera_index} to {path}; "
              f"{_dropped(dropped)}")
        return path


def _write(path: Path, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
           normals: Tensor, transform: SceneTransform) -> tuple[DroppedRows, np.ndarray]:
    """Write Gaussians of the training frame ([N, ·] as ``inria_vertices`` takes them) as PLY rows in
    the dataset's source frame; returns what was dropped and the rows."""
    normals = transform.directions_to_colmap(normals)
    means, quats, scales = gaussians_to_colmap(means, quats, scales, transform)
    rows, dropped = inria_vertices(means, quats, scales, opacities, colors, normals)
    write_ply(path, rows)
    return dropped, rows


def _dropped(dropped: DroppedRows) -> str:
    return (f"dropped {dropped.dropped} (non-finite {dropped.non_finite}, zero quaternion "
            f"{dropped.zero_quaternion}, opacity < 1/255 {dropped.transparent})")


def _psnr_line(report: dict) -> str:
    if report["psnr_model"] is None:
        return "no test views to measure PSNR on"
    return (f"test views ({report['test_views']}): PSNR model {report['psnr_model']:.2f} dB, baked "
            f"{report['psnr_baked']:.2f} dB, baked vs model {report['psnr_baked_vs_model']:.2f} dB")
