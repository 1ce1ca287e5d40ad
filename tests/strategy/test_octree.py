"""The octree strategy: statistics, growing and pruning, the budget, resizing the optimizers, workers' sums."""

import copy
import math

import pytest
import torch

from hico_plugin.engine.optimizers import Optimizers
from hico_plugin.field import AnchorField, FieldConfig
from hico_plugin.strategy import DensifyConfig
from helpers_field import camera_at, field_schedules, hand_field, make_field, point_clouds, ring_cameras


def with_strategy(field: AnchorField):
    """The field and the strategy its config names (the model builds it so)."""
    return field, field.config.densify.setup(field=field, schedule_scale=field.schedule_scale)


def test_accumulate_stats_sums_per_offset():
    field, strategy = with_strategy(make_field())
    torch.manual_seed(1)
    with torch.no_grad():
        field.anchor_features.normal_()
    camera = ring_cameras()[0]
    g = field.decode(camera, field.select(camera, 10))
    radii = torch.ones(len(g), dtype=torch.int32)
    radii[::2] = 0  # not drawn: no gradient statistic
    grad = torch.zeros(len(g), 2)
    grad[:, 0] = 1.0  # one pixel unit in x = width / 2 NDC units
    strategy.step_post_backward(field, g, grad, radii, camera, step=10)
    drawn = radii > 0
    expected = torch.zeros_like(strategy.offset_grad_accum)
    expected[g.anchor_ids[drawn], g.child_ids[drawn]] = camera.width / 2
    torch.testing.assert_close(strategy.offset_grad_accum, expected)
    assert torch.equal(strategy.offset_denom, (expected > 0).float())
    torch.testing.assert_close(strategy.opacity_accum[g.visible_ids], g.raw_opacities.clamp_min(0).sum(1))
    assert int(strategy.anchor_denom.sum()) == len(g.visible_ids) and int(strategy.stat_views) == 1
    strategy.step_post_backward(field, g, grad, radii, camera, step=10**6)  # past densify.stop_step: ignored
    assert int(strategy.stat_views) == 1


@pytest.mark.parametrize("radii_shape", [(0,), (0, 2)])
def test_accumulate_stats_of_a_view_that_decodes_nothing(radii_shape):
    field, strategy = with_strategy(make_field())
    with torch.no_grad():
        field.decoder.mlp_opacity[-1].bias.fill_(-10.0)  # every child transparent: none is kept
    camera = ring_cameras()[0]
    g = field.decode(camera, field.select(camera, 10))
    assert len(g) == 0 and len(g.visible_ids) > 0
    strategy.step_post_backward(field, g, torch.zeros(0, 2), torch.zeros(radii_shape, dtype=torch.int32), camera, step=10)
    assert int(strategy.stat_views) == 1 and float(strategy.offset_denom.sum()) == 0.0
    assert int(strategy.anchor_denom.sum()) == len(g.visible_ids)


def grow_prune_case(**densify_changes):
    """(field, strategy): anchor 0 (level 0, cell 4,4,4) has high-gradient offsets; anchor 1 never shows
    opacity."""
    field, strategy = with_strategy(hand_field([[4, 4, 4], [0, 0, 0]], [0, 0], [[4, 4, 1.5]], progressive=False,
                                               densify=DensifyConfig(**densify_changes)))
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
        strategy.offset_denom[0] = 50.0
        mean_grads = torch.tensor([1.05 * tau, 2.0 * tau * growth, 1.05 * tau, 1.05 * tau, 0.5 * tau])
        strategy.offset_grad_accum[0] = mean_grads * 50.0
        strategy.opacity_accum[0] = 40.0
        strategy.anchor_denom[:] = 50.0
        strategy.stat_views.fill_(100)
    return field, strategy


