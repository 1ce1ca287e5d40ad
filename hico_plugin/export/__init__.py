"""Exports of a trained run: PLY files (baked or decoded Gaussians, anchors) and camera paths for videos.

The ``hico-export`` exporters are registered in ``export/exporters/`` (``EXPORTERS``); this package holds what
they and ``hico-render`` build on: ``write_ply`` / ``read_ply`` (binary little-endian, atomic), ``bake(model,
dataset, level_range=None, reference_view=None) -> BakedGaussians``, ``inria_vertices(...) -> (rows,
DroppedRows)``, ``anchor_vertices``, ``gaussians_to_colmap``, ``orbit_path`` / ``interpolate_path(cameras,
num_frames) -> Cameras``.
"""

from hico_plugin.export.bake import BakedGaussians, bake
from hico_plugin.export.camera_paths import interpolate_path, orbit_path
from hico_plugin.export.gaussians import (
    DroppedRows,
    anchor_vertices,
    facing_normals,
    gaussians_to_colmap,
    inria_vertices,
)
from hico_plugin.export.ply import read_ply, write_ply

__all__ = [
    "BakedGaussians",
    "DroppedRows",
    "bake",
    "anchor_vertices",
    "facing_normals",
    "gaussians_to_colmap",
    "inria_vertices",
    "interpolate_path",
    "orbit_path",
    "read_ply",
    "write_ply",
]
