"""CLCA: vectorised contexts vs a slow per-anchor loop, fallbacks, parameter count, identity at init."""

import itertools
import math

import pytest
import torch

from hico_plugin.errors import HicoError
from hico_plugin.field import (
    CONTEXT_AGGREGATORS, ContextConfig, ContextIndex, OctreeGrid, context_graph, context_lookup, context_triplet,
    dense_cell_ids)
from hico_plugin.field.octree import voxelize

@pytest.fixture(autouse=True)
def _check_sparse_invariants():
    """The sparse products' matrices must be valid CSR (sorted, in range): checked here, not in training."""
    with torch.sparse.check_sparse_tensor_invariants():
        yield


GRID = OctreeGrid(origin=(0.5, -1.0, 2.0), cube_size=16.0, voxel_size=2.0, num_levels=4, fork=2,
                  d_std=10.0, init_level=2)


def random_visible_anchors(seed: int, num: int = 300, dim: int = 8, span: int = 6):
    """Anchors on grid points of random levels, few cells (so cells are shared), small drift."""
    gen = torch.Generator().manual_seed(seed)
    levels = torch.randint(0, GRID.num_levels, (num,), generator=gen)
    # Coarse cells cover the same region as fine ones: index range grows with the level.
    index = (torch.rand(num, 3, generator=gen) * span * 2.0 ** levels[:, None].float()).long()
    positions = GRID.grid_position(index, levels)
    drift = (torch.rand(num, 3, generator=gen) - 0.5) * 0.4  # < half a voxel: own cell unchanged
    positions = positions + drift * (GRID.voxel_size / 2.0 ** levels.float())[:, None]
    features = torch.randn(num, dim, generator=gen)
    return features, levels, positions


def lookup(features, levels, positions, rule="trilinear", reduce="mean"):
    """context_lookup with every anchor counted as visible."""
    return context_lookup(features, context_graph(levels, positions, GRID, rule), reduce)


def enhance(module, features, levels, positions):
    """The aggregator on anchors all counted as visible, through its own (cached) graph."""
    return module(features, module.graph(levels, positions, torch.arange(levels.shape[0]), GRID))


def candidate_parents(index, level, rule, position):
    """The definition for one anchor: [(parent index tuple, weight)] at level - 1."""
    if level == 0:
        return []
    if rule == "paper":  # the paper's round((p - o) / v_{l-1})
        origin = torch.tensor(GRID.origin)
        cell = torch.round((position - origin) / (GRID.voxel_size / 2.0 ** (level - 1))).long()
        return [(tuple(cell.tolist()), 1.0)]
    out = []
    for corner in itertools.product((0, 1), repeat=3):
        parent, weight = [], 1.0
        for axis in range(3):
            half = index[axis] / 2  # the anchor in level-(l-1) units
            low = math.floor(half)
            parent.append(low + corner[axis])
            weight *= (half - low) if corner[axis] else 1.0 - (half - low)
        if weight > 0:
            out.append((tuple(parent), weight))
    return out


def slow_lookup(features, levels, positions, rule, reduce):
    """Eqs. 2-4 one anchor at a time: (parent, self, child, parent_found, child_found)."""
    origin = torch.tensor(GRID.origin)
    levels = levels.tolist()
    own = [tuple(torch.round((positions[i] - origin) / (GRID.voxel_size / 2.0 ** levels[i])).long().tolist())
           for i in range(len(levels))]
    parents = [candidate_parents(own[i], levels[i], rule, positions[i]) for i in range(len(levels))]

    def cell_members(level, cell):
        return [j for j in range(len(levels)) if levels[j] == level and own[j] == cell]

    def pool(weighted):  # [(feature, weight)]
        if reduce == "amax":
            return torch.stack([f for f, _ in weighted]).amax(0)
        return sum(w * f for f, w in weighted) / sum(w for _, w in weighted)

    out = []
    for i, level in enumerate(levels):
        c_self = pool([(features[j], 1.0) for j in cell_members(level, own[i])])
        parent_terms = []
        for cell, weight in parents[i]:
            members = cell_members(level - 1, cell)
            if members:
                cell_pool = pool([(features[j], 1.0) for j in members])
                parent_terms += ([(features[j], weight) for j in members] if reduce == "amax"
                                 else [(cell_pool, weight)])
        child_terms = [(features[j], w) for j in range(len(levels)) if levels[j] == level + 1
                       for cell, w in parents[j] if cell == own[i]]
        zero = torch.zeros_like(features[i])
        fallback = c_self if rule == "paper" else zero
        out.append((pool(parent_terms) if parent_terms else fallback, c_self,
                    pool(child_terms) if child_terms else fallback, bool(parent_terms), bool(child_terms)))
    parent, c_self, child, pf, cf = zip(*out)
    return torch.stack(parent), torch.stack(c_self), torch.stack(child), torch.tensor(pf), torch.tensor(cf)


