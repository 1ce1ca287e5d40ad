"""The effects analysis against the built-in scenes' declared effects, and its pieces."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch

from hico_plugin.analysis.evidence import dataset_tracks
from hico_plugin.analysis.photo_gains import exposure_gains
from hico_plugin.data import DataParserConfig
from hico_plugin.errors import HicoError
from hico_plugin.metrics.colour import cc_psnr, nerfw_psnr
from hico_plugin.model.effects import analyze_effects, parse_effects
from hico_plugin.model.effects.exposure import AffineColour
from hico_plugin.scenes import SCENES
from hico_plugin.scenes.generate import generate_scene
from helpers_datasets import SMALL_DISTRICT, write_without_tracks

SMALL = dict(num_views=16, width=96, height=72, pixel_samples=1)
# effect declared by a scene -> the analysis finding that must agree with it. Sensor noise is left
# out: the noise estimate needs flat unclipped regions and reads texture as noise without a sky. A
# declared sky must be found as open sky (the environment finding's kind).
FINDING = {"exposure": "exposure", "multi_distance": "multi_distance"}
# a scene's own small capture where SMALL would not show what the analysis reads: the district's 16
# views of 81 blocks have no neighbouring views to measure parallax between
SIZE = {"district": SMALL_DISTRICT}
# scenes whose views see featureless ground hundreds of metres away (the district's obliques look
# 17-26 degrees down at ground out to ten flight heights): a distant background with or without sky
DISTANT_GROUND = {"district"}


def _combinations():
    for name in SCENES.names():
        declared = SCENES.get(name)().effects.declared()
        for values in itertools.product([True, False], repeat=len(declared)):
            yield name, dict(zip(declared, values))


def _load(name, effects):
    path = generate_scene(name, **{**SMALL, **SIZE.get(name, {})}, effects=effects)
    return path, DataParserConfig(data=path).setup()


@pytest.mark.parametrize("name,effects", list(_combinations()),
                         ids=lambda v: v if isinstance(v, str) else "-".join(k for k, on in v.items() if on) or "none")
def test_detector_agrees_with_declared_effects(name, effects):
    _, dataset = _load(name, effects)
    report = analyze_effects(dataset)
    for effect, finding in FINDING.items():  # undeclared effects are absent from the scene
        assert report.present(finding) == effects.get(effect, False), (effect, report.effects[finding].reason)
    environment = report.effects["environment"]
    open_sky = environment.present and environment.figures["kind"] == "open sky"
    assert open_sky == (effects.get("sky", False) or name in DISTANT_GROUND), environment.reason


def test_exposure_gains_match_the_generator():
    path, dataset = _load("pagoda", {"exposure": True, "sky": True, "sensor_noise": False})
    true = np.log2(np.array(json.loads((path / "scene.json").read_text())["exposure_gains"]))  # [C,3]
    tracks = dataset_tracks(dataset)
    assert tracks.source == "colmap tracks"
    gains, per_image = exposure_gains(dataset, tracks)
    true -= true.mean(axis=0)  # the analysis fixes the mean gain at 0
    error = np.abs(gains - true)  # stops, per channel
    assert error.max() < 0.1 and np.median(error) < 0.04
    assert per_image[0]["image"] == dataset.image_names[0]


def test_exposure_is_measured_when_the_colmap_points_carry_no_tracks(tmp_path):
    path = generate_scene("pagoda", num_views=40, width=192, height=144, pixel_samples=1,
                          effects={"exposure": True, "sky": True, "sensor_noise": False})
    dataset = DataParserConfig(data=write_without_tracks(path, tmp_path / "no_tracks")).setup()
    assert len(dataset.tracks) > 0 and len(dataset.tracks.observations()[0]) == 0
    tracks = dataset_tracks(dataset)
    assert tracks.source == "depth buffer"
    true = np.log2(np.array(json.loads((path / "scene.json").read_text())["exposure_gains"]))
    gains, _ = exposure_gains(dataset, tracks)
    assert np.abs(gains - (true - true.mean(axis=0))).max() < 0.1  # stops, every photo and channel
    report = analyze_effects(dataset)
    assert report.present("exposure"), report.effects["exposure"].reason


def test_appearance_starts_from_the_measured_gains():
    from hico_plugin.model.hico import HiCoModelConfig

    path, dataset = _load("pagoda", {"exposure": True, "sky": True, "sensor_noise": False})
    model = HiCoModelConfig(effects="auto,environment=off,lod=off").setup(dataset=dataset, total_steps=100)
    colour = model.effects["exposure"]
    true = np.log2(np.array(json.loads((path / "scene.json").read_text())["exposure_gains"]))
    true = (true - true.mean(axis=0))[dataset.train_indices.numpy()]
    start = torch.diagonal(colour.matrix.detach(), dim1=1, dim2=2).log2().numpy()
    assert np.abs(start - true).max() < 0.1
    # every effect forced: no analysis ran, and the exposure still starts from the measured gains
    forced = HiCoModelConfig(effects="environment=off,exposure=on,lod=off").setup(dataset=dataset, total_steps=100)
    assert forced.effects_report is None
    torch.testing.assert_close(forced.effects["exposure"].matrix, colour.matrix)
    assert torch.count_nonzero(colour.matrix.detach() - torch.diag_embed(torch.diagonal(
        colour.matrix.detach(), dim1=1, dim2=2))) == 0 and not colour.bias.any()
    # an unknown gain (too few shared points) starts at identity
    colour = AffineColour(2, torch.tensor([[float("nan")] * 3, [1.0, 0.0, -1.0]]))
    assert torch.equal(colour.matrix[0], torch.eye(3))
    assert torch.equal(colour.matrix[1], torch.diag(torch.tensor([2.0, 1.0, 0.5])))


def test_cc_psnr_discounts_an_affine_colour_change_and_nerfw_scores_the_other_half():
    torch.manual_seed(0)
    render = torch.rand(24, 32, 3) * 0.8
    photo = (render @ torch.tensor([[1.2, 0.05, 0.0], [0.0, 0.9, 0.0], [0.0, 0.0, 1.1]]).T + 0.03).clamp(0, 1)
    assert float(cc_psnr(render, photo)) > 60
    assert float(nerfw_psnr(render, photo)) > 60
    noisy = (photo + 0.05 * torch.randn_like(photo)).clamp(0, 1)
    assert float(nerfw_psnr(render, noisy)) < float(cc_psnr(render, noisy)) + 0.5


def test_affine_colour_is_identity_for_views_without_a_training_slot():
    colour = AffineColour(3)
    rgb = torch.rand(4, 5, 3)
    with torch.no_grad():
        colour.matrix[1] *= 2.0
    assert torch.equal(colour(rgb, -1), rgb)
    assert torch.allclose(colour(rgb, 1), 2 * rgb)


def test_effects_spec_parsing():
    assert parse_effects("auto") == {"environment": "auto", "exposure": "auto", "lod": "auto"}
    assert parse_effects("auto,environment=off")["environment"] == "off"
    assert parse_effects("auto,sky=off")["environment"] == "off"  # the environment's old name
    with pytest.raises(HicoError, match="unknown effect 'fog'"):
        parse_effects("fog=on")
    with pytest.raises(HicoError, match="expected 'auto'"):
        parse_effects("environment")


def test_bench_effects_axis_plans_one_run_per_effects_value(tmp_path):
    from hico_plugin.bench.matrix import BENCH_MODES, plan

    import dataclasses

    bench = dataclasses.replace(BENCH_MODES["effects"], output_dir=tmp_path).resolved()
    runs = plan(bench)
    assert len(runs) == len(bench.scenes) * len(bench.effects)
    by_effects = {r["effects"]: r for r in runs if r["scene"] == "tiny"}
    assert by_effects["auto"]["preset"] == "hico-gs-lite"
    spec = "environment=on,exposure=off,lod=off"
    assert by_effects[spec]["config"].model.effects == spec
    assert len({r["run_dir"] for r in runs}) == len(runs)  # every effects value trains its own run
