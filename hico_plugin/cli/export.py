"""``hico-export --load-config RUN/config.yml {gaussians|anchors|mesh} [...]``: PLY files of a trained run.

    hico-export --load-config outputs/city-block/hico-gs-lite/config.yml gaussians --camera-index 3
    hico-export --load-config outputs/city-block/hico-gs-lite/config.yml anchors --output anchors.ply
    hico-export --load-config outputs/city-block/hico-gs-lite/config.yml mesh --depth-filter

Each target is a dataclass with ``run(run)``; adding one (e.g. ``mesh``) is one more entry in
``Target``. Run options may stand before or after the target name. Outputs are in COLMAP's frame.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Sequence, Union

import torch
import tyro

import hico_plugin.presets  # noqa: F401  (loads the config classes a config.yml may name)
from hico_plugin.cli import run_cli
from hico_plugin.engine import LoadedRun, load_run
from hico_plugin.errors import HicoError
from hico_plugin.export import (
    anchor_vertices,
    facing_normals,
    gaussians_to_colmap,
    inria_vertices,
    write_ply,
)
from hico_plugin.mesh import MeshExportConfig
from hico_plugin.visualization.visualize import level_colors


@dataclass
class ExportGaussians:
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
        path = self.output or run.run_dir / "exports" / f"gaussians_view{self.camera_index}.ply"
        write_ply(path, rows)
        print(f"gaussians: wrote {dropped.kept} of {len(gaussians)} decoded for view {self.camera_index} to {path}; "
              f"dropped {dropped.dropped} (non-finite {dropped.non_finite}, zero quaternion {dropped.zero_quaternion}, "
              f"opacity < 1/255 {dropped.transparent})")
        return path


@dataclass
class ExportAnchors:
    """The anchor points (position, octree level, feature; coloured by level) as a PLY point cloud."""

    output: Path | None = None
    """PLY to write (default RUN/exports/anchors.ply)."""

    @torch.no_grad()
    def run(self, run: LoadedRun) -> Path:
        field, transform = run.model.field, run.dataset.transform
        positions, levels = field.anchor_points()
        colors = level_colors(levels, field.grid.num_levels)
        rows = anchor_vertices(transform.points_to_colmap(positions), levels, field.anchor_features, colors)
        path = self.output or run.run_dir / "exports" / "anchors.ply"
        write_ply(path, rows)
        counts = torch.bincount(levels.cpu(), minlength=field.grid.num_levels).tolist()
        print(f"anchors: wrote {len(rows)} anchors (per level {counts}, "
              f"{field.anchor_features.shape[1]} features) to {path}")
        return path


Target = Union[
    Annotated[ExportGaussians, tyro.conf.subcommand("gaussians")],
    Annotated[ExportAnchors, tyro.conf.subcommand("anchors")],
    Annotated[MeshExportConfig, tyro.conf.subcommand("mesh")],
]


@dataclass
class ExportArgs:
    """Export a trained HiCo-GS run as PLY files (in the original COLMAP frame)."""

    target: Target
    load_config: Path
    """The run's config.yml (written by hico-train next to its checkpoints)."""
    checkpoint: Path | None = None
    """Checkpoint to export instead of the run's newest."""
    device: str | None = None
    """Device to decode on (default: the run's)."""


def parse(args: Sequence[str]) -> ExportArgs:
    # Cascade: run options may follow the target name; no "target:" prefix on the target names.
    return tyro.cli(ExportArgs, args=list(args), prog="hico-export",
                    config=(tyro.conf.CascadeSubcommandArgs, tyro.conf.OmitSubcommandPrefixes))


def main(args: ExportArgs) -> Path:
    run = load_run(args.load_config, args.checkpoint, args.device)
    return args.target.run(run)


def entrypoint(argv: Sequence[str] | None = None) -> None:
    run_cli(lambda: main(parse(sys.argv[1:] if argv is None else argv)))
