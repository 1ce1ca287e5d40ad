"""Anchor field: octree invariants, selection, decoder, state round trips."""

import math

import numpy as np
import pytest
import torch

from hico_plugin.cameras import Camera
from hico_plugin.errors import HicoError
from hico_plugin.field import ContextConfig, DecoderConfig, FieldConfig, OctreeBuildConfig, OctreeGrid
from hico_plugin.field.decoder import INITIAL_OPACITY
from hico_plugin.field.lod import progressive_interval_ends
from hico_plugin.field.octree import build_octree, distance_range
from hico_plugin.model.hico import default_optimizers

from helpers_field import camera_at, hand_field, make_field, point_clouds, ring_cameras

def test_octree_invariants_on_random_clouds():
    for points, center in point_clouds():
        cameras = ring_cameras(center)
        positions, levels, grid = build_octree(points, cameras.centers, OctreeBuildConfig())
        origin = torch.tensor(grid.origin)
        assert grid.num_levels >= 2 and grid.fork == 2
        lo, hi = map(torch.tensor, grid.bbox)
        assert ((points >= lo) & (points <= hi)).all(), "cube must enclose all points"
        index = grid.grid_index(positions, levels)
        torch.testing.assert_close(grid.grid_position(index, levels), positions)  # on grid points
        keys = torch.cat([levels[:, None], index], 1)
        assert torch.unique(keys, dim=0).shape[0] == keys.shape[0], "duplicate (level, cell) keys"
        fine = levels > 0
        parent = torch.div(index[fine], 2, rounding_mode="floor")
        coarse_cells = torch.tensor([grid.cells_per_axis(int(lv) - 1) for lv in levels[fine]])
        assert (parent >= 0).all() and (parent <= coarse_cells[:, None]).all()
        # The anchor lies in its parent's region [k', k' + 1/2] x v_{l-1} of the octree grid.
        offset = (positions[fine] - origin) / (grid.voxel_size / 2.0 ** (levels[fine] - 1).float())[:, None]
        assert ((offset - parent >= -1e-4) & (offset - parent <= 0.5 + 1e-4)).all()
        assert (index >= 0).all()


def test_level_count_and_standard_distance_follow_camera_range():
    points, _ = next(point_clouds())
    cameras = ring_cameras()
    per_camera = []
    for c in cameras.centers:
        d = np.linalg.norm(points.numpy() - c.numpy(), axis=1)
        per_camera += list(np.quantile(d, [0.001, 0.999]))
    dist_min, dist_max = np.quantile(per_camera, 0.001), np.quantile(per_camera, 0.999)
    got_min, got_max = distance_range(points, cameras.centers)
    assert got_min == pytest.approx(dist_min, rel=1e-4) and got_max == pytest.approx(dist_max, rel=1e-4)
    _, _, grid = build_octree(points, cameras.centers, OctreeBuildConfig())
    assert grid.d_std == pytest.approx(dist_max, rel=1e-4)
    assert grid.num_levels == round(math.log2(dist_max / dist_min)) + 1
    assert grid.init_level == grid.num_levels // 2


def test_bad_points_are_user_errors():
    cameras = ring_cameras()
    with pytest.raises(HicoError, match="sparse points"):
        build_octree(torch.zeros(0, 3), cameras.centers, OctreeBuildConfig())
    with pytest.raises(HicoError, match="NaN"):
        build_octree(torch.tensor([[0.0, 0.0, float("nan")]] * 3), cameras.centers, OctreeBuildConfig())


def test_state_dict_round_trip_restores_grid_and_shapes():
    field = make_field()
    with torch.no_grad():
        field.anchor_features.normal_()
        field.extra_level.uniform_()
    other_points = torch.rand(500, 3) * 3 + 1  # a different cloud: other grid, other anchor count
    fresh = FieldConfig().setup(points=other_points, train_cameras=ring_cameras(), schedule_scale=0.1)
    assert fresh.num_anchors != field.num_anchors and fresh.grid != field.grid
    fresh.load_state_dict(field.state_dict())
    assert fresh.grid == field.grid
    for (name, a), (_, b) in zip(field.state_dict().items(), fresh.state_dict().items()):
        if isinstance(a, torch.Tensor):
            assert torch.equal(a, b), name
    camera = ring_cameras()[0]
    assert torch.equal(fresh.select(camera, 100), field.select(camera, 100))
    assert fresh.level_interval_ends == field.level_interval_ends


def test_near_camera_selects_finer_levels_than_far_camera():
    # Same spot, all three levels; d_std = 10: at distance 10 only level 0, at 2.5 levels 0..2.
    field = hand_field([[4, 4, 4]] * 3, [0, 1, 2], [[4, 4, 0]])
    far = camera_at((4.0, 4.0 - 10.0, 4.0), (4.0, 4.0, 4.0))
    near = camera_at((4.0, 4.0 - 2.5, 4.0), (4.0, 4.0, 4.0))
    assert field.select(far, None).tolist() == [0]
    assert field.select(near, None).tolist() == [0, 1, 2]
    with torch.no_grad():
        field.extra_level.fill_(1.0)  # eps raises the predicted level by one
    assert field.select(far, None).tolist() == [0, 1]


def test_frustum_culls_anchors_behind_and_beside_the_camera():
    field = hand_field([[4, 4, 4], [4, -4, 4], [30, 4, 4], [4.5, 4, 4.5]], [0, 0, 0, 0], [[4, 4, 0]])
    with torch.no_grad():
        field.log_scaling.fill_(math.log(0.1))  # small anchors: the margin alone decides
    camera = camera_at((4.0, 0.0, 4.0), (4.0, 4.0, 4.0))  # looks along +y
    assert field.select(camera, None).tolist() == [0, 3]



