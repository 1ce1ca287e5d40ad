"""Geometry out: TSDF mesh extraction from a trained model and surface metrics against ground truth.

Public API::

    MeshExportConfig(...).run(loaded_run) -> Path              # hico-export target (.model/.dataset/.run_dir)
    MeshExportConfig(...).run_config(config_path, checkpoint=None, device=None) -> Path
    MeshExportConfig(...).export(model, dataset, run_dir) -> Path
    extract_mesh(model, dataset, config: MeshExportConfig) -> TriangleMesh         # COLMAP frame
    fuse_tsdf(depths, colors, cameras, voxel_size, sdf_trunc, max_depth, min_weight=1.0) -> TriangleMesh
    multiview_depth_filter(depths [C, H, W], cameras, ...) -> [C, H, W] bool
    clean_mesh(mesh, min_component_triangles) -> TriangleMesh
    evaluate_surface(mesh, gt_points [M, 3]) -> SurfaceMetrics                     # tau = 1.5 x GT spacing
    surface_results(dataset, mesh_path) -> dict   # hico-eval: surface_precision/recall/f1/chamfer/tau
    write_ply(path, mesh) / read_ply(path)
"""

from hico_plugin.mesh.evaluate import evaluate_surface, sample_surface, surface_results
from hico_plugin.mesh.extract import MeshExportConfig, extract_mesh
from hico_plugin.mesh.mesh import TriangleMesh, clean_mesh, read_ply, write_ply
from hico_plugin.mesh.tsdf import fuse_tsdf, multiview_depth_filter

__all__ = [
    "MeshExportConfig",
    "TriangleMesh",
    "clean_mesh",
    "evaluate_surface",
    "extract_mesh",
    "fuse_tsdf",
    "multiview_depth_filter",
    "read_ply",
    "sample_surface",
    "surface_results",
    "write_ply",
]