@pytest.mark.parametrize("rule", ["trilinear", "paper"])
@pytest.mark.parametrize("reduce", ["mean", "amax"])
def test_lookup_matches_slow_loop(rule, reduce):
    for seed in range(3):
        features, levels, positions = random_visible_anchors(seed, num=100 if seed else 200)
        fast = lookup(features, levels, positions, rule, reduce)
        slow = slow_lookup(features, levels, positions, rule, reduce)
        for name, a, b in zip(("parent", "self", "child", "parent_found", "child_found"),
                              (fast.parent, fast.own, fast.child, fast.parent_found, fast.child_found), slow):
            torch.testing.assert_close(a, b, msg=f"{name} differs (seed {seed})")


def test_paper_rule_ties_and_trilinear_weights():
    # Level-1 anchor at odd index 3 lies halfway between level-0 points 1 and 2: the paper's round(1.5)
    # picks 2 (half to even); trilinear averages both with weight 1/2.
    levels = torch.tensor([1, 0, 0])
    index = torch.tensor([[3, 0, 0], [1, 0, 0], [2, 0, 0]])
    positions = GRID.grid_position(index, levels)
    features = torch.tensor([[0.0], [10.0], [20.0]])
    assert lookup(features, levels, positions, "paper").parent[0].item() == 20.0
    trilinear = lookup(features, levels, positions, "trilinear")
    assert trilinear.parent[0].item() == 15.0 and trilinear.parent_pooled[0].item() == 2
    # Both level-0 anchors see the level-1 anchor as a child (weight 1/2 each, one anchor pooled).
    assert trilinear.child[1:, 0].tolist() == [0.0, 0.0] and trilinear.child_found[1:].all()
    assert trilinear.child_pooled.tolist() == [0, 1, 1]


def test_absent_context_is_the_learned_missing_vector_not_self():
    # a: level 0 alone, no children; b: level 2 with no visible parent candidate.
    levels = torch.tensor([0, 2])
    positions = GRID.grid_position(torch.tensor([[7, 7, 7], [1, 1, 1]]), levels)
    features = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    missing = torch.tensor([[-1.0, -1.0], [-2.0, -2.0]])
    triplet = context_triplet(features, context_graph(levels, positions, GRID, "trilinear"), missing=missing)
    assert torch.equal(triplet[:, 0], missing[0].expand(2, -1)) and torch.equal(triplet[:, 2], missing[1].expand(2, -1))
    assert torch.equal(triplet[:, 1], features)
    paper = context_triplet(features, context_graph(levels, positions, GRID, "paper"), missing=missing)
    assert torch.equal(paper[:, 0], features) and torch.equal(paper[:, 2], features)  # the paper's fallback


def test_built_levels_nest_under_trilinear_but_not_under_the_paper_rule():
    """Every anchor voxelize() makes above level 0 finds a parent among its trilinear candidates."""
    gen = torch.Generator().manual_seed(0)
    points = torch.rand(3000, 3, generator=gen) * torch.tensor([10.0, 10.0, 0.5]) + 0.3  # a noisy slab
    positions, levels = voxelize(points, GRID)
    features = torch.randn(positions.shape[0], 4, generator=gen)
    trilinear = lookup(features, levels, positions, "trilinear")
    paper = lookup(features, levels, positions, "paper")
    fine = levels > 0
    assert trilinear.parent_found[fine].all()
    assert paper.parent_found[fine].float().mean() < 0.9  # the literal rule misses many parents
    # A child is found by the coarser anchor for every finer one: each child has >= 1 parent.
    assert int(trilinear.child_pooled[levels < GRID.num_levels - 1].sum()) >= int(fine.sum())


