"""The compiled CLCA kernel against the torch reference (context_graph.ContextIndex + context_lookup's
sparse products): the same graph, the same triplet and gradients, float64 gradcheck, hard cases."""

import pytest
import torch

from hico_plugin.field import ContextIndex, OctreeGrid, context_triplet
from hico_plugin.field import context as context_module
from hico_plugin.field.context_fused import KERNEL, pooled_triplet, view_graph
from hico_plugin.field.context_graph import ParentRule
from helpers_native import require_kernel

GRID = OctreeGrid(origin=(0.5, -1.0, 2.0), cube_size=16.0, voxel_size=2.0, num_levels=4, fork=2,
                  d_std=10.0, init_level=2)


@pytest.fixture(autouse=True)
def _kernel():
    require_kernel(KERNEL)


def anchors(seed: int, num: int = 400, dim: int = 8, span: int = 5, drift: float = 1.2,
            dtype=torch.float32, origin_shift: float = 0.0):
    """Anchors on grid points of random levels in few cells; drift up to 0.6 voxel moves some across cells."""
    gen = torch.Generator().manual_seed(seed)
    levels = torch.randint(0, GRID.num_levels, (num,), generator=gen)
    index = (torch.rand(num, 3, generator=gen) * span * 2.0 ** levels[:, None].float()).long()
    positions = GRID.grid_position(index, levels, dtype)
    jitter = (torch.rand(num, 3, generator=gen, dtype=dtype) - 0.5) * drift
    positions = positions + jitter * (GRID.voxel_size / 2.0 ** levels.to(dtype))[:, None] + origin_shift
    return torch.randn(num, dim, generator=gen, dtype=dtype), levels, positions


def canonical(graph):
    """The graph with cells renamed by their first member anchor: equal for any cell numbering."""
    first = torch.full((graph.num_cells,), graph.num_anchors, dtype=torch.long)
    first = first.scatter_reduce(0, graph.cell, torch.arange(graph.num_anchors), "amin")
    return (first[graph.cell], graph.anchor, first[graph.edge_cell], graph.weight,
            graph.count[graph.cell], graph.cell[graph.members].diff() >= 0)


def reference_triplet(features, graph, missing, monkeypatch):
    with monkeypatch.context() as patch:
        patch.setattr(context_module, "fused_context", lambda device: False)
        return context_triplet(features, graph, "mean", missing)


