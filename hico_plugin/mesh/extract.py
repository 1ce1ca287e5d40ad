"""Mesh extraction from a trained model: render depth + RGB over the training views at full LOD, fuse
them in a TSDF, mesh, clean, and map the vertices to the original COLMAP frame.

Distances in ``MeshExportConfig`` are in COLMAP units (those of the output PLY); fusion runs in the
normalised frame the model works in, so they are multiplied by ``dataset.transform.scale`` there.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch

from hico_plugin.config import InstantiateConfig
from hico_plugin.errors import HicoError
from hico_plugin.mesh.mesh import TriangleMesh, clean_mesh, write_ply
from hico_plugin.mesh.tsdf import fuse_tsdf, multiview_depth_filter


@dataclass
class MeshExportConfig(InstantiateConfig):
    """TSDF-fuse rendered depth and colour of the training views into a PLY mesh (COLMAP frame)."""

    output: Path | None = None
    """PLY to write (default RUN/exports/mesh.ply)."""
    depth: Literal["plane", "expected"] = "plane"
    """Depth to fuse: plane depth (DNGC's unbiased depth, the default) or alpha-normalised expected depth."""
    voxel_size: float | None = None
    """TSDF voxel edge in COLMAP units; default the scene extent (twice the 99th percentile of the sparse
    points' distances from their mean, so it follows the scene, not the axes) / 512."""
    sdf_trunc: float | None = None
    """TSDF truncation distance in COLMAP units; default 4 x voxel size."""
    max_depth: float | None = None
    """Depths beyond this (COLMAP units) are ignored; default the far camera-to-point distance of the scene."""
    min_alpha: float = 0.5
    """Pixels whose accumulated opacity is below this carry no depth (their depth is unreliable)."""
    depth_filter: bool = False
    """Keep only pixels whose depth is confirmed by neighbour views (reprojection < 1 px, consistent depth)."""
    filter_neighbours: int = 8
    """Nearest views (by camera centre) the depth filter checks each view against."""
    filter_min_views: int = 2
    """The depth filter keeps a pixel when at least this many neighbour views agree."""
    min_weight: float = 1.0
    """Voxels observed by fewer views than this are left out of the surface."""
    min_component_triangles: int = 1000
    """Connected components with fewer triangles are removed (floaters)."""

    def setup(self, **kwargs: Any) -> MeshExportConfig:
        return self

    def export(self, model: Any, dataset: Any, run_dir: Path) -> Path:
        """Extract the mesh of ``model`` and write it (to ``output`` or RUN/exports/mesh.ply)."""
        mesh = extract_mesh(model, dataset, self)
        path = write_ply(self.output or Path(run_dir) / "exports" / "mesh.ply", mesh)
        print(f"mesh: wrote {len(mesh.vertices)} vertices, {len(mesh.faces)} triangles ({self.depth} depth, "
              f"{len(dataset.train_indices)} training views) to {path}")
        return path

    def run(self, run: Any) -> Path:
        """hico-export's target protocol: ``run`` has ``model``, ``dataset`` and ``run_dir``."""
        return self.export(run.model, run.dataset, run.run_dir)

    def run_config(self, config_path: str | Path, checkpoint: str | Path | None = None,
                   device: str | None = None) -> Path:
        """Load the run at ``config_path`` (RUN/config.yml) and export its mesh; returns the path."""
        from hico_plugin.engine import load_run

        run = load_run(config_path, checkpoint, device)
        return self.export(run.model, run.dataset, run.run_dir)


def scene_extent(dataset: Any) -> float:
    """Robust diameter (normalised units) of the sparse points (of the camera centres when there are too
    few points): twice the 99th percentile of their distances from their mean. Distances from a mean
    follow any rotation, shift and scale of the scene, so the voxel size derived from it does too; the
    diagonal of an axis-aligned box would change with the scene's heading (up to sqrt(2) for a flat
    city turned 45 degrees about its up axis)."""
    points = dataset.points if len(dataset.points) >= 10 else dataset.cameras.centers
    points = points.to(torch.float64)[:: max(1, len(points) // 1_000_000)]  # quantile's size limit
    radii = (points - points.mean(dim=0)).norm(dim=-1)
    extent = 2 * float(torch.quantile(radii, 0.99))
    if not extent > 0:
        raise HicoError("mesh: cannot derive a voxel size from the scene (its points span no volume); set --voxel-size")
    return extent


def default_voxel_size(dataset: Any) -> float:
    """The TSDF voxel edge (normalised units) when --voxel-size is not given: scene extent / 512."""
    return scene_extent(dataset) / 512


@torch.no_grad()
def render_depths(model: Any, dataset: Any, indices: list[int], depth: str
                  ) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
    """Per view: [H, W] camera z in the normalised frame (0 = none), [H, W, 3] uint8 RGB and [H, W]
    accumulated opacity, rendered at full LOD (step None)."""
    name = {"plane": "plane_depth", "expected": "depth"}[depth]
    depths, colors, alphas = [], [], []
    for i in indices:
        out, _ = model.render(dataset.cameras[i], {name, "rgb", "alpha"}, step=None)
        depths.append(getattr(out, name)[..., 0].float().cpu())
        alphas.append(out.alpha[..., 0].float().cpu())
        colors.append((out.rgb[..., :3].float().clamp(0, 1) * 255).round().to(torch.uint8).cpu())
    return depths, colors, alphas


def extract_mesh(model: Any, dataset: Any, config: MeshExportConfig) -> TriangleMesh:
    """The cleaned, coloured mesh of ``model`` over ``dataset``'s training views, in the COLMAP frame."""
    scale = float(dataset.transform.scale)
    indices = [int(i) for i in dataset.train_indices]
    if not indices:
        raise HicoError("mesh: the dataset has no training views to render")
    voxel = config.voxel_size * scale if config.voxel_size is not None else default_voxel_size(dataset)
    trunc = config.sdf_trunc * scale if config.sdf_trunc is not None else 4 * voxel
    max_depth = config.max_depth * scale if config.max_depth is not None else dataset.camera_distance_range()[1]
    depths, colors, alphas = render_depths(model, dataset, indices, config.depth)
    if not any(bool((alpha >= config.min_alpha).any()) for alpha in alphas):
        raise HicoError(f"mesh: no pixel of the {len(indices)} training views reaches opacity --min-alpha "
                        f"{config.min_alpha} (highest {max(float(a.max()) for a in alphas):.3g}); is the run trained?")
    depths = [torch.where(alpha >= config.min_alpha, d, torch.zeros_like(d)) for d, alpha in zip(depths, alphas)]
    if not any(bool(((d > 0) & (d <= max_depth)).any()) for d in depths):
        raise HicoError(f"mesh: no opaque pixel of the {len(indices)} training views has a {config.depth} depth in "
                        f"(0, --max-depth {max_depth / scale:.4g}] (COLMAP units); raise --max-depth")
    cameras = _subset(dataset.cameras, indices)
    if config.depth_filter:
        if len({tuple(d.shape) for d in depths}) > 1:
            raise HicoError("mesh: --depth-filter needs training views of one size; this dataset mixes sizes")
        keep = multiview_depth_filter(torch.stack(depths), cameras, config.filter_neighbours, config.filter_min_views)
        depths = [torch.where(k, d, torch.zeros_like(d)) for d, k in zip(depths, keep)]
    mesh = fuse_tsdf(depths, colors, cameras, voxel, trunc, max_depth, config.min_weight)
    mesh = clean_mesh(mesh, config.min_component_triangles)
    if len(mesh.faces) == 0:
        raise HicoError(f"mesh: fusion left no surface (voxel {voxel / scale:.4g}, max depth {max_depth / scale:.4g} "
                        f"COLMAP units, components under {config.min_component_triangles} triangles removed); "
                        "check --voxel-size / --max-depth / --min-component-triangles")
    vertices = dataset.transform.points_to_colmap(torch.from_numpy(mesh.vertices)).numpy()
    return TriangleMesh(vertices, mesh.faces, mesh.vertex_colors)


def _subset(cameras: Any, indices: list[int]) -> Any:
    ids = torch.tensor(indices, dtype=torch.long)
    return type(cameras)(cameras.viewmats[ids], cameras.Ks[ids], cameras.widths[ids], cameras.heights[ids])
