"""Which anchors CLCA's contexts read (paper Eqs. 2-4): the integer structure, apart from the features.

``index = ContextIndex(grid, "trilinear")`` once per field; ``graph = index.view(levels, positions, visible_ids)``
per view. The relation depends on each anchor's level and cell: the index sorts all anchors' cell keys when they
change, and while no anchor has changed cell since, a view only filters it by visibility (evaluation, the viewer);
else a view builds its own anchors' relation. Pooling uses sparse CSR products whose transposes are kept for
backward: one pass over the edges each way instead of [E,d] copies.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from enum import Enum
from functools import cached_property

import torch
from torch import Tensor

from hico_plugin.field.octree import OctreeGrid

class ParentRule(str, Enum):
    """Which coarser anchors are an anchor's parents (``ContextConfig.parent_rule``); a str, so configs and the
    command line name it ``trilinear`` or ``paper``.

    trilinear: the 1-8 level-(l-1) grid points around a level-l anchor, with trilinear weights; the levels nest
    (densification keeps the tree) and an absent context is a learned vector. paper: Eqs. 3-4 literally, the one
    cell round((p - o) / v_{l-1}) of the drifted position, which need not nest; an empty lookup reads c_self."""

    trilinear = "trilinear"
    paper = "paper"

    @property
    def nests(self) -> bool:
        """Whether the parents are grid points of the level above (trilinear), not the drifted
        position's cell (paper): what the lookup, its relation's cache key, its fallback for an empty
        lookup and densification's kept tree depend on."""
        return self is ParentRule.trilinear


PARENT_RULES = tuple(rule.value for rule in ParentRule)
_CORNERS = [[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)]


def dense_cell_ids(keys: Tensor) -> tuple[Tensor, int]:
    """Dense ids of integer keys: keys [N,4] long -> (ids [N] long in [0, U), U), equal keys <-> equal
    ids. Keys are packed into one int64 by mixed radix over their range when that fits (one 1-D sort),
    else ``unique(dim=0)`` (a lexicographic sort)."""
    if keys.shape[0] == 0:
        return keys.new_zeros(0), 0
    low = keys.min(0).values
    spans = (keys.max(0).values - low + 1).tolist()
    if math.prod(spans) < (1 << 62):
        shifted = keys - low
        packed = shifted[:, 0]
        for axis in range(1, keys.shape[1]):
            packed = packed * spans[axis] + shifted[:, axis]
        unique, ids = torch.unique(packed, return_inverse=True)
    else:
        unique, ids = torch.unique(keys, dim=0, return_inverse=True)
    return ids, unique.shape[0]


def cell_keys(positions: Tensor, levels: Tensor, grid: OctreeGrid) -> Tensor:
    """[N,4] long (level, grid index): the cell each anchor occupies (positions [N,3], levels [N])."""
    return torch.cat([levels[:, None], grid.grid_index(positions, levels)], 1)