@pytest.mark.parametrize("rule", ["trilinear", "paper"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_graph_equals_the_reference_graph(rule, seed):
    _, levels, positions = anchors(seed)
    visible = torch.sort(torch.randperm(400, generator=torch.Generator().manual_seed(seed))[:300]).values
    want = ContextIndex(GRID, rule).view(levels, positions, visible)
    got = view_graph(levels, positions, visible, GRID, ParentRule(rule))
    assert got.anchor.numel() > 20  # the case is not vacuous
    for a, b in zip(canonical(got), canonical(want)):
        assert torch.equal(a, b)
    order = got.edge_cell[got.by_cell]
    assert (order.diff() >= 0).all() and torch.equal(torch.sort(got.by_cell).values, torch.arange(got.anchor.numel()))


@pytest.mark.parametrize("rule", ["trilinear", "paper"])
@pytest.mark.parametrize("with_missing", [True, False])
@pytest.mark.parametrize("dim", [16, 32])  # 32, the features' width, has its own unrolled loops
def test_triplet_and_gradients_equal_the_reference(rule, with_missing, dim, monkeypatch):
    features, levels, positions = anchors(3, dim=dim)
    visible = torch.arange(0, 400, 2)
    graph = view_graph(levels, positions, visible, GRID, ParentRule(rule))
    ref_graph = ContextIndex(GRID, rule).view(levels, positions, visible)
    gen = torch.Generator().manual_seed(7)
    missing = torch.randn(2, dim, generator=gen) if with_missing else None
    outs, grads = [], []
    for g, fn in ((graph, lambda f, m: context_triplet(f, graph, "mean", m)),
                  (ref_graph, lambda f, m: reference_triplet(f, ref_graph, m, monkeypatch))):
        f = features[visible].clone().requires_grad_(True)
        m = missing.clone().requires_grad_(True) if with_missing else None
        out = fn(f, m)
        out.backward(torch.randn(out.shape, generator=torch.Generator().manual_seed(9)))
        outs.append(out.detach())
        grads.append((f.grad, m.grad if (with_missing and m.grad is not None) else torch.zeros(2, dim)))
    torch.testing.assert_close(outs[0], outs[1])
    torch.testing.assert_close(grads[0][0], grads[1][0])
    torch.testing.assert_close(grads[0][1], grads[1][1])
    absent = (graph.parent_weight <= 0).sum() + (graph.child_weight[graph.cell] <= 0).sum()
    assert 0 < absent < 2 * visible.numel()  # both found and absent contexts occur


@pytest.mark.parametrize("rule", ["trilinear", "paper"])
def test_gradcheck_float64(rule):
    features, levels, positions = anchors(4, num=60, dim=3, dtype=torch.float64)
    graph = view_graph(levels, positions, torch.arange(60), GRID, ParentRule(rule))
    f = features.clone().requires_grad_(True)
    m = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: pooled_triplet(a, graph, b), (f, m))


def test_hard_cases():
    """No anchors, only coarsest-level anchors (no parent edges), one anchor, huge coordinates (grid
    indices beyond 16 bits: the wide cell table)."""
    for num, max_level in ((0, 4), (30, 1), (1, 4)):
        gen = torch.Generator().manual_seed(num)
        levels = torch.randint(0, max_level, (num,), generator=gen)
        positions = GRID.grid_position(torch.randint(0, 8, (num, 3), generator=gen), levels)
        graph = view_graph(levels, positions, torch.arange(num), GRID, ParentRule.trilinear)
        missing = torch.randn(2, 4)
        out = pooled_triplet(torch.randn(num, 4), graph, missing)
        assert out.shape == (num, 3, 4) and torch.isfinite(out).all()
        assert torch.equal(out[:, 0], missing[0].expand(num, -1))  # no parent anywhere
    features, levels, positions = anchors(5, origin_shift=3e7, dtype=torch.float64)
    ref = ContextIndex(GRID, "trilinear").view(levels, positions, torch.arange(400))
    got = view_graph(levels, positions, torch.arange(400), GRID, ParentRule.trilinear)
    for a, b in zip(canonical(got), canonical(ref)):
        assert torch.equal(a, b)


def test_outputs_do_not_depend_on_the_thread_count():
    features, levels, positions = anchors(6, num=3000, dim=32, span=12)
    graph = view_graph(levels, positions, torch.arange(3000), GRID, ParentRule.trilinear)
    results = []
    before = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            f = features.clone().requires_grad_(True)
            out = pooled_triplet(f, graph, torch.ones(2, 32))
            out.backward(torch.ones_like(out))
            results.append((out, f.grad))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])


@pytest.mark.parametrize("shift", [8181.5, -8191.5, 8200.0])
def test_graph_at_the_packed_keys_edge(shift):
    """Grid indices close to the packed cell table's 16-bit range (up to 32,765 and down to -32,767 on the
    finest level) and just past it (32,839: the wide table) give the reference graph."""
    _, levels, positions = anchors(7, num=300, dtype=torch.float64, origin_shift=shift)
    keys = ContextIndex(GRID, "trilinear").view(levels, positions, torch.arange(300))
    got = view_graph(levels, positions, torch.arange(300), GRID, ParentRule.trilinear)
    for a, b in zip(canonical(got), canonical(keys)):
        assert torch.equal(a, b)


@pytest.mark.parametrize("fork", [3, 4])
def test_graph_with_other_forks(fork):
    """A fork that is not 2: another power of two (a shift) and one that is not (integer division)."""
    grid = OctreeGrid(origin=(0.5, -1.0, 2.0), cube_size=16.0, voxel_size=2.0, num_levels=3, fork=fork,
                      d_std=10.0, init_level=1)
    gen = torch.Generator().manual_seed(fork)
    levels = torch.randint(0, 3, (400,), generator=gen)
    index = (torch.rand(400, 3, generator=gen) * 4 * fork ** levels[:, None].float()).long()
    positions = grid.grid_position(index, levels, torch.float64)
    want = ContextIndex(grid, "trilinear").view(levels, positions, torch.arange(400))
    got = view_graph(levels, positions, torch.arange(400), grid, ParentRule.trilinear)
    assert got.anchor.numel() > 100
    for a, b in zip(canonical(got), canonical(want)):
        assert torch.equal(a, b)
