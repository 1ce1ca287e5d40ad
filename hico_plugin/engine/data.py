"""Training batches: views drawn without replacement per epoch, a pure function of (seed, step).

The sample stream is the concatenation of one seeded permutation of the training views per epoch;
step ``s`` with a global batch of ``G`` views takes samples ``[s*G, (s+1)*G)``. Being a function of the
step, it needs no state to resume and is identical on every rank (each rank then takes its slice).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
from torch import Tensor

from hico_plugin.engine.protocol import TrainBatch, TrainDataset
from hico_plugin.errors import HicoError

# Ground truth the engine passes on when the dataset offers it: batch key -> dataset method.
_OPTIONAL_GT = {"depth": "gt_depth", "normal": "gt_normal", "mask": "mask"}


def epoch_permutation(num_views: int, seed: int, epoch: int) -> Tensor:
    """[num_views] long: the order of the training views in ``epoch``."""
    generator = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    return torch.randperm(num_views, generator=generator)


def batch_positions(num_views: int, global_batch: int, seed: int, step: int) -> Tensor:
    """[global_batch] long: positions in the training split of the views of ``step``."""
    if num_views <= 0:
        raise HicoError("dataset: the training split is empty")
    samples = torch.arange(step * global_batch, (step + 1) * global_batch)
    epochs = samples // num_views
    positions = torch.empty_like(samples)
    for epoch in torch.unique(epochs).tolist():  # at most two epochs per batch unless batch > views
        in_epoch = epochs == epoch
        positions[in_epoch] = epoch_permutation(num_views, seed, epoch)[samples[in_epoch] % num_views]
    return positions


def rank_slice(positions: Tensor, rank: int, world_size: int) -> Tensor:
    """This rank's share of the global batch (contiguous, equal sizes)."""
    per_rank = positions.numel() // world_size
    return positions[rank * per_rank : (rank + 1) * per_rank]


def as_float_image(image, where: str) -> Tensor:
    """uint8 (or float in [0, 1]) [H, W, 3] -> float32 [H, W, 3] in [0, 1]."""
    tensor = torch.as_tensor(np.asarray(image)) if not isinstance(image, Tensor) else image
    if tensor.ndim != 3 or tensor.shape[-1] != 3:
        raise HicoError(f"{where}: expected an [H, W, 3] image, got shape {tuple(tensor.shape)}")
    if tensor.dtype == torch.uint8:
        return tensor.to(torch.float32) / 255.0
    return tensor.to(torch.float32)


def load_view(dataset: TrainDataset, index: int,
              gt_keys: Iterable[str] | None = None) -> tuple[Tensor, dict[str, Tensor]]:
    """Image [H, W, 3] float in [0, 1] and the ground truth the dataset has for view ``index``
    (of the keys ``gt_keys``; None: every kind)."""
    image = as_float_image(dataset.image(index), f"dataset image {index}")
    gt = {}
    keys = None if gt_keys is None else set(gt_keys)
    wanted = {k: v for k, v in _OPTIONAL_GT.items() if keys is None or k in keys}
    for key, method in wanted.items():
        getter = getattr(dataset, method, None)
        value = getter(index) if getter is not None else None
        if value is not None:
            gt[key] = torch.as_tensor(np.asarray(value) if not isinstance(value, Tensor) else value).float()
    return image, gt


def make_batch(dataset: TrainDataset, indices: list[int], device: torch.device,
               gt_keys: Iterable[str] | None = None) -> TrainBatch:
    """Load the views ``indices`` (dataset indices) into a TrainBatch on ``device``, with the ground
    truth of ``gt_keys`` (None: every kind the dataset has)."""
    cameras = [dataset.cameras[i].to(device) for i in indices]
    views = [load_view(dataset, i, gt_keys) for i in indices]
    sizes = {tuple(image.shape) for image, _ in views}
    if len(sizes) > 1:
        raise HicoError(
            f"dataset: a batch mixes image sizes {sorted(sizes)}; use --batch-size 1 for such datasets"
        )
    images = torch.stack([image for image, _ in views]).to(device)
    common = set.intersection(*(set(gt) for _, gt in views)) if views else set()
    gt = {key: torch.stack([v[1][key] for v in views]).to(device) for key in sorted(common)}
    return TrainBatch(cameras=cameras, images=images, indices=torch.tensor(indices, dtype=torch.long, device=device), gt=gt)


def rank_batch(dataset: TrainDataset, train_indices: list[int], batch_size: int, seed: int, step: int,
               rank: int, world_size: int, device: torch.device, gt_keys: Iterable[str] | None = None) -> TrainBatch:
    """This rank's ``batch_size`` views of ``step`` (``train_indices``: the dataset indices of the
    training split), loaded on ``device`` with the ground truth of ``gt_keys``."""
    positions = batch_positions(len(train_indices), batch_size * world_size, seed, step)
    mine = rank_slice(positions, rank, world_size).tolist()
    return make_batch(dataset, [train_indices[p] for p in mine], device, gt_keys)