def test_growing_and_pruning_on_a_hand_built_case():
    field, strategy = grow_prune_case()
    assert strategy.step_post_update(field, 550) == {}  # not on the interval
    changes = strategy.step_post_update(field, 600)
    assert set(changes) == {"anchor", "offset", "anchor_feat", "scaling"}
    kept_rows, num_new = changes["anchor"]
    assert kept_rows.tolist() == [0] and num_new == 2  # anchor 1 pruned, two cells grown
    assert strategy.last_adjustment["grown"] == 2 and strategy.last_adjustment["pruned"] == 1
    assert strategy.last_adjustment["grown_level_0"] == 1 and strategy.last_adjustment["grown_level_1"] == 1
    torch.testing.assert_close(field.anchors.detach(), torch.tensor([[4.0, 4, 4], [5, 4, 4], [4, 4.5, 4]]))
    assert field.levels.tolist() == [0, 0, 1]
    torch.testing.assert_close(field.anchor_features[1], torch.arange(32.0))  # max over its source
    assert torch.equal(field.anchor_features[2], torch.zeros(32))  # next level: zeros
    torch.testing.assert_close(field.log_scaling[1:, 0], torch.log(torch.tensor([1.0, 0.5])))
    assert (field.log_scaling[:, 3:] <= 0.05 + 1e-7).all()  # clamp on prune
    assert field.extra_level.tolist() == pytest.approx([0.01, 0.0, 0.0])
    # Statistics: eligible offsets and judged anchors reset; new rows zero.
    assert strategy.offset_denom.abs().sum() == 0 and strategy.anchor_denom.abs().sum() == 0
    assert field.offsets.shape == (3, 5, 3) and int(strategy.stat_views) == 0


@pytest.mark.parametrize("budget, grown", [
    ({}, [[5.0, 4, 4], [4, 4.5, 4]]), ({"max_anchors": 3}, [[5.0, 4, 4], [4, 4.5, 4]]),
    ({"max_anchors": 2}, [[4.0, 4.5, 4]]), ({"max_anchors_per_seed": 1.0}, [[4.0, 4.5, 4]]),
    ({"max_anchors": 1, "max_anchors_per_seed": 1.5}, [])])
def test_an_anchor_budget_keeps_the_largest_gradient_cells_that_fit_after_pruning(budget, grown):
    # The level-1 cell's offset gradient (2 tau u) beats the level-0 cell's (1.05 tau); anchor 1 is
    # pruned in the same adjustment, so a budget of 2 (absolute, or 1x the 2 seed anchors) leaves room
    # for one new cell.
    field, strategy = grow_prune_case(**budget)
    strategy.step_post_update(field, 600)
    assert strategy.last_adjustment["pruned"] == 1
    torch.testing.assert_close(field.anchors.detach(), torch.tensor([[4.0, 4, 4], *grown]))
    limit = field.config.densify.budget(2)
    assert limit is None or int(field.drawn.sum()) <= limit


def test_the_anchor_budget_is_the_smaller_of_the_count_and_the_multiple_of_the_seed_anchors():
    assert DensifyConfig().budget(1000) is None
    assert DensifyConfig(max_anchors=5000).budget(1000) == 5000
    assert DensifyConfig(max_anchors_per_seed=3.0).budget(1000) == 3000
    assert DensifyConfig(max_anchors=2500, max_anchors_per_seed=3.0).budget(1000) == 2500


def test_densify_result_drives_optimizer_resize_and_resume():
    field, strategy = grow_prune_case()
    optimizers = Optimizers(field.param_groups(), field_schedules(field))
    field.anchor_features.sum().mul(0).add(field.anchor_features[0].sum()).backward()
    optimizers.step(0)
    old_moment = optimizers.optimizers["anchor_feat"].state[field.anchor_features]["exp_avg"].clone()
    for group, (kept_rows, num_new) in strategy.step_post_update(field, 600).items():
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
    # ... and the strategy beside it takes the grown statistics' shapes.
    _, fresh_strategy = with_strategy(hand_field([[4, 4, 4], [0, 0, 0]], [0, 0], [[4, 4, 1.5]], progressive=False))
    fresh_strategy.load_state_dict(strategy.state_dict())
    for name, a in strategy.state_dict().items():
        assert torch.equal(a, fresh_strategy.state_dict()[name]), name
    assert fresh_strategy.offset_grad_accum.shape == (3, 5)


def test_nothing_to_change_returns_empty_dict():
    field, strategy = with_strategy(hand_field([[4, 4, 4], [0, 0, 0]], [0, 0], [[4, 4, 1.5]], densify=DensifyConfig()))
    strategy.stat_views.fill_(100)
    assert strategy.step_post_update(field, 600) == {} and strategy.last_adjustment["grown"] == 0
    assert field.num_anchors == 2


