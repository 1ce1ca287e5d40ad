"""Data-parallel training over torch.distributed, started by ``torchrun`` (gloo on CPU, nccl on GPU).

Every rank holds the whole model. The global batch (``world_size x`` per-worker batch) is drawn
identically on every rank and split, each rank renders its own views, and gradients are averaged.
Densification stays identical everywhere because the model reduces its statistics with
``all_reduce_sum_`` / ``all_reduce_mean_`` and then decides on identical numbers. Only rank 0 writes
files and runs callbacks (progress bar, logs, viewer). Every helper is a no-op on a single process.
"""

from __future__ import annotations

import datetime
import os
from typing import Any, Iterable

import torch
import torch.distributed as dist
from torch import Tensor, nn

from hico_plugin.errors import HicoError
from hico_plugin.row_sparse import sparse_rows


def is_distributed() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def get_rank() -> int:
    return dist.get_rank() if is_distributed() else 0


def get_world_size() -> int:
    return dist.get_world_size() if is_distributed() else 1


def is_main_process() -> bool:
    return get_rank() == 0


def launched_by_torchrun() -> bool:
    """True when torchrun's environment asks for more than one worker."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def init_distributed(device: torch.device, timeout_minutes: float = 30.0) -> bool:
    """Join the process group described by torchrun's env vars (RANK, WORLD_SIZE, MASTER_ADDR/PORT).

    Returns True when running distributed. Uses nccl for CUDA devices and gloo otherwise.
    """
    if is_distributed():
        return True
    if not launched_by_torchrun():
        return False
    backend = "nccl" if device.type == "cuda" else "gloo"
    dist.init_process_group(backend=backend, timeout=datetime.timedelta(minutes=timeout_minutes))
    return True


def resolve_device(name: str) -> torch.device:
    """The device a config names: 'auto' (CUDA when available, else CPU), 'cpu', 'cuda' or 'cuda:N'."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise HicoError(f"config.device: '{name}' is not a device (expected auto, cpu, cuda or cuda:N)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise HicoError(f"config.device: '{name}' asked for but CUDA is not available")
    return device


def local_device(device: torch.device) -> torch.device:
    """The device of this worker: ``cuda:LOCAL_RANK`` under torchrun on GPU, else ``device``."""
    if device.type == "cuda" and device.index is None and launched_by_torchrun():
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return device


def all_reduce_sum_(tensor: Tensor) -> Tensor:
    """Sum ``tensor`` over ranks in place (no-op on one process); returns it."""
    if is_distributed():
        dist.all_reduce(tensor, op=dist.ReduceOp.SUM)
    return tensor


def all_reduce_mean_(tensor: Tensor) -> Tensor:
    """Average ``tensor`` over ranks in place (no-op on one process); returns it."""
    if is_distributed():
        dist.all_reduce(tensor, op=dist.ReduceOp.SUM)
        tensor.div_(dist.get_world_size())
    return tensor


def average_gradients_(params: Iterable[nn.Parameter]) -> None:
    """Average the gradients of ``params`` over ranks with one flat all-reduce.

    A missing gradient counts as zero, so a rank whose views saw none of a parameter still joins.
    """
    if not is_distributed():
        return
    params = [p for p in params if p.requires_grad]
    if not params:
        return
    # A parameter with a row-sparse gradient on any rank keeps one: its rows become those any rank
    # touched (a row counts as touched by its presence, whatever its value), as one process would name
    # the rows of all the views of the global batch.
    sparse = torch.tensor([p.grad is not None and p.grad.is_sparse for p in params], dtype=torch.float32)
    all_reduce_sum_(sparse)
    row_sparse = [bool(flag > 0) for flag in sparse]
    parts = []
    for p, rows in zip(params, row_sparse):
        grad = torch.zeros_like(p) if p.grad is None else p.grad.to_dense() if p.grad.is_sparse else p.grad
        parts.append(grad.reshape(-1))
        if rows:
            touched = torch.zeros(p.shape[0], dtype=p.dtype, device=p.device)
            if p.grad is not None and p.grad.is_sparse:
                touched[sparse_rows(p.grad)[0]] = 1
            parts.append(touched)
    flat = torch.cat(parts)
    all_reduce_sum_(flat)
    offset = 0
    for p, rows in zip(params, row_sparse):
        size = p.numel()
        grad = flat[offset : offset + size].view_as(p) / get_world_size()
        offset += size
        if rows:
            touched = flat[offset : offset + p.shape[0]].nonzero().squeeze(1)
            offset += p.shape[0]
            p.grad = torch.sparse_coo_tensor(touched[None], grad[touched], p.shape, is_coalesced=True)
        else:
            p.grad = grad


def broadcast_module_(module: nn.Module) -> None:
    """Copy rank 0's parameters and buffers to every rank (start of training)."""
    if not is_distributed():
        return
    with torch.no_grad():
        for tensor in list(module.parameters()) + list(module.buffers()):
            dist.broadcast(tensor.data, src=0)


def gather_objects(obj: Any) -> list[Any]:
    """``[obj of rank 0, obj of rank 1, ...]`` on every rank (``[obj]`` on one process)."""
    if not is_distributed():
        return [obj]
    gathered: list[Any] = [None] * dist.get_world_size()
    dist.all_gather_object(gathered, obj)
    return gathered


def broadcast_object(obj: Any) -> Any:
    """Rank 0's ``obj`` on every rank."""
    if not is_distributed():
        return obj
    holder = [obj]
    dist.broadcast_object_list(holder, src=0)
    return holder[0]


def barrier() -> None:
    if is_distributed():
        dist.barrier()


def shutdown(wait_for_peers: bool = True) -> None:
    """Leave the process group before the process exits; with ``wait_for_peers`` (a run that ended normally) every
    rank first meets the others at a barrier (after a failure a peer may never arrive).

    The barrier narrows a shutdown race (pytorch/pytorch#179291): a gloo worker that drops the last reference to a
    finished work's tensors takes the GIL, which during interpreter finalization aborts the process (SIGABRT,
    "terminate called without an active exception"). Ending on a barrier makes the last work one that holds no
    tensors and gives earlier ones a round trip to finish; Python cannot close the race."""
    if dist.is_available() and dist.is_initialized():
        if wait_for_peers and dist.get_world_size() > 1:
            dist.barrier()
        dist.destroy_process_group()
