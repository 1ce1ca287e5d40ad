"""Surface metrics of a mesh against ground-truth points (the MatrixCity / CityGaussianV2 protocol):
points sampled evenly over the mesh's area vs the ground truth, P / R / F1 at tau = 1.5 x the mean
ground-truth nearest-neighbour spacing, plus chamfer distance."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.mesh.mesh import TriangleMesh, read_ply
from hico_plugin.metrics.geometry import SurfaceMetrics, gt_spacing_threshold, surface_metrics


def sample_surface(mesh: TriangleMesh, count: int, seed: int = 0) -> np.ndarray:
    """[count, 3] points uniformly distributed over the mesh's area: a face drawn with probability
    proportional to its area, then a uniform barycentric point in it."""
    areas = mesh.face_areas()
    total = float(areas.sum()) if len(areas) else 0.0
    if not total > 0:
        raise HicoError(f"surface metrics: the mesh has no area to sample ({len(mesh.faces)} faces)")
    rng = np.random.default_rng(seed)
    faces = mesh.faces[rng.choice(len(areas), size=count, p=areas / total)]
    u, v = rng.random(count), rng.random(count)
    # Reflect the points of the unit square's upper half so (u, v) is uniform over the triangle.
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    a, b, c = (mesh.vertices[faces[:, k]] for k in range(3))
    return a + u[:, None] * (b - a) + v[:, None] * (c - a)


def evaluate_surface(mesh: TriangleMesh, gt_points: Tensor | np.ndarray, spacing_factor: float = 1.5,
                     num_samples: int | None = None, seed: int = 0) -> SurfaceMetrics:
    """Precision / recall / F1 / chamfer of ``mesh`` against ``gt_points`` ([M, 3], same frame).

    ``num_samples`` points are drawn over the mesh's area (default ``N_vertices + N_faces``, as
    CityGaussianV2); tau = ``spacing_factor`` x the mean ground-truth nearest-neighbour spacing.
    """
    gt = gt_points.detach().cpu().double().numpy() if isinstance(gt_points, Tensor) else np.asarray(gt_points)
    count = len(mesh.vertices) + len(mesh.faces) if num_samples is None else int(num_samples)
    if count < 1:
        raise HicoError(f"surface metrics: the mesh is empty ({len(mesh.vertices)} vertices, {len(mesh.faces)} faces)")
    samples = sample_surface(mesh, count, seed)
    tau = gt_spacing_threshold(gt, spacing_factor)
    return surface_metrics(torch.from_numpy(samples), gt, tau)


def surface_results(dataset: Any, mesh: str | Path | TriangleMesh) -> dict[str, float]:
    """hico-eval's (and hico-bench's) surface entries for ``mesh`` (COLMAP frame, as hico-export writes
    it: a TriangleMesh or its PLY file) against ``dataset.gt_surface_points``: ``surface_precision``,
    ``surface_recall``, ``surface_f1``, ``surface_chamfer`` and ``surface_tau`` (distances in COLMAP
    units). Empty when the dataset has no ground-truth surface or the file does not exist."""
    gt = dataset.gt_surface_points
    if gt is None or not (isinstance(mesh, TriangleMesh) or Path(mesh).is_file()):
        return {}
    metrics = evaluate_surface(mesh if isinstance(mesh, TriangleMesh) else read_ply(mesh),
                               dataset.transform.points_to_colmap(gt.double()))
    return {"surface_precision": metrics.precision, "surface_recall": metrics.recall, "surface_f1": metrics.f1,
            "surface_chamfer": metrics.chamfer, "surface_tau": metrics.threshold}
