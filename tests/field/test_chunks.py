"""View culling by chunks: ``AnchorField.select`` tests the chunks a view may see, then their anchors;
the result must be the LOD + frustum rule's over every anchor, in every case the bounds may get wrong."""

import math

import numpy as np
import pytest
import torch

from hico_plugin.cameras import Camera, Cameras
from hico_plugin.field import FieldConfig
from hico_plugin.field.chunks import AnchorChunks, morton_codes
from hico_plugin.field.field import anchor_radii
from hico_plugin.field.lod import frustum_visible, lod_visible
from hico_plugin.scenes.orbits import look_at as orbit_look_at

K = torch.tensor([[200.0, 0.0, 80.0], [0.0, 180.0, 60.0], [0.0, 0.0, 1.0]])


def _camera(eye, target, index=0) -> Camera:
    viewmat = orbit_look_at(np.array([eye], np.float64), np.array([target], np.float64))[0]
    return Camera(torch.from_numpy(viewmat).float(), K, 160, 120, index)


def _district_field(offset=(0.0, 0.0, 0.0), chunk_size=64, seed=0):
    """A flat 'district' of points 200 x 200 x 30 (shifted by offset) and a drone grid of cameras."""
    gen = torch.Generator().manual_seed(seed)
    points = torch.rand(20000, 3, generator=gen) * torch.tensor([200.0, 200.0, 30.0]) - torch.tensor([100.0, 100.0, 0.0])
    points += torch.tensor(offset)
    eyes = [(x + offset[0], y + offset[1], 60.0 + offset[2]) for x in (-80, 0, 80) for y in (-80, 0, 80)]
    cams = [_camera(e, (e[0] + 10, e[1], offset[2]), i) for i, e in enumerate(eyes)]
    cameras = Cameras(torch.stack([c.viewmat for c in cams]), K.expand(len(cams), 3, 3).clone(),
                      torch.full((len(cams),), 160), torch.full((len(cams),), 120))
    field = FieldConfig(chunk_size=chunk_size).setup(points=points, train_cameras=cameras)
    with torch.no_grad():  # trained-looking values: eps and scales that differ per anchor
        field.extra_level.uniform_(0.0, 0.9, generator=gen)
        field.log_scaling.add_(torch.randn(field.log_scaling.shape, generator=gen) * 0.5)
    return field


def _rule(field, camera, step=None, distance_scale=1.0) -> torch.Tensor:
    """The per-anchor rule over every anchor, as selection applied it before chunks: [V] ascending."""
    positions, log_scaling = field.anchors.detach(), field.log_scaling.detach()
    seen = lod_visible(positions, field.levels, field.extra_level, camera.center, field.grid,
                       field.active_levels(step), distance_scale)
    seen &= frustum_visible(positions, anchor_radii(log_scaling), camera, field.config.near, field.config.frustum_margin)
    return seen.nonzero().squeeze(1)


def _views(offset=(0.0, 0.0, 0.0)):
    o = torch.tensor(offset).tolist()
    at = lambda x, y, z: (x + o[0], y + o[1], z + o[2])  # noqa: E731
    return [
        _camera(at(0, 0, 150), at(1, 0, 0)),          # nadir, the whole district
        _camera(at(-90, -90, 40), at(0, 0, 0)),       # oblique from a corner
        _camera(at(30, 20, 1.7), at(60, 20, 1.7)),    # street level, inside the cloud
        _camera(at(0, 0, 15), at(0, 0, 80)),          # looking up: near plane straddles the cloud
        _camera(at(500, 500, 50), at(600, 600, 50)),  # looking away: nothing
        _camera(at(-99, 99, 29.9), at(-99, 0, 0)),    # at the cloud's corner
    ]


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (1.4e5, -2.3e5, 310.0)])
def test_select_equals_the_rule_over_every_anchor(offset):
    """Every view kind, every active level count, the viewer's LOD scale; also at city-scale
    coordinates (1e5 units), where float32 rounding of the per-anchor test is largest."""
    field = _district_field(offset)
    assert field.chunks().low.shape[0] > 100
    for camera in _views(offset):
        for step in (None, 0, 10**9):
            for scale in (1.0, 0.3, 4.0):
                picked = field.select(camera, step, scale)
                assert torch.equal(picked, _rule(field, camera, step, scale)), (camera.center, step, scale)