def test_training_loop_with_the_rasterizer_grows_and_stays_finite():
    """select -> decode -> rasterize -> loss -> stats -> Adam -> densify, a few steps on a tiny scene."""
    from hico_plugin.rasterizer import rasterize

    torch.manual_seed(0)
    cameras = ring_cameras()
    # Not progressive, so high-gradient offsets may grow into the next level right away (at init the
    # offsets are zero and same-level proposals land in the anchor's own, occupied cell).
    densify = DensifyConfig(start_step=2, interval=2, grad_threshold=1e-5)
    field, strategy = with_strategy(FieldConfig(progressive=False, densify=densify).setup(
        points=next(point_clouds())[0][:400], train_cameras=cameras, schedule_scale=1.0))
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
        strategy.step_post_backward(field, gaussians, out.means2d.grad, out.radii, camera, step)
        optimizers.step(step)
        optimizers.zero_grad()
        for group, (kept_rows, num_new) in strategy.step_post_update(field, step).items():
            optimizers.resize_group(group, field.param_groups()[group], kept_rows, num_new)
        grown += strategy.last_adjustment.get("grown", 0) if strategy.is_adjust_step(step) else 0
    assert all(math.isfinite(v) for v in losses)
    assert grown > 0 and strategy.offset_grad_accum.shape[0] == field.num_anchors
    assert all(torch.isfinite(p).all() for ps in field.param_groups().values() for p in ps)


def test_sync_stats_sums_only_new_increments_over_workers():
    """Two workers with identical fields see different views; after sync both hold the stats a
    single worker seeing every view would hold, also across an adjustment that keeps some stats."""
    def worker():
        field, strategy = grow_prune_case()
        with torch.no_grad():
            strategy.offset_grad_accum[0, 4] = 1e-9  # an offset below the count threshold: carried over
            strategy.offset_denom[0, 4] = 1.0
        strategy.sync(lambda increment: None)  # one worker alone: the preset stats are shared
        return field, strategy

    first = worker()
    workers, single = [first, copy.deepcopy(first)], copy.deepcopy(first)  # same MLP weights
    camera = camera_at((4.0, 4.0 - 2.5, 4.0), (4.0, 4.0, 4.0))

    def observe(pair, seed, step):
        field, strategy = pair
        torch.manual_seed(seed)
        g = field.decode(camera, field.select(camera, step))
        strategy.step_post_backward(field, g, torch.randn(len(g), 2), torch.ones(len(g)), camera, step)

    for step, seeds in ((590, (1, 2)), (700, (3, 4))):
        for pair, seed in zip(workers, seeds):
            observe(pair, seed, step)
        for seed in seeds:
            observe(single, seed, step)
        increments = [{name: getattr(s, name) - getattr(s, f"{name}_synced") for name in
                       ("opacity_accum", "anchor_denom", "offset_grad_accum", "offset_denom", "stat_views")}
                      for _, s in workers]
        for me, other in ((0, 1), (1, 0)):  # a fake all-reduce: add the other worker's increment
            pending = iter(list(increments[other].values()))
            workers[me][1].sync(lambda t: t.add_(next(pending)))
        for name in ("opacity_accum", "offset_grad_accum", "offset_denom", "stat_views"):
            for _, strategy in workers:
                torch.testing.assert_close(getattr(strategy, name), getattr(single[1], name), msg=name)
        if step == 590:
            for field, strategy in (*workers, single):
                strategy.step_post_update(field, 600)
            assert workers[0][0].num_anchors == single[0].num_anchors


def test_bytes_per_anchor_are_the_statistics_rows():
    field, strategy = with_strategy(make_field())
    rows = [t for t in strategy.buffers() if t.dim() and t.shape[0] == field.num_anchors]
    assert strategy.bytes_per_anchor() * field.num_anchors == sum(t.numel() * t.element_size() for t in rows)
    strategy.keep(torch.arange(0, field.num_anchors, 2))
    assert all(t.shape[0] == len(range(0, field.num_anchors, 2)) for t in strategy.buffers() if t.dim())
