"""config.yml: the whole config tree round-trips through save_config / load_config."""

import enum
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from hico_plugin.config import InstantiateConfig
from hico_plugin.engine import TrainerConfig, load_config, save_config
from hico_plugin.errors import HicoError


class Kind(enum.Enum):
    MEAN = "mean"
    MAX = "max"


@dataclass
class Inner(InstantiateConfig):
    kind: Kind = Kind.MEAN
    sizes: tuple[int, ...] = (1, 2, 3)
    weights: dict[str, float] = field(default_factory=lambda: {"rgb": 1.0, "normal": 0.05})


@dataclass
class Outer(InstantiateConfig):
    inner: Inner = field(default_factory=Inner)
    points: Path | None = None
    layers: list[Inner] = field(default_factory=list)


def test_round_trip_keeps_types(tmp_path):
    config = TrainerConfig(
        output_dir=Path("outputs/x"), max_steps=123,
        model=Outer(inner=Inner(kind=Kind.MAX, sizes=(4,)), points=Path("/data/p.ply"), layers=[Inner()]),
    )
    path = save_config(config, tmp_path / "config.yml")
    loaded = load_config(path)
    assert loaded == config
    assert type(loaded.model) is Outer and isinstance(loaded.output_dir, Path)
    assert loaded.model.inner.sizes == (4,) and loaded.model.inner.kind is Kind.MAX
    assert "!dataclass:test_engine_config.Outer" in path.read_text()


def test_missing_fields_take_defaults_and_unknown_fields_are_errors(tmp_path):
    path = tmp_path / "config.yml"
    path.write_text("!dataclass:hico_plugin.engine.trainer.TrainerConfig\nmax_steps: 7\n")
    assert load_config(path) == TrainerConfig(max_steps=7)
    path.write_text("!dataclass:hico_plugin.engine.trainer.TrainerConfig\nmax_stepz: 7\n")
    with pytest.raises(HicoError, match=r"config.yml: unknown field\(s\) max_stepz"):
        load_config(path)
    path.write_text("!dataclass:hico_plugin.nowhere.Config\n")
    with pytest.raises(HicoError, match="'hico_plugin.nowhere.Config' is not a registered config class"):
        load_config(path)
    path.write_text("max_steps: [\n")
    with pytest.raises(HicoError, match="not valid YAML"):
        load_config(path)


def test_run_config_paths_are_written_absolute(tmp_path, monkeypatch):
    """A run's config.yml reloads from any working directory (hico-eval --load-config elsewhere)."""
    from hico_plugin.data.parser import DataParserConfig
    from hico_plugin.engine.config_io import load_config, save_config

    monkeypatch.chdir(tmp_path)
    config = DataParserConfig(data=Path("data/site"))
    save_config(config, tmp_path / "run.yml", absolute_paths=True)
    save_config(config, tmp_path / "preset.yml")
    assert load_config(tmp_path / "run.yml").data == tmp_path / "data" / "site"
    assert load_config(tmp_path / "preset.yml").data == Path("data/site")


def test_a_run_from_before_losses_became_a_mapping_still_loads(tmp_path):
    import hico_plugin.presets  # noqa: F401  (the config classes a run's config.yml names)
    from hico_plugin.losses import DNGCLossConfig, PhotometricLossConfig

    path = tmp_path / "config.yml"
    path.write_text("!dataclass:hico_plugin.model.hico.HiCoModelConfig\n"
                    "losses: !dataclass:hico_plugin.losses.LossesConfig\n"
                    "  rgb: !dataclass:hico_plugin.losses.photometric.PhotometricLossConfig\n    ssim_lambda: 0.3\n"
                    "  dngc: !dataclass:hico_plugin.losses.dngc.DNGCLossConfig\n    enabled: false\n")
    assert load_config(path).losses == {"rgb": PhotometricLossConfig(ssim_lambda=0.3),
                                         "dngc": DNGCLossConfig(enabled=False)}


def test_a_run_from_before_orientation_and_kept_ancestors_loads_as_it_was_trained(tmp_path):
    import hico_plugin.presets  # noqa: F401  (the config classes a run's config.yml names)
    from hico_plugin.presets import all_presets

    path = tmp_path / "config.yml"
    path.write_text("!dataclass:hico_plugin.data.parser.DataParserConfig\ndownscale: 2\n")
    assert load_config(path).orient is False  # its scene frame was not rotated
    path.write_text("!dataclass:hico_plugin.data.parser.DataParserConfig\norient: true\n")
    assert load_config(path).orient_method == "up"  # it was rotated by the cameras' mean up
    path.write_text("!dataclass:hico_plugin.field.densify.DensifyConfig\ninterval: 100\n")
    assert load_config(path).keep_ancestors is False and load_config(path).draw_ancestors is True
    # a config written today keeps today's values
    save_config(all_presets()["hico-gs-lite"][1], path)
    loaded = load_config(path)
    assert loaded.data.orient is True and loaded.model.field.densify.keep_ancestors is True
    assert loaded.model.field.densify.draw_ancestors is False
    assert loaded.data.orient_method == "manhattan"
    # a whole run's file from before: its data source (a subclass of the parser config) without orient
    text = path.read_text()
    assert "\n  orient: true\n" in text and "\n      keep_ancestors: true\n" in text
    path.write_text(text.replace("\n  orient: true\n", "\n").replace("\n      keep_ancestors: true\n", "\n"))
    old = load_config(path)
    assert type(old.data).__name__ == "DataSourceConfig"
    assert old.data.orient is False and old.model.field.densify.keep_ancestors is False


def test_a_run_from_before_the_environment_was_renamed_still_loads(tmp_path):
    """The environment was the "sky" (field ``sky``, class SkyConfig in model/ and then in model/effects/)
    and the background a fixed colour; a config.yml of either time loads as what it trained."""
    import hico_plugin.presets  # noqa: F401  (the config classes a run's config.yml names)
    from hico_plugin.model.effects.environment import EnvironmentConfig

    path = tmp_path / "config.yml"
    for home in ("hico_plugin.model.sky", "hico_plugin.model.effects.sky"):
        path.write_text("!dataclass:hico_plugin.model.hico.HiCoModelConfig\n"
                        f"sky: !dataclass:{home}.SkyConfig\n  hidden_dim: 16\n")
        loaded = load_config(path)
        assert loaded.environment == EnvironmentConfig(hidden_dim=16, stride=1) and loaded.learn_background is False


def test_parent_rule_is_an_enum_that_reads_and_writes_its_name(tmp_path):
    """ParentRule knows whether the levels nest; config.yml files name it, old ones as a plain string."""
    import hico_plugin.presets  # noqa: F401  (the config classes a run's config.yml names)
    from hico_plugin.field.context import ContextConfig
    from hico_plugin.field.context_graph import ParentRule

    assert ParentRule.trilinear.nests and not ParentRule.paper.nests
    path = tmp_path / "config.yml"
    save_config(ContextConfig(parent_rule="paper"), path)
    assert "parent_rule: !enum:hico_plugin.field.context_graph.ParentRule 'paper'" in path.read_text()
    assert load_config(path).parent_rule is ParentRule.paper
    path.write_text("!dataclass:hico_plugin.field.context.ContextConfig\nparent_rule: paper\n")
    assert load_config(path).parent_rule is ParentRule.paper
    with pytest.raises(HicoError, match="parent_rule: expected one of trilinear, paper, got 'ceil'"):
        ContextConfig(parent_rule="ceil")