def test_hard_cases_single_level_no_parent_empty():
    module = ContextConfig(kind="mean").setup(feature_dim=4)
    # Single level: nobody has a parent or child; the output is still finite and near f.
    levels = torch.zeros(5, dtype=torch.long)
    positions = GRID.grid_position(torch.arange(15).view(5, 3), levels)
    features = torch.randn(5, 4)
    found = lookup(features, levels, positions)
    assert not found.parent_found.any() and not found.child_found.any()
    assert (found.parent_pooled == 0).all() and (found.child_pooled == 0).all()
    out = enhance(module, features, levels, positions)
    assert torch.isfinite(out).all() and (out - features).abs().max() < 0.05
    # Only fine anchors, none with a parent.
    levels = torch.full((5,), 3, dtype=torch.long)
    found = lookup(features, levels, positions)
    assert not found.parent_found.any()
    # Empty visible set.
    empty = lookup(torch.zeros(0, 4), torch.zeros(0, dtype=torch.long), torch.zeros(0, 3))
    assert empty.parent.shape == (0, 4) and empty.parent_found.shape == (0,)


def test_dense_cell_ids_packed_and_fallback_agree():
    gen = torch.Generator().manual_seed(0)
    keys = torch.randint(0, 5, (400, 4), generator=gen)
    ids, count = dense_cell_ids(keys)
    assert count == torch.unique(keys, dim=0).shape[0]
    wide = keys * torch.tensor([1, 1 << 20, 1 << 20, 1 << 20])  # range too wide to pack in 62 bits
    wide_ids, wide_count = dense_cell_ids(wide)
    assert wide_count == count
    same = keys[:, None, :].eq(keys[None]).all(-1)
    assert torch.equal(ids[:, None] == ids[None], same)
    assert torch.equal(wide_ids[:, None] == wide_ids[None], same)


@pytest.mark.parametrize("rule", ["trilinear", "paper"])
@pytest.mark.parametrize("kind", ["mean", "max", "attention"])
def test_near_identity_at_init_and_matches_reference(kind, rule):
    torch.manual_seed(0)
    features, levels, positions = random_visible_anchors(5, num=150, dim=32)
    module = ContextConfig(kind=kind, parent_rule=rule).setup(feature_dim=32)
    shift = enhance(module, features, levels, positions) - features
    assert 0 < shift.abs().max() < 0.05  # near zero, not exactly zero (paper Sec. 3.3)
    for p in module.parameters():
        torch.nn.init.normal_(p, std=0.3)
    reduce = "amax" if kind == "max" else "mean"
    parent, own, child, parent_found, child_found = slow_lookup(features, levels, positions, rule, reduce)
    if rule == "trilinear":
        parent = torch.where(parent_found[:, None], parent, module.missing[0])
        child = torch.where(child_found[:, None], child, module.missing[1])
    if kind == "attention":
        tokens = torch.stack([parent, own, child], 1) + module.roles
        q = module.query(features)
        scores = torch.einsum("vh,vth->vt", q, module.key(tokens)) / 32**0.5
        expected = features + module.out((scores.softmax(1)[..., None] * module.value(tokens)).sum(1))
    else:
        expected = features + module.mlp(torch.cat([parent, own, child], 1))
    torch.testing.assert_close(enhance(module, features, levels, positions), expected)


def test_none_is_identity_without_parameters():
    features, levels, positions = random_visible_anchors(1, num=50, dim=32)
    module = ContextConfig(kind="none").setup(feature_dim=32)
    assert enhance(module, features, levels, positions) is features
    assert sum(p.numel() for p in module.parameters()) == 0


def test_parameter_count():
    # (96*32 + 32) + (32*32 + 32) = 4,160 with biases; 4,096 without; + 2 x 32 "missing" vectors.
    # The paper's 3,168 is neither.
    count = lambda cfg: sum(p.numel() for p in cfg.setup(feature_dim=32).parameters())  # noqa: E731
    assert count(ContextConfig(kind="mean")) == 4160 + 64
    assert count(ContextConfig(kind="max")) == 4160 + 64
    assert count(ContextConfig(kind="mean", bias=False)) == 4096 + 64
    assert count(ContextConfig(kind="attention")) == 4 * (32 * 32 + 32) + 3 * 32 + 64


@pytest.mark.parametrize("kind", ["mean", "max", "attention"])
def test_gradients_reach_the_first_layer_at_init(kind):
    """With an exactly zero last layer the first layer got no gradient until the last one moved."""
    features, levels, positions = random_visible_anchors(2, num=80, dim=32)
    features.requires_grad_(True)
    module = ContextConfig(kind=kind).setup(feature_dim=32)
    enhance(module, features, levels, positions).square().sum().backward()
    first = module.mlp[0].weight if kind != "attention" else module.value.weight
    assert torch.isfinite(features.grad).all() and first.grad.abs().sum() > 0
    assert module.missing.grad.abs().sum() > 0  # some anchor of this view lacks a context


