"""CLCA's relation and pooling as one compiled CPU kernel: csrc/context_cpu.cpp, a torch extension built on first
use (``hico_plugin.native``). Where it is not built (no compiler, ``HICO_NO_FUSED=1``, tensors on a GPU)
context_graph.py's ``ContextIndex`` and context.py's sparse products, the reference, are used.

``view_graph`` returns ``ContextIndex.view``'s ``ContextGraph`` with cells numbered by first appearance (no output
depends on it); ``pooled_triplet`` is ``context_triplet``'s "mean" MLP input, absent contexts replaced. Nothing is
cached between steps: a view costs a few passes, and training anchors change cells every few steps anyway.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from hico_plugin.field.context_graph import ContextGraph, ParentRule, cell_keys, parent_edges
from hico_plugin.field.octree import OctreeGrid
from hico_plugin.native import NativeKernel

KERNEL = NativeKernel("hico_context_cpu", Path(__file__).parent / "csrc" / "context_cpu.cpp",
                      "fused CLCA kernel", "the torch context lookup (slower)", loader="torch")


def fused_context(device: torch.device) -> bool:
    """Whether CLCA's graph and pooling run in the compiled kernel for tensors on ``device``."""
    return device.type == "cpu" and KERNEL.available()


@torch.no_grad()
def view_graph(levels: Tensor, positions: Tensor, visible: Tensor, grid: OctreeGrid, rule: ParentRule
               ) -> ContextGraph:
    """levels [N] long, positions [N,3] of all anchors, visible [V] long ascending -> the view's graph
    (``ContextIndex.view``'s contract). CPU tensors; call ``fused_context`` first."""
    ext = KERNEL.get()
    levels, positions = levels[visible], positions.detach()[visible]
    keys = cell_keys(positions, levels, grid).contiguous()
    if rule.nests:
        anchor, parent_keys, weight = ext.trilinear_parents(keys, grid.fork, positions)
    else:
        anchor, parent_index, weight = parent_edges(levels, positions, grid, rule)
        parent_keys = torch.cat([levels[anchor, None] - 1, parent_index], 1)
    graph = ext.build_graph(keys, anchor.contiguous(), parent_keys.contiguous(), weight.contiguous())
    return ContextGraph(rule, *graph)


class _PooledTriplet(torch.autograd.Function):
    @staticmethod
    def forward(ctx, features: Tensor, missing: Tensor, fallback: int, *graph: Tensor) -> Tensor:
        graph = [t.to(features.dtype) if t.is_floating_point() else t for t in graph]
        ctx.graph, ctx.fallback = graph, fallback
        return KERNEL.get().lookup_forward(features.contiguous(), graph, missing.contiguous(), fallback)[0]

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        grad_features, grad_missing = KERNEL.get().lookup_backward(grad.contiguous(), ctx.graph, ctx.fallback)
        return grad_features, grad_missing, None, *[None] * len(ctx.graph)


def pooled_triplet(features: Tensor, graph: ContextGraph, missing: Tensor | None = None) -> Tensor:
    """features [V,d] -> [V,3,d] (c_parent, c_self, c_child) mean-pooled along ``graph``; where a context
    is absent, the row of missing [2,d] (parent, child; zeros if None) under the trilinear rule, c_self
    under the paper's. Differentiable w.r.t. features and missing. CPU tensors; call ``fused_context``
    first."""
    if missing is None or not graph.rule.nests:
        missing = features.new_zeros(2, features.shape[1])
    return _PooledTriplet.apply(features, missing, 0 if graph.rule.nests else 1, graph.cell, graph.count,
                                graph.anchor, graph.edge_cell, graph.weight, graph.by_cell, graph.members)
