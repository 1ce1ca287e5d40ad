"""hico-bench: quick matrix on the tiny scene (2 presets x 2 tiny budgets), caching, report, compare;
hico-analyze on the runs it trained."""

import json
import sys

import pytest

from hico_plugin.bench import (
    BENCH_MODES,
    BenchConfig,
    compare_results,
    load_results,
    pareto_front,
    write_outputs,
)
from hico_plugin.bench.stage_timer import STAGES
from hico_plugin.cli import analyze as analyze_cli
from hico_plugin.cli import bench as bench_cli
from hico_plugin.errors import HicoError

# 30 steps: well past the 10-20 at which the tiny scene's mesh first keeps a component of 1,000 triangles
ARGS = ["--quick", "--presets", "octree-gs", "hico-gs", "--budgets", "1", "30", "--max-eval-views", "1"]


@pytest.fixture(scope="module")
def bench_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    bench_cli.entrypoint(ARGS + ["--output-dir", str(out)])
    return out


def test_quick_matrix_records_every_cell(bench_dir):
    results = load_results(bench_dir)
    cells = results["cells"]
    assert {(c["preset"], c["scene"], c["budget"]) for c in cells} == {
        (p, "tiny", b) for p in ("octree-gs", "hico-gs") for b in (1, 30)}
    for cell in cells:
        assert cell["psnr"] > 5 and 0 < cell["ssim"] <= 1 and cell["lpips"] is None  # quick skips LPIPS
        assert cell["normal_error_deg"] is not None and cell["depth_abs_rel"] is not None  # tiny has GT
        assert cell["num_anchors"] > 0 and cell["num_gaussians"] > 0 and cell["fps"] > 0
        assert cell["max_steps"] == 30 and cell["wall_seconds"] > 0
        assert set(cell["stage_ms"]) == set(STAGES) and cell["wall_ms_per_step"] > 0
        assert cell["step_ms"] == pytest.approx(sum(cell["stage_ms"].values()))
    final = {c["preset"]: c for c in cells if c["budget"] == 30}
    for stage in ("lod_select", "decode", "rasterize", "losses", "backward", "optimizer"):
        assert final["hico-gs"]["stage_ms"][stage] > 0
    assert final["hico-gs"]["stage_ms"]["clca"] > 0  # CLCA runs its MLP
    assert final["octree-gs"]["stage_ms"]["clca"] < 0.2 * final["hico-gs"]["stage_ms"]["clca"]  # identity
    nested_wall = sorted(c["wall_seconds"] for c in cells if c["preset"] == "hico-gs")
    assert nested_wall[0] < nested_wall[1]  # checkpoints of one run


def test_report_contents(bench_dir):
    report = (bench_dir / "report.md").read_text()
    assert "## Ablation" in report and ("| method | tiny PSNR | Δ vs octree-gs | tiny normal err (°) | tiny mesh F1 | "
                                        "train time (s) | ms / step |") in report
    assert "## Accuracy vs time" in report and "★" in report
    assert "## Time to quality" in report and "| tiny | hico-gs | PSNR " in report
    assert "## Where a training step's time goes" in report and "| clca |" in report
    assert "CLCA + DNGC (hico-gs)" in report
    cells = load_results(bench_dir)["cells"]
    assert f"{cells[0]['psnr']:.2f}" in report
    for name in ("psnr_vs_time.png", "normal_vs_time.png", "stage_breakdown.png"):
        assert (bench_dir / name).stat().st_size > 1000 and f"({name})" in report


def test_second_invocation_reruns_nothing(bench_dir, capsys, monkeypatch):
    stamps = {p: p.stat().st_mtime_ns for p in (bench_dir / "cells").iterdir()}

    def no_training(*args, **kwargs):
        raise AssertionError("a cached cell was trained again")

    monkeypatch.setattr("hico_plugin.engine.trainer.Trainer.train", no_training)
    bench_cli.entrypoint(ARGS + ["--output-dir", str(bench_dir)])
    assert "2 runs, 2 cached, 0 to train" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in (bench_dir / "cells").iterdir()} == stamps