def test_sees_applies_selects_rule_to_any_subset_of_anchors():
    field = make_field()
    camera = ring_cameras()[8]  # the close view: several levels, some anchors culled
    selected = field.select(camera, None)
    assert 0 < len(selected) < field.num_anchors
    subset = torch.arange(0, field.num_anchors, 3)
    expected = torch.isin(subset, selected)
    assert torch.equal(field.sees(camera, subset), expected)

def test_progressive_levels_follow_the_schedule():
    ends6 = progressive_interval_ends(OctreeGrid((0, 0, 0), 1, 1, 6, 2, 1, 3), 10_000, 1.5)
    assert ends6 == pytest.approx([6000, 10000])
    ends8 = progressive_interval_ends(OctreeGrid((0, 0, 0), 1, 1, 8, 2, 1, 4), 10_000, 1.5)
    assert ends8 == pytest.approx([4736.84, 7894.74, 10000], abs=0.01)
    field = hand_field([[4, 4, 4]], [0], [[4, 4, 0]])  # 3 levels, init_level 1
    field.set_schedule_scale(0.1)  # coarse_steps 10k of 30k -> the last level switches on at 1000
    assert field.level_interval_ends == pytest.approx([1000.0])
    assert [field.active_levels(s) for s in (0, 1000, 1001, None)] == [2, 2, 3, 3]
    assert not field.progressive_done(1000) and field.progressive_done(1001)


def test_decoder_outputs_and_opacity_mask():
    field = make_field(decoder=DecoderConfig(appearance_dim=4, chunk_size=50))
    torch.manual_seed(0)
    with torch.no_grad():
        field.anchor_features.normal_()
        field.offsets.normal_()
    camera = ring_cameras()[2]
    ids = field.select(camera, None)
    g = field.decode(camera, ids)
    k = field.offsets.shape[1]
    assert g.raw_opacities.shape == (len(ids), k) and torch.equal(g.keep_mask, g.raw_opacities > 0)
    assert len(g) == int(g.keep_mask.sum()) and 0 < len(g) < len(ids) * k
    assert (g.opacities > 0).all() and (g.opacities <= 1).all()
    assert ((g.colors > 0) & (g.colors < 1)).all()
    torch.testing.assert_close(g.quats.norm(dim=-1), torch.ones(len(g)))
    scaling = torch.exp(field.log_scaling.detach())
    offsets = field.offsets[g.anchor_ids, g.child_ids]
    expected_means = field.anchors[g.anchor_ids] + offsets * scaling[g.anchor_ids, :3]
    torch.testing.assert_close(g.means, expected_means)
    assert (g.scales <= scaling[g.anchor_ids, 3:] + 1e-6).all()
    # One big chunk gives the same Gaussians as chunks of 50 anchors.
    field.decoder.config.chunk_size = 1 << 20
    whole = field.decode(camera, ids)
    torch.testing.assert_close(whole.means, g.means)
    torch.testing.assert_close(whole.colors, g.colors)
    # A camera without a training index uses the mean appearance embedding.
    table = field.decoder.appearance.weight
    free = Camera(camera.viewmat, camera.K, camera.width, camera.height, index=-1)
    torch.testing.assert_close(field.decoder.appearance_code(-1, table), table.mean(0))
    assert not torch.equal(field.decode(free, ids).colors, g.colors)
    # Gradients reach the anchors' parameters and every MLP group.
    (g.means.sum() + g.colors.sum() + g.opacities.sum() + g.scales.sum()).backward()
    for name, params in field.param_groups().items():
        if name != "clca":  # zero last layer: only the last layer itself gets a gradient at init
            assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in params), name



def test_fresh_decoder_starts_children_near_3dgs_initial_opacity():
    # Around opacity 0 a few early steps can push every child below 0, after which none is drawn
    # and none gets a gradient again; a fresh decoder starts them at 3DGS's 0.1 instead.
    field = make_field()
    camera = ring_cameras()[2]
    ids = field.select(camera, None)
    opacity = field.decode(camera, ids).raw_opacities
    assert abs(float(opacity.mean()) - INITIAL_OPACITY) < 0.05
    assert float((opacity > 0).float().mean()) > 0.6


def test_one_viewpoint_per_anchor_decodes_each_anchor_as_its_own_camera_would():
    field = make_field(decoder=DecoderConfig(add_distance=True, chunk_size=64))
    torch.manual_seed(0)
    with torch.no_grad():
        field.anchor_features.normal_()
    cameras = ring_cameras()
    ids = torch.arange(field.num_anchors)
    features = field.enhanced_features(ids)
    which = ids % len(cameras)
    mixed = field.decode_features(features, ids, cameras.centers[which], -1)
    for c in range(len(cameras)):
        rows = ids[which == c]
        own = field.decode_features(features[rows], rows, cameras.centers[c], -1)
        mine = which[mixed.anchor_ids] == c
        assert torch.equal(mixed.anchor_ids[mine], own.anchor_ids)
        torch.testing.assert_close(mixed.colors[mine], own.colors)
        torch.testing.assert_close(mixed.opacities[mine], own.opacities)

def test_default_optimizers_cover_every_group():
    field = make_field(decoder=DecoderConfig(appearance_dim=4))
    assert set(field.param_groups()) <= set(default_optimizers())
    assert "clca" not in make_field(context=ContextConfig(kind="none")).param_groups()
