"""Row gathers whose backward avoids torch's single-threaded scatter-add.

``index_select``'s backward is ``index_add_``, which torch runs single-threaded on a CPU since rows might repeat.
The decoder's gathers never repeat (``take_rows``), so each gradient row is written to its place in one pass over
the ascending rows (csrc/segment_cpu.cpp) instead of a zero fill and copies; ``repeat_rows`` (rows repeating in
runs: each kept child reads its anchor's position and scaling) sums each anchor's children in order from zero,
index_add_'s sum, the anchors split among threads (timings: benchmarks/RESULTS.md, "Figures behind the defaults").
"""

from __future__ import annotations

import math
from ctypes import c_int, c_int64, c_void_p
from pathlib import Path

import torch
from torch import Tensor

from hico_plugin.native import DTYPE_SUFFIXES, NativeKernel, pointer
from hico_plugin.row_sparse import row_sparse

# source, rows, count, row width (elements / bytes), output rows, output, threads -> status (0: done)
_ROWS = ([c_void_p, c_void_p, c_int64, c_int64, c_int64, c_void_p, c_int], c_int)
KERNEL = NativeKernel("hico_segment_cpu", Path(__file__).parent / "csrc" / "segment_cpu.cpp",
                      "row-sum kernel", "torch's index_add_",
                      functions={"hico_segment_sum_{dtype}": _ROWS, "hico_place_rows": _ROWS})


class _TakeRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, source: Tensor, rows: Tensor, sparse_grad: bool) -> Tensor:
        ctx.save_for_backward(rows)
        ctx.source_shape, ctx.sparse_grad = source.shape, sparse_grad
        return source.index_select(0, rows)

    @staticmethod
    def backward(ctx, grad: Tensor):
        (rows,) = ctx.saved_tensors
        if ctx.sparse_grad:
            return row_sparse(grad, rows, ctx.source_shape), None, None
        return _placed_rows(grad, rows, ctx.source_shape), None, None


def take_rows(source: Tensor, rows: Tensor, sparse_grad: bool = False) -> Tensor:
    """source [R, ...], rows [M] long with no value twice -> source[rows] [M, ...]: the values and
    gradient of ``source.index_select(0, rows)`` (a repeated row would get one of its gradients, not
    their sum). ``sparse_grad``: source's gradient is row-sparse (``hico_plugin.row_sparse``), holding
    only ``rows``, so the backward writes nothing of the size of ``source`` and the optimizer can
    update just those rows."""
    if not source.requires_grad:
        return source.index_select(0, rows)
    return _TakeRows.apply(source, rows, sparse_grad)


def _placed_rows(grad: Tensor, rows: Tensor, shape: torch.Size) -> Tensor:
    """zeros(shape).index_copy_(0, rows, grad), bit for bit; in one pass where rows strictly ascend and are wide
    enough. Rows under 16 bytes (1-3 float32s) stay with torch: one copy call a row costs what the zero fill saves
    (timings: benchmarks/RESULTS.md, "Figures behind the defaults")."""
    row_bytes = math.prod(shape[1:]) * grad.element_size()
    lib = KERNEL.get() if grad.device.type == "cpu" and row_bytes >= 16 else None
    if lib is not None:
        grad, rows = grad.contiguous(), rows.contiguous()
        out = grad.new_empty(shape)
        status = lib.hico_place_rows(pointer(grad), pointer(rows), rows.numel(), row_bytes, shape[0],
                                     pointer(out), torch.get_num_threads())
        if status == 0:
            return out
    return grad.new_zeros(shape).index_copy_(0, rows, grad)


def _row_sums(grad: Tensor, rows: Tensor, num_rows: int) -> Tensor:
    """zeros(num_rows, ...).index_add_(0, rows, grad), bit for bit; in parallel where rows ascend."""
    if grad.device.type == "cpu" and grad.dtype in DTYPE_SUFFIXES and KERNEL.available():
        grad, rows = grad.contiguous(), rows.contiguous()
        out = grad.new_empty((num_rows, *grad.shape[1:]))
        cols = math.prod(grad.shape[1:])
        status = KERNEL.function("hico_segment_sum_{dtype}", grad.dtype)(
            pointer(grad), pointer(rows), rows.numel(), cols, num_rows, pointer(out), torch.get_num_threads())
        if status == 0:
            return out
    return grad.new_zeros((num_rows, *grad.shape[1:])).index_add_(0, rows, grad)


class _RepeatRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, source: Tensor, rows: Tensor) -> Tensor:
        ctx.save_for_backward(rows)
        ctx.num_rows = source.shape[0]
        return source.index_select(0, rows)

    @staticmethod
    def backward(ctx, grad: Tensor):
        (rows,) = ctx.saved_tensors
        return _row_sums(grad, rows, ctx.num_rows), None


def repeat_rows(source: Tensor, rows: Tensor) -> Tensor:
    """source [R, ...], rows [M] long, ascending (values may repeat) -> source[rows] [M, ...]: the values and
    gradient of ``source.index_select(0, rows)`` bit for bit (rows out of order are summed by index_add_)."""
    if not source.requires_grad:
        return source.index_select(0, rows)
    return _RepeatRows.apply(source, rows)
