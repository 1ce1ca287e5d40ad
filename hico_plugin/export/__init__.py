"""Exports of a trained run: PLY files (baked or decoded Gaussians, anchors) and camera paths for videos.

The exporters ``hico-export`` runs are registered components in ``export/exporters/`` (``EXPORTERS``);
this package's top level holds what they and ``hico-render`` build on. Public API::

    write_ply(path, vertices) / read_ply(path)                     # binary little-endian PLY, atomic
    bake(model, dataset, level_range=None, reference_view=None) -> BakedGaussians  # the whole model
    inria_vertices(means, quats, scales, opacities, colors, normals=None) -> (rows, DroppedRows)
    anchor_vertices(positions, levels, features, colors=None) -> rows
    gaussians_to_colmap(means, quats, scales, transform) -> (means, quats, scales)
    orbit_path(cameras, num_frames) / interpolate_path(cameras, num_frames) -> Cameras
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
