"""Row-sparse gradients: a sparse COO tensor of a dense parameter [R, ...] that names the rows a step
touched (``embedding(sparse=True)``'s layout), so that the backward and the optimizer cost the rows
touched, not the parameter (gsplat's ``sparse_grad``). The field writes them, Adam reads them."""

from __future__ import annotations

import torch
from torch import Tensor


def row_sparse(values: Tensor, rows: Tensor, shape: torch.Size | tuple[int, ...]) -> Tensor:
    """The sparse COO tensor of ``shape`` [R, ...] whose rows ``rows`` [M] long hold ``values`` [M, ...]
    and every other row zero (a row named twice holds the sum)."""
    return torch.sparse_coo_tensor(rows[None], values, shape)


def sparse_rows(grad: Tensor) -> tuple[Tensor, Tensor]:
    """(rows [M] long strictly ascending, values [M, ...]) of a row-sparse tensor, rows named twice
    summed. Autograd does not keep a gradient's coalesced mark, so one gather's gradient, whose rows
    already ascend, is read as it is instead of sorted again."""
    rows = grad._indices()[0]
    if grad.is_coalesced() or rows.numel() < 2 or bool((rows[1:] > rows[:-1]).all()):
        return rows, grad._values()
    grad = grad.coalesce()
    return grad.indices()[0], grad.values()
