"""Densification keeps the octree a tree for CLCA's trilinear lookup (DensifyConfig.keep_ancestors)."""

import dataclasses
import itertools
import math
from types import SimpleNamespace

import pytest
import torch

from hico_plugin.field import AnchorField
from hico_plugin.strategy.octree import draw_hidden_ancestors
from hico_plugin.strategy.rules import GrownAnchors, close_ancestors, orphan_edges
from hico_plugin.field.octree import OctreeGrid
from hico_plugin.presets import PRESETS

GRID = OctreeGrid(origin=(0.0, 0.0, 0.0), cube_size=64.0, voxel_size=1.0, num_levels=4, fork=2, d_std=1.0,
                  init_level=0)


def anchors(*rows):
    """rows of (level, i, j, k) -> positions [N,3], levels [N]."""
    keys = torch.tensor(rows, dtype=torch.long)
    return GRID.grid_position(keys[:, 1:], keys[:, 0]), keys[:, 0]


def slow_orphans(positions, levels):
    """Obvious reference: an anchor at level l > 0 with index k is an orphan when no level-(l-1)
    anchor has an index j with |2 j - k| <= 1 on every axis (the trilinear candidates)."""
    index = GRID.grid_index(positions, levels)
    out = []
    for n in range(len(levels)):
        if levels[n] == 0:
            out.append(False)
            continue
        coarser = (levels == levels[n] - 1).nonzero().squeeze(1)
        near = [((2 * index[m] - index[n]).abs() <= 1).all() for m in coarser]
        out.append(not any(near))
    return torch.tensor(out)


def test_orphans_match_the_obvious_reference():
    torch.manual_seed(0)
    levels = torch.randint(0, 4, (60,))
    index = torch.stack([torch.randint(0, 2 ** int(l) * 3, (3,)) for l in levels])
    positions = GRID.grid_position(index, levels)
    orphan, anchor, keys, weight = orphan_edges(levels, positions, GRID)
    assert torch.equal(orphan, slow_orphans(positions, levels))
    assert orphan.any() and not orphan.all()
    assert torch.equal(torch.unique(anchor), orphan.nonzero().squeeze(1))
    assert torch.all(keys[:, 0] == levels[anchor] - 1)


def test_close_ancestors_revives_a_pruned_parent_and_adds_missing_ones():
    # level-0 (0,0,0); level-1 (0,0,0) under it; level-2 (5,5,5) whose parents at level 1 are (2..3)^3;
    # a pruned level-1 anchor at (2,2,2) can serve it. Level-3 (25,25,25) has no ancestor at all.
    positions, levels = anchors((0, 0, 0, 0), (1, 0, 0, 0), (1, 2, 2, 2), (2, 5, 5, 5))
    features = torch.arange(4.0)[:, None].repeat(1, 2)
    keep = torch.tensor([True, True, False, True])
    new_pos, new_lev = anchors((3, 25, 25, 25))
    grown = GrownAnchors(new_pos, new_lev, torch.full((1, 2), 9.0))
    kept, out = close_ancestors(positions, levels, features, keep, grown, GRID)
    assert kept.tolist() == [True, True, True, True]  # (1,2,2,2) revived
    all_pos = torch.cat([positions[kept], out.positions])
    all_lev = torch.cat([levels[kept], out.levels])
    assert not slow_orphans(all_pos, all_lev).any()
    # level 3 -> new parents at levels 2, 1 and 0 carrying its feature; the revived level-1 anchor
    # (index 2 -> parent 1 at level 0, absent) gets a level-0 parent carrying its feature
    assert sorted(out.levels.tolist()) == [0, 0, 1, 2, 3]
    assert sorted(out.features[:, 0].tolist()) == [2.0, 9.0, 9.0, 9.0, 9.0]


def test_nothing_changes_when_every_anchor_has_a_parent():
    positions, levels = anchors((0, 0, 0, 0), (1, 1, 1, 1), (2, 2, 3, 2))
    keep = torch.ones(3, dtype=torch.bool)
    empty = GrownAnchors(positions[:0], levels[:0], torch.zeros(0, 2))
    kept, out = close_ancestors(positions, levels, torch.zeros(3, 2), keep, empty, GRID)
    assert kept.all() and out.positions.shape[0] == 0