def test_empty_view_and_bad_config():
    module = ContextConfig(kind="mean").setup(feature_dim=4)
    empty = enhance(module, torch.zeros(0, 4), torch.zeros(0, dtype=torch.long), torch.zeros(0, 3))
    assert empty.shape == (0, 4)
    assert set(CONTEXT_AGGREGATORS.names()) >= {"none", "mean", "max", "attention"}
    with pytest.raises(HicoError, match="context aggregator 'sum'"):
        ContextConfig(kind="sum").setup(feature_dim=4)
    with pytest.raises(HicoError, match="parent_rule"):
        ContextConfig(parent_rule="ceil").setup(feature_dim=4)


@pytest.mark.parametrize("rule", ["trilinear", "paper"])
@pytest.mark.parametrize("kind", ["mean", "max", "attention"])
def test_gradcheck_float64(kind, rule):
    features, levels, positions = random_visible_anchors(3, num=12, dim=4, span=1)
    module = ContextConfig(kind=kind, parent_rule=rule).setup(feature_dim=4).double()
    for p in module.parameters():
        torch.nn.init.normal_(p, std=0.5)
    found = lookup(features, levels, positions, rule)
    assert found.parent_found.any() and found.child_found.any() and not found.parent_found.all()
    features = features.double().requires_grad_(True)
    missing = module.missing.detach().clone().requires_grad_(True)

    graph = module.graph(levels, positions.double(), torch.arange(levels.shape[0]), GRID)

    def run(f, m):  # the learned "missing" vectors are an input too
        return torch.func.functional_call(module, {"missing": m}, (f, graph))

    assert torch.autograd.gradcheck(run, (features, missing))


def _first_steps_shift(kind: str) -> float:
    """Largest |f_hat - f| after 5 Adam steps (the clca group's lr) from zero anchor features."""
    torch.manual_seed(0)
    _, levels, positions = random_visible_anchors(3, num=200, dim=32)
    features = torch.zeros(200, 32)  # the field initialises anchor features to zero
    module = ContextConfig(kind=kind).setup(feature_dim=32)
    optimizer = torch.optim.Adam(module.parameters(), lr=0.008, eps=1e-15)
    direction = torch.randn(32, generator=torch.Generator().manual_seed(1))
    for _ in range(5):
        optimizer.zero_grad()
        (enhance(module, features, levels, positions) @ direction).sum().backward()
        optimizer.step()
    with torch.no_grad():
        return float((enhance(module, features, levels, positions) - features).abs().max())


def test_attention_moves_features_no_faster_than_mean_at_start():
    """Every anchor shares the aggregator's output while features are zero; with non-zero value
    biases attention shifted all of them twice as fast as mean CLCA and, in training, drove every
    opacity negative within ten steps (hico-gs-attn collapsed to 12.9 dB on city-block)."""
    assert _first_steps_shift("attention") < 1.5 * _first_steps_shift("mean")


def test_cached_index_views_equal_fresh_graphs_and_rebuild_when_an_anchor_changes_cell():
    """ContextIndex keeps the relation over all anchors; a view must equal the graph of the visible
    anchors alone, and an anchor drifting into another cell must be seen (not a stale relation)."""
    features, levels, positions = random_visible_anchors(4, num=300, dim=8)
    index = ContextIndex(GRID, "trilinear")
    gen = torch.Generator().manual_seed(5)
    before = lookup(features, levels, positions)
    for trial in range(5):
        visible = torch.sort(torch.randperm(300, generator=gen)[:200]).values
        if trial == 4:  # densification: other anchors (fewer here), the relation is rebuilt over them
            features, levels, positions, visible = features[:250], levels[:250], positions[:250], visible[visible < 250]
        if trial == 3:  # move a fine anchor that has parents a whole voxel of its level: its cell changes
            moved = int(((levels == 3) & before.parent_found).nonzero()[0])
            positions = positions.clone()
            positions[moved, 0] += GRID.voxel_size / 2.0**3
            visible = torch.arange(300)
            assert not torch.equal(lookup(features, levels, positions).parent, before.parent)  # the move matters
        cached = context_lookup(features[visible], index.view(levels, positions, visible))
        fresh = lookup(features[visible], levels[visible], positions[visible])
        for name in ("parent", "own", "child", "parent_found", "child_found", "parent_pooled", "child_pooled"):
            torch.testing.assert_close(getattr(cached, name), getattr(fresh, name), msg=f"{name}, trial {trial}")
    with pytest.raises(ValueError, match="ascending"):
        index.view(levels, positions, torch.tensor([3, 1]))
