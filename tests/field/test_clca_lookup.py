"""CLCA lookup on the built-in scenes: the levels nest (>= 95 % of parents found) and the per-level table."""

import pytest
import torch

from hico_plugin.cameras import Cameras
from hico_plugin.data.parser import DataParserConfig
from hico_plugin.field import ContextConfig, FieldConfig
from hico_plugin.field.lookup_stats import format_table, lookup_table
from hico_plugin.scenes.generate import generate_scene

SMALL = dict(num_views=16, width=64, height=48, pixel_samples=1, sparse_points=1500)


def scene_field(tmp_path_factory, name: str, rule: str):
    root = generate_scene(name, tmp_path_factory.mktemp(name) / name, **SMALL)
    data = DataParserConfig(data=root).parse()
    train = data.train_indices
    cameras = data.cameras
    train_cameras = Cameras(cameras.viewmats[train], cameras.Ks[train], cameras.widths[train],
                            cameras.heights[train])
    field = FieldConfig(context=ContextConfig(parent_rule=rule)).setup(
        points=data.points, train_cameras=train_cameras, num_train_cameras=len(train))
    views = [cameras[i] for i in range(len(cameras))]
    return field, views


@pytest.mark.parametrize("name", ["city-block", "pagoda"])
def test_parent_found_for_95_percent_of_visible_anchors(tmp_path_factory, name):
    torch.manual_seed(0)
    field, views = scene_field(tmp_path_factory, name, "trilinear")
    table = lookup_table(field, views)
    print(format_table(table))
    assert sum(row["visible"] for row in table[1:]) > 0
    for row in table[1:]:
        if row["visible"]:
            assert row["parent_found"] >= 0.95, f"level {row['level']}: {row}"
    assert table[0]["parent_found"] is None and table[-1]["child_found"] is None
    # At init f = 0, so ||f_hat - f|| / ||f|| is undefined, reported as None.
    assert all(row["adjustment"] is None for row in table)


def test_paper_rule_misses_and_adjustment_is_reported(tmp_path_factory):
    torch.manual_seed(0)
    field, views = scene_field(tmp_path_factory, "city-block", "paper")
    table = lookup_table(field, views[:4])
    assert min(row["parent_found"] for row in table[1:] if row["visible"]) < 0.9  # the gap
    with torch.no_grad():
        field.anchor_features.normal_()
        field.context.mlp[2].weight.normal_(std=0.1)
    table = lookup_table(field, views[:4])
    assert all(row["adjustment"] > 0 for row in table if row["visible"])