def slow_close_ancestors(positions, levels, features, keep, grown):
    """The rule one round at a time over every anchor, with Python loops: (keep, {(level, i, j, k): feature})."""
    keep = keep.clone()
    index = GRID.grid_index(positions, levels)
    members = [(int(levels[n]), tuple(index[n].tolist()), features[n]) for n in range(len(levels))]
    grown_index = GRID.grid_index(grown.positions, grown.levels)
    extra = [(int(grown.levels[n]), tuple(grown_index[n].tolist()), grown.features[n]) for n in range(len(grown.levels))]
    for _ in range(GRID.num_levels - 1):
        live = [m for n, m in enumerate(members) if keep[n]] + extra
        cells = {(lev, idx) for lev, idx, _ in live}
        orphans = []
        for lev, idx, feat in live:
            if lev == 0:
                continue
            candidates = []
            for corner in itertools.product((0, 1), repeat=3):
                parent, weight = [], 1.0
                for axis in range(3):
                    half = idx[axis] / 2
                    low = math.floor(half)
                    parent.append(low + corner[axis])
                    weight *= (half - low) if corner[axis] else 1.0 - (half - low)
                if weight > 0:
                    candidates.append(((lev - 1, tuple(parent)), weight))
            if not any(cell in cells for cell, _ in candidates):
                orphans.append((candidates, feat))
        if not orphans:
            break
        wanted = {cell for candidates, _ in orphans for cell, _ in candidates}
        revived = {(lev, idx) for n, (lev, idx, _) in enumerate(members) if not keep[n] and (lev, idx) in wanted}
        for n, (lev, idx, _) in enumerate(members):
            if (lev, idx) in revived:
                keep[n] = True
        new = {}
        for candidates, feat in orphans:
            if any(cell in revived for cell, _ in candidates):
                continue
            best = max(w for _, w in candidates)
            cell = next(c for c, w in candidates if w == best)
            new[cell] = feat if cell not in new else torch.maximum(new[cell], feat)
        extra += [(lev, idx, feat) for (lev, idx), feat in new.items()]
    return keep, {(lev, idx): feat for lev, idx, feat in extra}


def test_close_ancestors_matches_the_slow_rule_on_random_trees():
    """Only the first round checks every anchor; later ones check what the previous round added. The
    result must equal the rule applied to every anchor in every round."""
    for seed in range(6):
        gen = torch.Generator().manual_seed(seed)
        levels = torch.randint(0, 4, (80,), generator=gen)
        index = torch.stack([torch.randint(0, 2 ** int(lev) * 3, (3,), generator=gen) for lev in levels])
        keys = torch.unique(torch.cat([levels[:, None], index], 1), dim=0)  # one anchor per cell
        positions, levels = GRID.grid_position(keys[:, 1:], keys[:, 0]), keys[:, 0]
        features = torch.randn(len(levels), 3, generator=gen)
        keep = torch.rand(len(levels), generator=gen) > 0.3
        grown_levels = torch.randint(1, 4, (6,), generator=gen)
        grown_index = torch.stack([torch.randint(0, 2 ** int(lev) * 3, (3,), generator=gen) for lev in grown_levels])
        taken = {tuple(row) for row in keys.tolist()}
        fresh = torch.tensor([(int(lev), *idx) not in taken for lev, idx in zip(grown_levels, grown_index.tolist())])
        grown = GrownAnchors(GRID.grid_position(grown_index[fresh], grown_levels[fresh]), grown_levels[fresh],
                             torch.randn(int(fresh.sum()), 3, generator=gen))
        kept, out = close_ancestors(positions, levels, features, keep, grown, GRID)
        slow_keep, slow_extra = slow_close_ancestors(positions, levels, features, keep, grown)
        assert torch.equal(kept, slow_keep), seed
        out_index = GRID.grid_index(out.positions, out.levels)
        fast_extra = {(int(out.levels[n]), tuple(out_index[n].tolist())): out.features[n] for n in range(len(out.levels))}
        assert fast_extra.keys() == slow_extra.keys(), seed
        for cell, feat in slow_extra.items():
            assert torch.equal(fast_extra[cell], feat), (seed, cell)
        assert len(slow_extra) > len(grown.levels) and not kept.all()  # the case exercises new and revived anchors


@pytest.mark.parametrize(("preset", "densify_changes", "keeps"), [
    ("hico-gs", {}, True), ("hico-gs-clca", {}, True), ("hico-gs-clca-paper", {}, False), ("octree-gs", {}, False),
    ("octree-gs", {"keep_ancestors_without_context": True}, True),
    ("hico-gs-clca-paper", {"keep_ancestors_without_context": True}, True),
    ("hico-gs-clca", {"keep_ancestors": False}, False),
    ("octree-gs", {"keep_ancestors": False, "keep_ancestors_without_context": True}, False)])
