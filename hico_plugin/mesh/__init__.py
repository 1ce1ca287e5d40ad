"""Geometry out: TSDF mesh extraction from a trained model and surface metrics against ground truth.

Public API: ``MeshExportConfig`` (``run(loaded_run)``, ``run_config(config_path, ...)``, ``export(model, dataset,
run_dir)`` -> Path; the hico-export target), ``extract_mesh`` (COLMAP frame), ``fuse_tsdf``,
``multiview_depth_filter``, ``clean_mesh``, ``evaluate_surface(mesh, gt_points [M, 3])`` (tau = 1.5 x GT spacing),
``surface_results`` (hico-eval's surface_precision/recall/f1/chamfer/tau), ``write_ply`` / ``read_ply``.
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
