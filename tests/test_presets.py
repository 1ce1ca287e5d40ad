"""configs/*.yml are the resolved PRESETS, so a change of a default cannot leave them stale."""

from __future__ import annotations

from pathlib import Path

from hico_plugin.engine.config_io import load_config
from hico_plugin.presets import PRESETS, write_preset_files

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_configs_equal_the_resolved_presets(tmp_path):
    write_preset_files(str(tmp_path))
    written = sorted(p.name for p in tmp_path.glob("*.yml"))
    assert sorted(p.name for p in CONFIGS.glob("*.yml")) == written
    for name in written:
        # Compared as text: the files are what a user reads; regenerate them with write_preset_files.
        assert (CONFIGS / name).read_text() == (tmp_path / name).read_text(), (
            f"configs/{name} is stale; regenerate with python -c \"from hico_plugin.presets import "
            f"write_preset_files; write_preset_files('configs')\"")


def test_configs_load_back_as_the_presets():
    for path in CONFIGS.glob("*.yml"):
        assert load_config(path) == PRESETS[path.stem][1], path.name


def test_a_learning_rate_is_a_command_line_override():
    from hico_plugin.cli.train import parse

    config = parse(["hico-gs-lite", "--model.optimizers.mlp_color.lr-init", "0.01"])
    assert config.model.optimizers["mlp_color"].lr_init == 0.01
    assert config.model.optimizers["mlp_color"].lr_final == PRESETS["hico-gs-lite"][1].model.optimizers["mlp_color"].lr_final
    assert parse(["hico-gs-lite"]).model.optimizers["mlp_color"].lr_init == 0.008  # the preset is not edited