def test_the_tree_is_kept_where_the_trilinear_lookup_reads_it_or_on_request(preset, densify_changes, keeps):
    config = PRESETS[preset][1].model.field
    config = dataclasses.replace(config, densify=dataclasses.replace(config.densify, **densify_changes))
    positions, levels = anchors((0, 1, 1, 1), (1, 2, 2, 2))
    field = AnchorField(config, positions, levels, GRID, torch.zeros(1, 3))
    assert config.densify.setup(field=field).keeps_ancestors is keeps


def _clca_field(*rows, **densify_changes):
    config = PRESETS["hico-gs-clca"][1].model.field
    config = dataclasses.replace(config, densify=dataclasses.replace(config.densify, **densify_changes))
    positions, levels = anchors(*rows)
    field = AnchorField(config, positions, levels, GRID, torch.zeros(1, 3))
    strategy = config.densify.setup(field=field)
    strategy.start, strategy.interval, strategy.stop = 0, 1, 100
    return field, strategy


def _densify_with_opacity(pair, step, opacity_per_view):
    """One adjustment at ``step`` after 10 views in which every anchor was seen, with these mean
    summed opacities (below min_opacity = pruned); no offset is eligible to grow."""
    field, strategy = pair
    strategy.stat_views.fill_(10)
    strategy.last_adjust_step.fill_(step - 1)
    strategy.anchor_denom.fill_(10.0)
    strategy.opacity_accum.copy_(10.0 * torch.tensor(opacity_per_view))
    strategy.offset_denom.zero_()
    return strategy.step_post_update(field, step)


def test_a_kept_ancestor_lends_its_context_but_is_not_drawn_and_goes_when_no_anchor_needs_it():
    # A (level 0) -> B (level 1) -> C (level 2); B's opacity is too low, but C needs it as a parent
    pair = field, strategy = _clca_field((0, 0, 0, 0), (1, 1, 1, 1), (2, 3, 3, 3))
    assert strategy.keeps_ancestors and not field.config.densify.draw_ancestors
    _densify_with_opacity(pair, 1, [1.0, 0.0, 1.0])
    assert field.num_anchors == 3 and field.drawn.tolist() == [True, False, True]
    every = torch.arange(3)
    assert field.parent_found()[2]  # C reads B's context
    eye = SimpleNamespace(center=torch.tensor([0.0, 0.0, -50.0]), index=-1)
    decoded = field.decode(eye, every)
    assert set(decoded.anchor_ids.tolist()) <= {0, 2} and 0 in decoded.anchor_ids.tolist()
    # C's context (read from B) still reaches what is drawn: C's decoded feature differs without B
    with_b = field.enhanced_features(every)[2]
    without_b = field.enhanced_features(torch.tensor([0, 2]))[1]
    assert not torch.allclose(with_b, without_b)
    # C goes too: nothing needs B any more, so it goes with it (it is never judged by its own opacity)
    _densify_with_opacity(pair, 2, [1.0, 0.0, 0.0])
    assert field.num_anchors == 1 and field.drawn.tolist() == [True]


def test_growth_into_a_kept_ancestors_cell_draws_it_and_adds_no_second_anchor():
    pair = field, _ = _clca_field((0, 0, 0, 0), (1, 1, 1, 1), (2, 3, 3, 3))
    _densify_with_opacity(pair, 1, [1.0, 0.0, 1.0])
    b_feature = field.anchor_features.detach()[1].clone()
    asked, asked_levels = anchors((1, 1, 1, 1), (1, 0, 0, 0))  # B's cell and a free one
    rest = draw_hidden_ancestors(field, GrownAnchors(asked, asked_levels, torch.ones(2, field.anchor_features.shape[1])))
    assert field.drawn.tolist() == [True, True, True]
    assert rest.levels.tolist() == [1] and torch.equal(rest.positions, asked[1:])
    assert torch.equal(field.anchor_features.detach()[1], b_feature)  # B keeps its training


def test_drawn_ancestors_are_the_previous_behaviour():
    pair = field, _ = _clca_field((0, 0, 0, 0), (1, 1, 1, 1), (2, 3, 3, 3), draw_ancestors=True)
    _densify_with_opacity(pair, 1, [1.0, 0.0, 1.0])
    assert field.num_anchors == 3 and field.drawn.all()