def test_a_view_tests_only_the_chunks_it_may_see():
    field = _district_field()
    street = _views()[2]
    chunks = field.chunks()
    candidates = chunks.candidates(street, field.grid, field.active_levels(None), 1.0, field.config.near,
                                   field.config.frustum_margin)
    assert candidates.numel() < 0.35 * field.num_anchors
    away = chunks.candidates(_views()[4], field.grid, field.active_levels(None), 1.0, field.config.near,
                             field.config.frustum_margin)
    assert away.numel() == 0 and field.select(_views()[4]).numel() == 0


def test_bounds_follow_updates_seen_and_unseen():
    """Rows moved by a row-sparse step (after_update widens their chunks), rows moved behind the
    field's back (a version change recomputes the bounds), new eps (densification's)."""
    field = _district_field()
    views = _views()
    field.select(views[0])
    gen = torch.Generator().manual_seed(3)
    rows = torch.randperm(field.num_anchors, generator=gen)[:500].sort().values
    with torch.no_grad():
        field.anchors[rows] += torch.randn(500, 3, generator=gen) * 20
        field.log_scaling[rows] += 2.0
    field.anchors.grad = torch.sparse_coo_tensor(rows[None], torch.ones(500, 3), field.anchors.shape)
    field.log_scaling.grad = torch.sparse_coo_tensor(rows[None], torch.ones(500, 6), field.log_scaling.shape)
    field.after_update()
    for camera in views:
        assert torch.equal(field.select(camera), _rule(field, camera))
    with torch.no_grad():
        field.anchors[:100] -= 50.0
        field.extra_level += 1.0
    for camera in views:
        assert torch.equal(field.select(camera), _rule(field, camera))


def test_nonfinite_rows_hide_no_other_anchor():
    field = _district_field()
    views = _views()
    with torch.no_grad():
        field.anchors[5] = float("nan")
        field.log_scaling[7] = float("inf")
        field.extra_level[9] = float("nan")
    for camera in views:
        assert torch.equal(field.select(camera), _rule(field, camera))


def test_empty_and_tiny_fields():
    field = _district_field()
    for rows in (torch.zeros(0, dtype=torch.long), torch.tensor([3])):
        chunks = AnchorChunks.build(field.anchors.detach()[rows], field.levels[rows], field.extra_level[rows],
                                    anchor_radii(field.log_scaling.detach()[rows]), field.grid, 64)
        got = chunks.candidates(_views()[0], field.grid, 5, 1.0, 0.01, 0.15)
        assert got.numel() <= rows.numel()


def test_morton_order_keeps_neighbours_together():
    field = _district_field()
    grid = field.grid
    codes = morton_codes(field.anchors, grid)
    assert codes.min() >= 0 and codes.max() < 1 << 30
    chunks = field.chunks()
    extent = (chunks.high - chunks.low).norm(dim=1)
    assert float(extent.median()) < 0.25 * grid.cube_size * math.sqrt(3)


def test_bytes_per_anchor_are_the_tensors_rows():
    field = _district_field()
    field.chunks()
    memory = field.bytes_per_anchor()
    per_anchor = [t for t in list(field.parameters()) + list(field.buffers()) if t.dim() and t.shape[0] == field.num_anchors]
    held = sum(t.numel() * t.element_size() for t in per_anchor) / field.num_anchors
    chunks = field.chunks()
    held += (chunks.order.numel() + chunks.chunk_of.numel()) * 8 / field.num_anchors
    assert memory["total"] == memory["parameters"] * 3 + memory["buffers"] + memory["culling"]
    assert held + 2 * memory["parameters"] == memory["total"]  # Adam's two moments are not held yet


def test_counters_follow_the_anchors_without_counting_every_step():
    field = _district_field()
    first = field.stats()
    assert field.stats() == first and first["num_anchors"] == field.num_anchors
    field.keep(torch.arange(0, field.num_anchors, 2))
    kept = field.stats()
    assert kept["num_anchors"] == field.num_anchors
    assert sum(v for k, v in kept.items() if k.startswith("anchors/level_")) == field.num_anchors
    field.drawn[:5] = False  # in place, as densification hides ancestors
    assert field.stats()["anchors/context_only"] == 5
