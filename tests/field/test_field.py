"""Anchor field: octree invariants, selection, decoder, growing / pruning, state round trips."""

import copy
import math

import numpy as np
import pytest
import torch

from hico_plugin.cameras import Camera, Cameras
from hico_plugin.engine.optimizers import Optimizers
from hico_plugin.engine.protocol import LRSchedule
from hico_plugin.errors import HicoError
from hico_plugin.field import (
    AnchorField, ContextConfig, DecoderConfig, DensifyConfig, FieldConfig, OctreeBuildConfig, OctreeGrid)
from hico_plugin.field.decoder import INITIAL_OPACITY
from hico_plugin.field.lod import progressive_interval_ends
from hico_plugin.field.octree import build_octree, distance_range
from hico_plugin.model.hico import default_optimizers
from hico_plugin.scenes.orbits import look_at as orbit_look_at

K = torch.tensor([[100.0, 0.0, 64.0], [0.0, 100.0, 48.0], [0.0, 0.0, 1.0]])


def look_at(eye, target=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """world->camera 4x4 (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    return torch.from_numpy(orbit_look_at(np.array([eye], dtype=np.float64), np.array([target], dtype=np.float64))[0]).float()


def ring_cameras(center=(0.0, 0.0, 0.0), radius=8.0, count=8) -> Cameras:
    c = torch.tensor(center)
    eyes = [(c + torch.tensor([radius * math.cos(a), radius * math.sin(a), 2.0])).tolist()
            for a in np.linspace(0, 2 * math.pi, count, endpoint=False)]
    eyes.append((c + torch.tensor([2.5, 0.5, 1.0])).tolist())  # one close view: more levels
    viewmats = torch.stack([look_at(e, tuple(c.tolist())) for e in eyes])
    n = len(eyes)
    return Cameras(viewmats, K.expand(n, 3, 3).clone(), torch.full((n,), 128), torch.full((n,), 96))


def point_clouds():
    gen = torch.Generator().manual_seed(0)
    yield torch.randn(2000, 3, generator=gen) * 2, (0.0, 0.0, 0.0)
    # All coordinates positive and far from the origin: the base method's x1.1 cube would shrink.
    yield torch.rand(1500, 3, generator=gen) * 4 + 20, (22.0, 22.0, 22.0)
    plane = torch.rand(1500, 3, generator=gen) * 6 - 3
    plane[:, 2] = 0.01 * torch.randn(1500, generator=gen)
    yield plane, (0.0, 0.0, 0.0)


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


def make_field(**config_changes) -> AnchorField:
    points, _ = next(point_clouds())
    return FieldConfig(**config_changes).setup(points=points, train_cameras=ring_cameras(), schedule_scale=0.1)


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


def hand_grid(num_levels=3) -> OctreeGrid:
    return OctreeGrid(origin=(0.0, 0.0, 0.0), cube_size=8.0, voxel_size=1.0, num_levels=num_levels, fork=2,
                      d_std=10.0, init_level=1)


def hand_field(positions, levels, camera_centers, **config_changes) -> AnchorField:
    config = FieldConfig(**config_changes)
    return AnchorField(config, torch.tensor(positions, dtype=torch.float32), torch.tensor(levels),
                       hand_grid(), torch.tensor(camera_centers, dtype=torch.float32))


def camera_at(eye, target) -> Camera:
    return Camera(look_at(eye, target), K, 128, 96)


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


def field_schedules(field) -> dict[str, LRSchedule]:
    """The model's default schedules for the field's groups (scene extent 1, 30k steps)."""
    return {name: default_optimizers()[name].schedule(30_000) for name in field.param_groups()}


def test_accumulate_stats_sums_per_offset():
    field = make_field()
    torch.manual_seed(1)
    with torch.no_grad():
        field.anchor_features.normal_()
    camera = ring_cameras()[0]
    g = field.decode(camera, field.select(camera, 10))
    radii = torch.ones(len(g), dtype=torch.int32)
    radii[::2] = 0  # not drawn: no gradient statistic
    grad = torch.zeros(len(g), 2)
    grad[:, 0] = 1.0  # one pixel unit in x = width / 2 NDC units
    field.accumulate_stats(g, grad, radii, camera, step=10)
    drawn = radii > 0
    expected = torch.zeros_like(field.offset_grad_accum)
    expected[g.anchor_ids[drawn], g.child_ids[drawn]] = camera.width / 2
    torch.testing.assert_close(field.offset_grad_accum, expected)
    assert torch.equal(field.offset_denom, (expected > 0).float())
    torch.testing.assert_close(field.opacity_accum[g.visible_ids], g.raw_opacities.clamp_min(0).sum(1))
    assert int(field.anchor_denom.sum()) == len(g.visible_ids) and int(field.stat_views) == 1
    field.accumulate_stats(g, grad, radii, camera, step=10**6)  # past densify.stop_step: ignored
    assert int(field.stat_views) == 1


@pytest.mark.parametrize("radii_shape", [(0,), (0, 2)])
def test_accumulate_stats_of_a_view_that_decodes_nothing(radii_shape):
    field = make_field()
    with torch.no_grad():
        field.decoder.mlp_opacity[-1].bias.fill_(-10.0)  # every child transparent: none is kept
    camera = ring_cameras()[0]
    g = field.decode(camera, field.select(camera, 10))
    assert len(g) == 0 and len(g.visible_ids) > 0
    field.accumulate_stats(g, torch.zeros(0, 2), torch.zeros(radii_shape, dtype=torch.int32), camera, step=10)
    assert int(field.stat_views) == 1 and float(field.offset_denom.sum()) == 0.0
    assert int(field.anchor_denom.sum()) == len(g.visible_ids)


def grow_prune_case(**densify_changes) -> AnchorField:
    """Anchor 0 (level 0, cell 4,4,4) has high-gradient offsets; anchor 1 never shows opacity."""
    field = hand_field([[4, 4, 4], [0, 0, 0]], [0, 0], [[4, 4, 1.5]], progressive=False,
                       densify=DensifyConfig(**densify_changes))
    tau = field.config.densify.grad_threshold
    growth = 2**0.2
    with torch.no_grad():
        field.log_scaling.zero_()
        field.log_scaling[0, 3:] = 1.0
        field.anchor_features[0] = torch.arange(32.0)
        field.offsets[0, 0] = torch.tensor([1.0, 0.0, 0.0])  # -> level-0 cell (5,4,4)
        field.offsets[0, 1] = torch.tensor([0.0, 0.5, 0.0])  # -> level-1 cell (8,9,8)
        field.offsets[0, 2] = torch.tensor([0.0, 0.0, 0.0])  # own, occupied cell: dropped
        field.offsets[0, 3] = torch.tensor([1.2, 0.0, 0.0])  # same cell as offset 0: merged
        field.offset_denom[0] = 50.0
        mean_grads = torch.tensor([1.05 * tau, 2.0 * tau * growth, 1.05 * tau, 1.05 * tau, 0.5 * tau])
        field.offset_grad_accum[0] = mean_grads * 50.0
        field.opacity_accum[0] = 40.0
        field.anchor_denom[:] = 50.0
        field.stat_views.fill_(100)
    return field


def test_growing_and_pruning_on_a_hand_built_case():
    field = grow_prune_case()
    assert field.densify(550) == {}  # not on the interval
    changes = field.densify(600)
    assert set(changes) == {"anchor", "offset", "anchor_feat", "scaling"}
    kept_rows, num_new = changes["anchor"]
    assert kept_rows.tolist() == [0] and num_new == 2  # anchor 1 pruned, two cells grown
    assert field.last_densify["grown"] == 2 and field.last_densify["pruned"] == 1
    assert field.last_densify["grown_level_0"] == 1 and field.last_densify["grown_level_1"] == 1
    torch.testing.assert_close(field.anchors.detach(), torch.tensor([[4.0, 4, 4], [5, 4, 4], [4, 4.5, 4]]))
    assert field.levels.tolist() == [0, 0, 1]
    torch.testing.assert_close(field.anchor_features[1], torch.arange(32.0))  # max over its source
    assert torch.equal(field.anchor_features[2], torch.zeros(32))  # next level: zeros
    torch.testing.assert_close(field.log_scaling[1:, 0], torch.log(torch.tensor([1.0, 0.5])))
    assert (field.log_scaling[:, 3:] <= 0.05 + 1e-7).all()  # clamp on prune
    assert field.extra_level.tolist() == pytest.approx([0.01, 0.0, 0.0])
    # Statistics: eligible offsets and judged anchors reset; new rows zero.
    assert field.offset_denom.abs().sum() == 0 and field.anchor_denom.abs().sum() == 0
    assert field.offsets.shape == (3, 5, 3) and int(field.stat_views) == 0


@pytest.mark.parametrize("budget, grown", [
    ({}, [[5.0, 4, 4], [4, 4.5, 4]]), ({"max_anchors": 3}, [[5.0, 4, 4], [4, 4.5, 4]]),
    ({"max_anchors": 2}, [[4.0, 4.5, 4]]), ({"max_anchors_per_seed": 1.0}, [[4.0, 4.5, 4]]),
    ({"max_anchors": 1, "max_anchors_per_seed": 1.5}, [])])
def test_an_anchor_budget_keeps_the_largest_gradient_cells_that_fit_after_pruning(budget, grown):
    # The level-1 cell's offset gradient (2 tau u) beats the level-0 cell's (1.05 tau); anchor 1 is
    # pruned in the same adjustment, so a budget of 2 (absolute, or 1x the 2 seed anchors) leaves room
    # for one new cell.
    field = grow_prune_case(**budget)
    field.densify(600)
    assert field.last_densify["pruned"] == 1
    torch.testing.assert_close(field.anchors.detach(), torch.tensor([[4.0, 4, 4], *grown]))
    limit = field.config.densify.budget(2)
    assert limit is None or int(field.drawn.sum()) <= limit


def test_the_anchor_budget_is_the_smaller_of_the_count_and_the_multiple_of_the_seed_anchors():
    assert DensifyConfig().budget(1000) is None
    assert DensifyConfig(max_anchors=5000).budget(1000) == 5000
    assert DensifyConfig(max_anchors_per_seed=3.0).budget(1000) == 3000
    assert DensifyConfig(max_anchors=2500, max_anchors_per_seed=3.0).budget(1000) == 2500


def test_densify_result_drives_optimizer_resize_and_resume():
    field = grow_prune_case()
    optimizers = Optimizers(field.param_groups(), field_schedules(field))
    field.anchor_features.sum().mul(0).add(field.anchor_features[0].sum()).backward()
    optimizers.step(0)
    old_moment = optimizers.optimizers["anchor_feat"].state[field.anchor_features]["exp_avg"].clone()
    for group, (kept_rows, num_new) in field.densify(600).items():
        optimizers.resize_group(group, field.param_groups()[group], kept_rows, num_new)
    moment = optimizers.optimizers["anchor_feat"].state[field.anchor_features]["exp_avg"]
    assert torch.equal(moment[0], old_moment[0]) and torch.equal(moment[1:], torch.zeros(2, 32))
    assert all(p is q for p, q in zip(optimizers.all_params(),
                                      [p for ps in field.param_groups().values() for p in ps]))
    # Resume: a freshly built (2-anchor) field takes the grown checkpoint's shapes exactly.
    fresh = hand_field([[4, 4, 4], [0, 0, 0]], [0, 0], [[4, 4, 1.5]], progressive=False)
    fresh.load_state_dict(field.state_dict())
    for (name, a), (_, b) in zip(field.state_dict().items(), fresh.state_dict().items()):
        if isinstance(a, torch.Tensor):
            assert torch.equal(a, b), name
    assert fresh.num_anchors == 3 and isinstance(fresh.anchors, torch.nn.Parameter)


def test_nothing_to_change_returns_empty_dict():
    field = hand_field([[4, 4, 4], [0, 0, 0]], [0, 0], [[4, 4, 1.5]], densify=DensifyConfig())
    field.stat_views.fill_(100)
    assert field.densify(600) == {} and field.last_densify["grown"] == 0
    assert field.num_anchors == 2


def test_training_loop_with_the_rasterizer_grows_and_stays_finite():
    """select -> decode -> rasterize -> loss -> stats -> Adam -> densify, a few steps on a tiny scene."""
    from hico_plugin.rasterizer import rasterize

    torch.manual_seed(0)
    cameras = ring_cameras()
    # Not progressive, so high-gradient offsets may grow into the next level right away (at init the
    # offsets are zero and same-level proposals land in the anchor's own, occupied cell).
    densify = DensifyConfig(start_step=2, interval=2, grad_threshold=1e-5)
    field = FieldConfig(progressive=False, densify=densify).setup(
        points=next(point_clouds())[0][:400], train_cameras=cameras, schedule_scale=1.0)
    optimizers = Optimizers(field.param_groups(), field_schedules(field))
    target = torch.full((24, 32, 3), 0.7)
    losses, grown = [], 0
    for step in range(1, 6):
        camera = cameras[step % len(cameras)].scaled(0.25)
        gaussians = field.decode(camera, field.select(camera, step))
        out = rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                        gaussians.colors, camera.viewmat, camera.K, camera.width, camera.height,
                        use_compile=False)
        out.means2d.retain_grad()
        loss = (out.rgb - target).abs().mean()
        loss.backward()
        losses.append(loss.item())
        field.accumulate_stats(gaussians, out.means2d.grad, out.radii, camera, step)
        optimizers.step(step)
        optimizers.zero_grad()
        for group, (kept_rows, num_new) in field.densify(step).items():
            optimizers.resize_group(group, field.param_groups()[group], kept_rows, num_new)
        grown += field.last_densify.get("grown", 0) if field.is_densify_step(step) else 0
    assert all(math.isfinite(v) for v in losses)
    assert grown > 0 and field.offset_grad_accum.shape[0] == field.num_anchors
    assert all(torch.isfinite(p).all() for ps in field.param_groups().values() for p in ps)


def test_sync_stats_sums_only_new_increments_over_workers():
    """Two workers with identical fields see different views; after sync both hold the stats a
    single worker seeing every view would hold, also across an adjustment that keeps some stats."""
    def worker():
        field = grow_prune_case()
        with torch.no_grad():
            field.offset_grad_accum[0, 4] = 1e-9  # an offset below the count threshold: carried over
            field.offset_denom[0, 4] = 1.0
        field.sync_stats(lambda increment: None)  # one worker alone: the preset stats are shared
        return field

    first = worker()
    workers, single = [first, copy.deepcopy(first)], copy.deepcopy(first)  # same MLP weights
    camera = camera_at((4.0, 4.0 - 2.5, 4.0), (4.0, 4.0, 4.0))

    def observe(field, seed, step):
        torch.manual_seed(seed)
        g = field.decode(camera, field.select(camera, step))
        field.accumulate_stats(g, torch.randn(len(g), 2), torch.ones(len(g)), camera, step)

    for step, seeds in ((590, (1, 2)), (700, (3, 4))):
        for field, seed in zip(workers, seeds):
            observe(field, seed, step)
        for seed in seeds:
            observe(single, seed, step)
        increments = [{name: getattr(f, name) - getattr(f, f"{name}_synced") for name in
                       ("opacity_accum", "anchor_denom", "offset_grad_accum", "offset_denom", "stat_views")}
                      for f in workers]
        for me, other in ((0, 1), (1, 0)):  # a fake all-reduce: add the other worker's increment
            pending = iter(list(increments[other].values()))
            workers[me].sync_stats(lambda t: t.add_(next(pending)))
        for name in ("opacity_accum", "offset_grad_accum", "offset_denom", "stat_views"):
            for field in workers:
                torch.testing.assert_close(getattr(field, name), getattr(single, name), msg=name)
        if step == 590:
            for field in (*workers, single):
                field.densify(600)
            assert workers[0].num_anchors == single.num_anchors