def test_compare(bench_dir, tmp_path, capsys):
    other = tmp_path / "other.json"
    document = load_results(bench_dir)
    for cell in document["cells"]:
        cell["psnr"] += 1.0
    other.write_text(json.dumps(document))
    bench_cli.entrypoint(["compare", str(bench_dir), str(other)])
    out = capsys.readouterr().out
    assert out.count("(+1.00)") == 4 and "4 cells matched" in out
    assert "No cell" in compare_results({"cells": []}, document)


def test_pareto_front():
    points = [(1.0, 10.0), (2.0, 12.0), (3.0, 11.0), (2.0, 12.0), (0.5, 5.0)]
    assert pareto_front(points) == [True, True, False, True, True]


def test_report_without_matplotlib(bench_dir, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    write_outputs(BenchConfig(), load_results(bench_dir)["cells"], tmp_path)
    report = (tmp_path / "report.md").read_text()
    assert "tables only" in report and "![" not in report and not list(tmp_path.glob("*.png"))


FULL = BenchConfig()
TYPED_AT_FULL_DEFAULT = {
    "presets": ["--presets", *FULL.presets],
    "scenes": ["--scenes", *FULL.scenes],
    "budgets": ["--budgets", *map(str, FULL.budgets)],
    "lpips": ["--lpips", FULL.lpips],
    "downscale": ["--downscale", str(FULL.downscale)],
    "max_eval_views": ["--max-eval-views", str(FULL.max_eval_views)],
}


@pytest.mark.parametrize("spelling", [["--quick"], ["quick"]])
@pytest.mark.parametrize("field", sorted(TYPED_AT_FULL_DEFAULT))
def test_quick_keeps_a_typed_value_equal_to_the_full_default(field, spelling):
    config = bench_cli.parse([*spelling, *TYPED_AT_FULL_DEFAULT[field]])
    quick = BENCH_MODES["quick"]
    assert getattr(config, field) == getattr(FULL, field)
    assert getattr(quick, field) != getattr(FULL, field)  # otherwise the test could not fail
    for other in TYPED_AT_FULL_DEFAULT.keys() - {field}:
        assert getattr(config, other) == getattr(quick, other)


def test_mode_alone_gives_its_defaults():
    assert bench_cli.parse(["--quick"]) == BENCH_MODES["quick"] == bench_cli.parse(["quick"])
    assert bench_cli.parse([]) == BENCH_MODES["full"] == bench_cli.parse(["full"])
    assert bench_cli.parse(["--budgets", "5", "--quick"]).budgets == (5,)


def test_report_lists_its_settings(bench_dir):
    report = (bench_dir / "report.md").read_text()
    assert "- presets: octree-gs, hico-gs" in report and "- scenes: tiny" in report
    assert "- budgets: 1, 30 steps (nested schedule)" in report
    assert "- downscale: 1; LPIPS: none; eval views: at most 1; seeds: 42" in report
    assert "- mesh F1: hico-export mesh defaults" in report and "voxel = scene extent / 512" in report


def test_cells_record_mesh_f1_by_default(bench_dir):
    """Each cell is meshed as hico-export does and scored as hico-eval does: F1 in (0, 1], tau the
    tiny scene's ground-truth rule, the voxel the exporter's default (COLMAP units), all in the tables.
    Thirty steps on tiny are at the edge of leaving a 1,000-triangle component, so a cell may be left
    unscored (its F1 None, the reason in the log); hico-gs's is scored."""
    from hico_plugin.data import DataParserConfig
    from hico_plugin.mesh.extract import default_voxel_size
    from hico_plugin.metrics.geometry import gt_spacing_threshold
    from hico_plugin.scenes.generate import generate_scene

    assert BenchConfig().mesh and BENCH_MODES["quick"].mesh
    cells = load_results(bench_dir)["cells"]
    final = [c for c in cells if c["budget"] == 30 and c.get("surface_f1") is not None]
    assert "hico-gs" in {c["preset"] for c in final}, cells
    assert all(0 < c["surface_f1"] <= 1 and 0 < c["surface_precision"] <= 1 for c in final), final
    tiny = DataParserConfig(data=generate_scene("tiny")).setup()
    gt = tiny.transform.points_to_colmap(tiny.gt_surface_points.double())
    for cell in final:
        assert cell["surface_tau"] == pytest.approx(gt_spacing_threshold(gt), rel=1e-6)
        assert cell["mesh_voxel"] == pytest.approx(default_voxel_size(tiny) / tiny.transform.scale, rel=1e-6)
    report = (bench_dir / "report.md").read_text()
    tau, voxel = final[0]["surface_tau"], final[0]["mesh_voxel"]
    assert f"tiny: voxel {voxel:.4f}, tau {tau:.4f}" in report
    assert f"| {final[0]['surface_f1']:.3f} |" in report


def test_mesh_off_is_another_cell(tmp_path):
    from hico_plugin.bench.matrix import plan

    on = BenchConfig(presets=("hico-gs",), scenes=("tiny",), budgets=(2,), output_dir=tmp_path).resolved()
    off = BenchConfig(**{**on.__dict__, "mesh": False})
    assert plan(on)[0]["cells"][2] != plan(off)[0]["cells"][2]  # cached cells without F1 are not reused


def test_bad_input_is_one_line(tmp_path, capsys):
    with pytest.raises(HicoError, match="--presets"):
        BenchConfig(presets=("nope",)).resolved()
    with pytest.raises(SystemExit) as exit_info:
        bench_cli.entrypoint(["compare", str(tmp_path / "missing.json"), str(tmp_path)])
    assert exit_info.value.code == 2 and "results.json" in capsys.readouterr().err


def test_analyze_bench_runs(bench_dir, tmp_path, capsys):
    runs = sorted((bench_dir / "runs" / "tiny").iterdir())
    analyze_cli.entrypoint([str(r) for r in runs] + ["--output-dir", str(tmp_path), "--no-tsne"])
    docs = {d["method"]: d for d in (json.loads(p.read_text()) for p in tmp_path.glob("run_*/analysis.json"))}
    assert docs["octree-gs"]["f_hat"] is None and docs["hico-gs"]["f_hat"] is not None
    levels = len(docs["hico-gs"]["anchors_per_level"])
    assert len(docs["hico-gs"]["f"]["distance"]) == levels and len(docs["hico-gs"]["f_hat"]["adjacent"]) == levels - 1
    comparison = json.loads((tmp_path / "compare.json").read_text())
    assert [r["features"] for r in comparison["runs"]] == ["f_hat", "f"]
    assert (tmp_path / "compare_adjacent.png").is_file()
    with pytest.raises(SystemExit):
        analyze_cli.entrypoint([str(tmp_path)])
    assert "not a training run" in capsys.readouterr().err


def test_plan_nested_vs_separate(tmp_path):
    from hico_plugin.bench.matrix import plan

    base = BenchConfig(presets=("hico-gs",), scenes=("tiny",), budgets=(2, 5), output_dir=tmp_path).resolved()
    nested = plan(base)
    assert len(nested) == 1 and nested[0]["max_steps"] == 5 and sorted(nested[0]["cells"]) == [2, 5]
    separate = plan(BenchConfig(**{**base.__dict__, "schedule": "separate"}))
    assert [r["max_steps"] for r in separate] == [2, 5]
    # Schedules scale with max_steps, so a budget-2 cell of a 5-step run is a different cell.
    assert separate[0]["cells"][2] != nested[0]["cells"][2]
    assert all(r["todo"] for r in nested + separate)


def seeded_cells(psnrs: dict[str, list[float]]) -> list[dict]:
    return [{"preset": preset, "scene": "tiny", "budget": 10, "seed": seed, "psnr": value,
             "normal_error_deg": 10.0, "wall_seconds": 1.0, "step_ms": 5.0}
            for preset, values in psnrs.items() for seed, value in enumerate(values)]


def test_seeded_ablation_marks_only_differences_beyond_two_standard_errors():
    from hico_plugin.bench.report import ablation_table
    from hico_plugin.bench.seeds import difference

    # +0.40 with SE sqrt(0.08^2/3 + 0.38^2/3) = 0.224 -> 1.8 SE: not significant (the courtyard).
    diff, se, significant = difference([25.36, 25.44, 25.52], [24.66, 25.04, 25.42])
    assert diff == pytest.approx(0.40) and se == pytest.approx(0.2242, abs=1e-3) and not significant
    assert difference([26.0, 26.1, 25.9], [25.0, 25.1, 24.9])[2]  # +1.0 at SE 0.08
    assert difference([26.0], [25.0]) == (1.0, None, False)  # one seed shows no spread
    table = ablation_table(seeded_cells({"octree-gs": [25.0, 25.1, 24.9], "hico-gs": [26.0, 26.1, 25.9],
                                         "hico-gs-clca": [25.0, 25.4, 24.8]}))
    assert "| hico-gs | 26.00 ± 0.10 | +1.00 ± 0.08 * |" in table
    assert "| hico-gs-clca | 25.07 ± 0.31 | +0.07 ± 0.19 |" in table
    assert "| octree-gs | 25.00 ± 0.10 |  |" in table
    # a scene whose photos differ in exposure is ranked by colour-corrected PSNR
    exposed = [{**c, "psnr_cc": c["psnr"] + 5.0, "psnr": 0.0, "effects_on": ["exposure", "lod"]}
               for c in seeded_cells({"octree-gs": [25.0, 25.1, 24.9], "hico-gs": [26.0, 26.1, 25.9]})]
    table = ablation_table(exposed)
    assert "tiny PSNR-cc" in table and "| hico-gs | 31.00 ± 0.10 | +1.00 ± 0.08 * |" in table


def test_seeds_multiply_the_runs(tmp_path):
    from hico_plugin.bench.matrix import plan

    config = BENCH_MODES["quick"]
    one = plan(BenchConfig(**{**config.__dict__, "output_dir": tmp_path, "seeds": (0,)}).resolved())
    three = plan(BenchConfig(**{**config.__dict__, "output_dir": tmp_path, "seeds": (0, 1, 2, 1)}).resolved())
    assert len(three) == 3 * len(one)
    assert [r["seed"] for r in three] == [s for s in (0, 1, 2) for _ in one]  # seed-major, duplicates dropped
    assert len({r["run_dir"] for r in three}) == len(three) and {r["config"].seed for r in three} == {0, 1, 2}
    assert bench_cli.parse(["--seeds", "0", "1", "2"]).seeds == (0, 1, 2)
    with pytest.raises(HicoError, match="--seeds"):
        BenchConfig(seeds=()).resolved()


def test_time_to_quality_interpolates_between_evaluations():
    from hico_plugin.bench.report import quality_targets, reach_seconds, time_to_quality_table

    def run(preset, seed, points):
        return [{"preset": preset, "scene": "tiny", "seed": seed, "budget": 100 * (i + 1), "psnr": p,
                 "wall_seconds": t} for i, (t, p) in enumerate(points)]

    fast = run("fast", 0, [(10.0, 20.0), (20.0, 24.0), (40.0, 26.0)])
    assert reach_seconds(fast, "psnr", 22.0) == pytest.approx(15.0)  # halfway between 20 and 24 dB
    assert reach_seconds(fast, "psnr", 19.0) == 10.0  # already reached at the first evaluation
    assert reach_seconds(fast, "psnr", 26.5) is None
    slow = run("slow", 0, [(30.0, 20.0), (60.0, 23.0), (90.0, 25.05)])
    cells = fast + slow + run("fast", 1, [(12.0, 21.0), (22.0, 25.0), (44.0, 27.0)])
    # default levels: the lowest final mean over methods (slow: 25.05 -> 25.0) and 1 dB below
    assert quality_targets(cells, "psnr") == [24.0, 25.0]
    assert quality_targets(cells, "psnr", (26.0, 22.0)) == [22.0, 26.0]
    table = time_to_quality_table(cells, (26.0,))
    # fast: seed 0 reaches 26 dB at 40 s, seed 1 between 22 s (25 dB) and 44 s (27 dB) at 33 s
    assert "| tiny | fast | PSNR 26.0: 36 ± 5 s (2/2) |" in table
    assert "| tiny | slow | PSNR 26.0: not reached (0/1) |" in table
