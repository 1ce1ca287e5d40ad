"""Plug-ins from outside: a real distribution declaring a ``hico_plugin.components`` entry point adds
an aggregator and a preset that ``hico-train`` lists and trains; a broken one is one warning."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).parent / "plugin_example"
REPO = Path(__file__).resolve().parents[1]


def _run(args: list[str], site: Path, cwd: Path) -> subprocess.CompletedProcess:
    # The installed plug-in is visible only through PYTHONPATH, as a --target install would be.
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(site)]))
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def _cli(name: str) -> str:
    return str(Path(sys.executable).with_name(name))


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The example plug-in pip-installed (a real wheel build: dist-info with entry_points.txt)."""
    work = tmp_path_factory.mktemp("plugin")
    shutil.copytree(EXAMPLE, work / "src")  # setuptools writes build/ and egg-info beside the sources
    target = work / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--no-index", "--target", str(target), str(work / "src")], check=True, timeout=300)
    entry_points = next(target.glob("hico_example_plugin-*.dist-info")) / "entry_points.txt"
    assert "[hico_plugin.components]" in entry_points.read_text()
    return target


def test_plugin_components_are_registered_by_name(site, tmp_path):
    code = ("from hico_plugin.field.context import CONTEXT_AGGREGATORS; "
            "from hico_plugin.presets import all_presets; "
            "print(CONTEXT_AGGREGATORS.names(), sorted(all_presets()))")
    result = _run([sys.executable, "-c", code], site, tmp_path)
    assert result.returncode == 0, result.stderr
    assert "'gated-mean'" in result.stdout and "'example-gated'" in result.stdout
    without = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                             env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert without.returncode == 0 and "gated-mean" not in without.stdout


def test_hico_train_lists_and_trains_the_plugin_preset(site, tmp_path):
    listed = _run([_cli("hico-train"), "--help"], site, tmp_path)
    assert listed.returncode == 0, listed.stderr
    assert "example-gated" in listed.stdout

    out = tmp_path / "run"
    trained = _run([_cli("hico-train"), "example-gated", "--scene", "tiny", "--max-steps", "2", "--vis", "none",
                    "--progress", "none", "--output-dir", str(out), "--model.eval-lpips", "none",
                    "--model.renderer.no-use-compile"], site, tmp_path)
    assert trained.returncode == 0, trained.stderr
    text = (out / "config.yml").read_text()
    assert "kind: gated-mean" in text and "method_name: example-gated" in text
    assert json.loads((out / "eval.json").read_text())["results"]["step"] == 2
    assert "eval: psnr" in trained.stdout


def test_a_broken_plugin_is_one_warning_not_a_crash(tmp_path):
    site = tmp_path / "site"
    (site / "broken_plugin-1.0.dist-info").mkdir(parents=True)
    (site / "broken_plugin-1.0.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: broken-plugin\nVersion: 1.0\n")
    (site / "broken_plugin-1.0.dist-info" / "entry_points.txt").write_text(
        "[hico_plugin.components]\nbroken = broken_plugin\n")
    (site / "broken_plugin.py").write_text("raise RuntimeError('this plug-in is broken')\n")
    result = _run([_cli("hico-train"), "--help"], site, tmp_path)
    assert result.returncode == 0, result.stderr
    assert "hico-gs-lite" in result.stdout
    warnings = [line for line in result.stderr.splitlines() if "Warning" in line]
    assert len(warnings) == 1, result.stderr
    assert "'broken'" in warnings[0] and "broken-plugin" in warnings[0] and "this plug-in is broken" in warnings[0]
