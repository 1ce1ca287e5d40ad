"""Train / test splits beyond every-Nth: an extrapolation split and sparse training views.

``extrapolation_split`` holds out the views at one end of the cameras' principal axis and leaves a gap
of unused views, so that every test camera is farther from the nearest training camera than any
training camera is from its nearest neighbour: the test views see the scene from where no training
view was. ``sparse_views`` keeps every Nth training view.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from hico_plugin.errors import HicoError


def nearest_distances(a: np.ndarray, b: np.ndarray, exclude_self: bool = False) -> np.ndarray:
    """Distance of each point of a [n,3] to its nearest point of b [m,3] (itself excluded): [n]."""
    dist = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    if exclude_self:
        np.fill_diagonal(dist, np.inf)
    return dist.min(1)


def extrapolation_split(centres: np.ndarray, test_every: int) -> tuple[Tensor, Tensor]:
    """(train, test) view indices: the 1/test_every views farthest along the first principal axis of
    the camera centres [N,3] are the test split; the training views nearest to them are dropped until
    every test view is farther from the training cameras than any training camera from its nearest
    other training camera (the dropped views are in neither split)."""
    num = centres.shape[0]
    if test_every < 2:
        raise HicoError(f"--test-every: the extrapolation split needs >= 2, got {test_every}")
    centred = centres - centres.mean(0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    order = np.argsort(-(centred @ axis), kind="stable")
    test = np.sort(order[: max(1, num // test_every)])
    train = [i for i in range(num) if i not in set(test.tolist())]
    while len(train) >= 2:
        points = centres[train]
        to_test = nearest_distances(points, centres[test])
        spacing = nearest_distances(points, points, exclude_self=True).max()
        if to_test.min() > spacing:
            return torch.tensor(train, dtype=torch.long), torch.from_numpy(test).long()
        train.pop(int(to_test.argmin()))  # the training view closest to the held-out side
    raise HicoError(f"--split extrapolate: {num} views leave no training views at a gap from the test views; "
                    "use more views or the interleaved split")


def sparse_views(train: Tensor, every: int) -> Tensor:
    """Every ``every``-th training view (1 = all of them)."""
    if every < 1:
        raise HicoError(f"--train-every: expected a whole number >= 1, got {every}")
    return train[::every]
