"""The viewer's "CLCA parent found" overlay: colours, and the field's per-anchor flag it reads."""

import numpy as np
import torch

from hico_plugin.field import FieldConfig, OctreeGrid
from hico_plugin.field.field import AnchorField
from hico_plugin.viewer.lookup_overlay import COARSEST, FOUND, MISSING, parent_found_colors, read_parent_found


def test_colours_by_found_and_level():
    colors = parent_found_colors(np.array([True, False, False]), np.array([1, 2, 0]))
    assert colors.dtype == np.uint8 and colors.tolist() == [list(FOUND), list(MISSING), list(COARSEST)]


def test_field_flags_anchors_without_a_parent_and_state_reads_them():
    grid = OctreeGrid(origin=(0.0, 0.0, 0.0), cube_size=8.0, voxel_size=1.0, num_levels=3, fork=2,
                      d_std=10.0, init_level=1)
    levels = torch.tensor([0, 1, 2, 2])
    index = torch.tensor([[1, 1, 1], [3, 2, 2], [6, 4, 4], [13, 1, 1]])  # the last has no level-1 anchor near
    field = AnchorField(FieldConfig(), grid.grid_position(index, levels), levels, grid,
                        torch.tensor([[4.0, 4.0, 20.0]]))
    assert field.parent_found().tolist() == [False, True, True, False]

    class State:
        def anchor_parent_found(self):
            return field.parent_found()

    assert read_parent_found(State()).tolist() == [False, True, True, False]
    assert read_parent_found(object()) is None  # a model without CLCA: no overlay
