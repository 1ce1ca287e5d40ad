"""``hico-export ... mesh`` on a tiny trained run (built-in `tiny` scene, 2 steps): a PLY in the COLMAP
frame, and one-line errors instead of tracebacks."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from hico_plugin.cli import evaluate as eval_cli
from hico_plugin.cli import export as export_cli
from hico_plugin.data.sources import DataSourceConfig
from hico_plugin.mesh import read_ply

pytestmark = pytest.mark.skipif(importlib.util.find_spec("open3d") is None,
                                reason="open3d not installed (pip install 'hico_plugin[mesh]')")


@pytest.fixture
def run_dir(tiny_run):
    return tiny_run


def test_export_mesh_writes_a_ply_in_the_colmap_frame(run_dir, tmp_path, capsys):
    torch.manual_seed(0)
    path = export_cli.main(export_cli.parse(["--load-config", str(run_dir / "config.yml"), "mesh", "--min-alpha", "0",
                                             "--depth", "expected", "--min-component-triangles", "10",
                                             "--output", str(tmp_path / "mesh.ply")]))
    assert path == tmp_path / "mesh.ply"
    mesh = read_ply(path)
    assert len(mesh.faces) > 0 and mesh.vertex_colors is not None
    assert f"to {path}" in capsys.readouterr().out
    # In the COLMAP frame the (barely trained) surface lies near the scene's ground truth; left in the
    # normalised frame it would be ~0.7 away.
    dataset = DataSourceConfig(scene="tiny").setup()
    gt = dataset.transform.points_to_colmap(dataset.gt_surface_points.double()).numpy()
    distances, _ = cKDTree(gt).query(mesh.vertices)
    assert np.median(distances) < 0.2


def test_export_mesh_errors_are_one_line(run_dir, capsys):
    with pytest.raises(SystemExit) as exit_info:
        export_cli.entrypoint(["--load-config", str(run_dir / "config.yml"), "mesh", "--min-alpha", "0",
                               "--max-depth", "1e-6"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: mesh: no opaque pixel") and "--max-depth 1e-06" in err and "\n" not in err


def test_eval_adds_surface_metrics_of_the_exported_mesh(run_dir, capsys):
    config = str(run_dir / "config.yml")
    path = export_cli.main(export_cli.parse(["--load-config", config, "mesh", "--min-alpha", "0",
                                             "--min-component-triangles", "10"]))
    assert path == run_dir / "exports" / "mesh.ply"
    results = eval_cli.main(eval_cli.parse(["--load-config", config]))["results"]
    for key in ("surface_precision", "surface_recall", "surface_f1", "surface_chamfer", "surface_tau"):
        assert results[key] is not None, key
    assert 0 <= results["surface_f1"] <= 1 and results["surface_chamfer"] > 0
    assert "surface_f1" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        eval_cli.entrypoint(["--load-config", config, "--mesh", str(run_dir / "missing.ply")])
    assert capsys.readouterr().err.strip().startswith("error: --mesh:")
