"""Densification keeps the octree a tree for CLCA's trilinear lookup (DensifyConfig.keep_ancestors)."""

import torch

from hico_plugin.field.densify import GrownAnchors, close_ancestors, orphan_edges
from hico_plugin.field.octree import OctreeGrid

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
