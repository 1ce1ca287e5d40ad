"""The viewer's config loads without viser, and config.yml files naming its old module still load."""

import subprocess
import sys
from pathlib import Path

import hico_plugin.presets  # noqa: F401 - registers the config classes
from hico_plugin.engine.config_io import load_config
from hico_plugin.viewer.config import ViewerConfig

PRESETS = Path(__file__).resolve().parents[2] / "configs"


def test_a_training_run_without_a_viewer_never_imports_viser():
    code = ("import sys, hico_plugin.cli.train; from hico_plugin.viewer import ViewerConfig; "
            "print('viser' in sys.modules)")
    shown = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert shown.strip() == "False"


def test_the_package_still_exports_the_viewer_and_its_config():
    from hico_plugin import viewer

    assert viewer.ViewerConfig is ViewerConfig
    assert viewer.Viewer.__module__ == "hico_plugin.viewer.viewer"
    assert sorted(viewer.__all__) == viewer.__all__ and "attach_viewer" in viewer.__all__


def test_a_config_naming_the_viewer_module_of_older_runs_loads(tmp_path):
    text = (PRESETS / "hico-gs-lite.yml").read_text()
    today = "!dataclass:hico_plugin.viewer.config.ViewerConfig"
    assert today in text
    (tmp_path / "config.yml").write_text(text.replace(today, "!dataclass:hico_plugin.viewer.viewer.ViewerConfig"))
    loaded = load_config(tmp_path / "config.yml")
    assert type(loaded.viewer) is ViewerConfig and loaded.viewer == ViewerConfig()