def parent_edges(levels: Tensor, positions: Tensor, grid: OctreeGrid, rule: ParentRule
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """Candidate parents of every anchor above level 0: (anchor [E] long, ascending; parent index [E,3]
    long at level - 1; weight [E]). levels [V] long, positions [V,3]. Weights of one anchor sum to 1.

    trilinear: anchors sit on grid points, so a level-l anchor with index k lies at k / b in level-(l-1)
    units; its parents are the 1, 2, 4 or 8 grid points around it with their trilinear weights.
    paper: the one cell ``round((p - o) / v_{l-1})`` of the (drifted) position, weight 1.
    """
    fine = (levels > 0).nonzero().squeeze(1)
    if not ParentRule(rule).nests:
        index = grid.grid_index(positions.detach()[fine], levels[fine] - 1)
        return fine, index, positions.new_ones(fine.shape[0])
    own = grid.grid_index(positions.detach()[fine], levels[fine])  # [F,3]
    base = torch.div(own, grid.fork, rounding_mode="floor")
    frac = (own - base * grid.fork).to(positions.dtype) / grid.fork  # [F,3] position of k/b in its cell
    axis = torch.stack([1.0 - frac, frac], 2)  # [F,3,2]: weight of the lower / upper point per axis
    weights = (axis[:, 0, :, None, None] * axis[:, 1, None, :, None] * axis[:, 2, None, None, :]).reshape(-1, 8)
    rows, corner = (weights > 0).nonzero(as_tuple=True)  # by anchor, then corner (x slowest)
    corners = torch.tensor(_CORNERS, device=levels.device)
    return fine[rows], base[rows] + corners[corner], weights[rows, corner]


def _csr(rows: Tensor, cols: Tensor, values: Tensor, shape: tuple[int, int]) -> Tensor:
    """CSR matrix from entries already sorted by row."""
    crow = torch.zeros(shape[0] + 1, dtype=torch.long, device=rows.device)
    crow[1:] = torch.bincount(rows, minlength=shape[0]).cumsum(0)
    with warnings.catch_warnings():  # torch flags all CSR support as "beta" once per process
        warnings.simplefilter("ignore", UserWarning)
        # Invariant checks follow torch's global switch (on in the tests, off by default: they cost a pass).
        return torch.sparse_csr_tensor(crow, cols, values, shape)


class _SparseMatmul(torch.autograd.Function):
    """matrix @ dense with the gradient matrix^T @ grad from a prebuilt transpose (no transpose, no
    sort in the backward pass). Gradient w.r.t. dense only: the weights are not trained."""

    @staticmethod
    def forward(ctx, matrix: Tensor, matrix_t: Tensor, dense: Tensor) -> Tensor:
        ctx.matrix_t = matrix_t
        return matrix @ dense

    @staticmethod
    def backward(ctx, grad: Tensor):
        return None, None, ctx.matrix_t @ grad


@dataclass
class WeightedSum:
    """out [rows,d] = sum over entries (row, col, value) of value * x[col], as CSR and its transpose."""

    matrix: Tensor
    transpose: Tensor

    def __call__(self, x: Tensor) -> Tensor:
        return _SparseMatmul.apply(self.matrix.to(x.dtype), self.transpose.to(x.dtype), x)


@dataclass
class ContextGraph:
    """The parent relation among one view's V visible anchors, whose cells get dense ids [0, K).

    cell [V] long: each anchor's own cell; count [K] long: visible anchors per cell.
    Edges, sorted by anchor: anchor [E] (visible index), edge_cell [E] (the candidate parent cell,
    holding >= 1 visible anchor), weight [E] (trilinear weight, 1 under the paper rule);
    by_cell [E] orders the edges by cell, members [V] orders the anchors by cell.
    """

    rule: ParentRule
    cell: Tensor
    count: Tensor
    anchor: Tensor
    edge_cell: Tensor
    weight: Tensor
    by_cell: Tensor
    members: Tensor

    @property
    def num_anchors(self) -> int:
        return self.cell.shape[0]

    @property
    def num_cells(self) -> int:
        return self.count.shape[0]

    @cached_property
    def parent_weight(self) -> Tensor:
        """[V]: total weight of an anchor's present parents (0 = no parent context)."""
        return self.weight.new_zeros(self.num_anchors).index_add(0, self.anchor, self.weight)

    @cached_property
    def child_weight(self) -> Tensor:
        """[K]: total weight of the finer anchors reading a cell (0 = no child context)."""
        return self.weight.new_zeros(self.num_cells).index_add(0, self.edge_cell, self.weight)

    def cell_mean(self) -> WeightedSum:
        """[K,d] <- [V,d]: mean feature of each cell's visible anchors."""
        share = 1.0 / self.count.clamp_min(1)[self.cell].to(self.weight.dtype)  # [V] 1 / its cell's count
        anchors = torch.arange(self.num_anchors, device=self.cell.device)
        shape = (self.num_cells, self.num_anchors)
        return WeightedSum(_csr(self.cell[self.members], self.members, share[self.members], shape),
                           _csr(anchors, self.cell, share, shape[::-1]))

    def of_cell(self) -> WeightedSum:
        """[V,d] <- [K,d]: each anchor reads its own cell's row. A product rather than index_select:
        index_select's backward is a scatter-add, several times slower on CPU than the transpose product."""
        ones = self.weight.new_ones(self.num_anchors)
        anchors = torch.arange(self.num_anchors, device=self.cell.device)
        shape = (self.num_anchors, self.num_cells)
        return WeightedSum(_csr(anchors, self.cell, ones, shape),
                           _csr(self.cell[self.members], self.members, ones, shape[::-1]))

    def parent_mean(self) -> WeightedSum:
        """[V,d] <- [K,d]: weighted mean over an anchor's parent cells (no parent: 0)."""
        values = self.weight / self.parent_weight.clamp_min(1e-12)[self.anchor]
        return self._edge_sum(values, anchors_are_rows=True)

    def child_mean(self) -> WeightedSum:
        """[K,d] <- [V,d]: weighted mean over the finer anchors that have the cell as a parent."""
        values = self.weight / self.child_weight.clamp_min(1e-12)[self.edge_cell]
        return self._edge_sum(values, anchors_are_rows=False)

    def _edge_sum(self, values: Tensor, anchors_are_rows: bool) -> WeightedSum:
        """The edges as a [V,K] (anchor rows) or [K,V] (cell rows) matrix, with its transpose."""
        order = self.by_cell
        by_anchor = _csr(self.anchor, self.edge_cell, values, (self.num_anchors, self.num_cells))
        by_cell = _csr(self.edge_cell[order], self.anchor[order], values[order], (self.num_cells, self.num_anchors))
        return WeightedSum(by_anchor, by_cell) if anchors_are_rows else WeightedSum(by_cell, by_anchor)


class ContextIndex:
    """The relation over all anchors, rebuilt only when an anchor's level or cell changed; ``view``
    restricts it to the visible ones. Holds no parameters and nothing worth saving."""

    def __init__(self, grid: OctreeGrid, rule: ParentRule | str):
        self.grid, self.rule = grid, ParentRule(rule)
        self._signature: Tensor | None = None

    def _cell_signature(self, levels: Tensor, positions: Tensor) -> Tensor:
        """[N, 4 or 7] long: what the relation is made from (level, own cell; paper: + parent cell)."""
        parts = [cell_keys(positions, levels, self.grid)]
        if not self.rule.nests:  # the parent cell follows the drifted position
            parts.append(self.grid.grid_index(positions, (levels - 1).clamp_min(0)))
        return torch.cat(parts, 1)

    def _build(self, levels: Tensor, positions: Tensor, signature: Tensor) -> None:
        num = levels.shape[0]
        anchor, parent_index, weight = parent_edges(levels, positions, self.grid, self.rule)
        parent_keys = torch.cat([levels[anchor, None] - 1, parent_index], 1)
        ids, num_cells = dense_cell_ids(torch.cat([signature[:, :4], parent_keys]))
        cell, edge_cell = ids[:num], ids[num:]
        occupied = torch.bincount(cell, minlength=num_cells)[edge_cell] > 0  # a cell no anchor holds is never read
        self._signature = signature
        self._cell, self._num_cells = cell, num_cells
        self._anchor, self._edge_cell, self._weight = anchor[occupied], edge_cell[occupied], weight[occupied]
        self._by_cell = torch.argsort(self._edge_cell, stable=True)
        self._members = torch.argsort(cell, stable=True)

    @torch.no_grad()
    def view(self, levels: Tensor, positions: Tensor, visible: Tensor) -> ContextGraph:
        """levels [N] long, positions [N,3] of all anchors; visible [V] long, ascending -> the graph of
        the visible anchors (their order)."""
        positions = positions.detach()
        if visible.shape[0] > 1 and bool((visible[1:] <= visible[:-1]).any()):
            raise ValueError("ContextIndex.view: visible ids must be ascending and unique")
        signature = self._cell_signature(levels, positions)
        same_anchors = self._signature is not None and torch.equal(signature[:, 0], self._signature[:, 0])
        # Densification appends grown anchors and drops pruned ones, so it changes the level column; were
        # that column ever unchanged by it, the drift path below would still be exact, only slower.
        if not same_anchors:  # first call, or densification changed the anchors
            self._build(levels, positions, signature)
        elif not torch.equal(signature, self._signature):
            # Some anchors drifted into another cell since the build. In training a few do nearly every
            # step (those sitting near a rounding boundary), so rebuilding over all anchors would cost
            # more than it saves: the view's own anchors get a relation of their own instead.
            local = ContextIndex(self.grid, self.rule)
            local._build(levels[visible], positions[visible], signature[visible])
            return local._view(torch.arange(visible.shape[0], device=visible.device), positions.dtype)
        return self._view(visible, positions.dtype)

    def _view(self, visible: Tensor, dtype: torch.dtype) -> ContextGraph:
        """The built relation restricted to ``visible`` [V] (ascending)."""
        device = self._cell.device
        local = torch.full((self._cell.shape[0],), -1, dtype=torch.long, device=device)
        local[visible] = torch.arange(visible.shape[0], device=device)
        # Renumber the cells the view's anchors hold 0..K-1 (order kept, so the cached orders by cell
        # stay sorted): the pooled tables then have at most V rows, not one per cell of the scene.
        held = torch.zeros(self._num_cells, dtype=torch.bool, device=device)
        held[self._cell[visible]] = True
        renumber = held.cumsum(0) - 1
        cell = renumber[self._cell[visible]]
        count = torch.bincount(cell, minlength=int(held.sum()))
        keep = (local[self._anchor] >= 0) & held[self._edge_cell]
        kept_at = keep.cumsum(0) - 1  # position of a kept edge among the kept ones (anchor order)
        by_cell = kept_at[self._by_cell[keep[self._by_cell]]]
        members = local[self._members]
        return ContextGraph(self.rule, cell, count, local[self._anchor[keep]], renumber[self._edge_cell[keep]],
                            self._weight[keep].to(dtype), by_cell, members[members >= 0])


def context_graph(levels: Tensor, positions: Tensor, grid: OctreeGrid, rule: ParentRule = ParentRule.trilinear
                  ) -> ContextGraph:
    """The graph of a set of anchors all counted as visible: levels [V] long, positions [V,3]."""
    return ContextIndex(grid, rule).view(levels, positions, torch.arange(levels.shape[0], device=levels.device))
