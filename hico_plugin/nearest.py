"""Exact k-nearest-neighbour search between point sets, with OpenCV's FLANN k-d tree.

OpenCV is a dependency already; SciPy's cKDTree would add its resident memory to every run. With unlimited checks
and ``eps = 0`` the ``FLANN_INDEX_KDTREE_SINGLE`` index prunes only branches that cannot hold a closer point, so
the search is exact (FLANN's ``KDTreeSingleIndex::searchLevel``) and deterministic. FLANN is float32: points are
centred on their bounding box's middle in float64 first, and ``_MARGIN`` extra candidates are re-measured in
float64 and sorted, so rounding near the k-th distance loses no true neighbour (benchmarks/RESULTS.md).
"""

from __future__ import annotations

import cv2
import numpy as np

_KDTREE_SINGLE = 4  # cvflann::FLANN_INDEX_KDTREE_SINGLE
_INDEX_PARAMS = {"algorithm": _KDTREE_SINGLE, "leaf_max_size": 10}
_SEARCH_PARAMS = {"checks": -1, "eps": 0.0}
_MARGIN = 2  # candidates beyond the k-th, re-measured in float64 (see above)
_CHUNK = 1 << 16  # queries per search: bounds the float64 re-measuring's [chunk, k] arrays


def _as_points(array: np.ndarray, name: str) -> np.ndarray:
    array = np.ascontiguousarray(array, dtype=np.float64)  # OpenCV reads C-ordered rows
    if array.ndim != 2 or array.shape[1] == 0:
        raise ValueError(f"knn: {name} must be an [N, D] array, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"knn: {name} contains NaN or inf coordinates")
    return array


def knn(points: np.ndarray, k: int, queries: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` points nearest to each query: (distances [Q, k'] float64 ascending, indices [Q, k'] int64).

    points: [N, D] (D = 3 for 3D points; any float or int dtype, any strides).
    queries: [Q, D], or None for the points themselves; then each point's ``k`` nearest *other* points
    (a duplicate of a point is another point, at distance 0).
    k' = min(k, N), or min(k, N - 1) for the points themselves: fewer columns when there are fewer points.
    Equal distances come out in the order the tree finds them (deterministic, not by index).
    """
    points = _as_points(points, "points")
    own = queries is None
    queries = points if own else _as_points(queries, "queries")
    if queries.shape[1] != points.shape[1]:
        raise ValueError(f"knn: queries are {queries.shape[1]}-D but points are {points.shape[1]}-D")
    width = max(0, min(k, points.shape[0] - own))
    distances = np.empty((queries.shape[0], width))
    indices = np.empty((queries.shape[0], width), dtype=np.int64)
    if width == 0 or queries.shape[0] == 0:
        return distances, indices
    centre = (points.min(axis=0) + points.max(axis=0)) / 2
    tree_points = (points - centre).astype(np.float32)  # referenced by the index while it lives
    index = cv2.flann_Index(tree_points, _INDEX_PARAMS)
    search = min(width + own + _MARGIN, points.shape[0])  # + own: the query's own entry is dropped below
    for start in range(0, queries.shape[0], _CHUNK):
        chunk = queries[start:start + _CHUNK]
        found, _ = index.knnSearch((chunk - centre).astype(np.float32), search, params=_SEARCH_PARAMS)
        found = found.astype(np.int64)
        squared = np.zeros(found.shape)
        for axis in range(points.shape[1]):  # per coordinate: 3x faster than a norm over [chunk, k, D]
            squared += (points[found, axis] - chunk[:, axis, None]) ** 2
        dist = np.sqrt(squared)
        if own:  # the query itself, when found (a duplicate may come first and push it out)
            dist[found == np.arange(start, start + chunk.shape[0])[:, None]] = np.inf
        order = np.argsort(dist, axis=1, kind="stable")[:, :width]
        distances[start:start + chunk.shape[0]] = np.take_along_axis(dist, order, axis=1)
        indices[start:start + chunk.shape[0]] = np.take_along_axis(found, order, axis=1)
    return distances, indices
