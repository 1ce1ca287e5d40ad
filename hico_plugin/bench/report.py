"""results.json, report.md (tables + optional matplotlib figures) and the comparison of two results."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

from hico_plugin.bench.seeds import format_difference, format_mean_std, values_of
from hico_plugin.bench.stage_timer import STAGES
from hico_plugin.errors import HicoError
from hico_plugin.storage import write_text_atomic

RESULTS_VERSION = 1


def pareto_front(points: list[tuple[float, float]]) -> list[bool]:
    """For (cost, quality) points: True where no other point is at most as costly and at least as
    good with one of the two strictly better (lower cost / higher quality is better)."""
    flags = []
    for i, (cost, quality) in enumerate(points):
        dominated = any(c <= cost and q >= quality and (c < cost or q > quality)
                        for j, (c, q) in enumerate(points) if j != i)
        flags.append(not dominated)
    return flags


def scene_score(cells: list[dict[str, Any]]) -> str:
    """The PSNR a scene's cells are ranked by: colour-corrected (``psnr_cc``) where the model turned
    per-image exposure on for it -- its photos differ in exposure, and raw PSNR would mostly measure
    how well a test photo's unknown exposure is guessed -- else raw ``psnr``."""
    exposure = any("exposure" in c.get("effects_on", ()) for c in cells)
    return "psnr_cc" if exposure and all(c.get("psnr_cc") is not None for c in cells) else "psnr"


def _score_label(key: str) -> str:
    return "PSNR-cc" if key == "psnr_cc" else "PSNR"


def mark_pareto(cells: list[dict[str, Any]]) -> None:
    """Set ``cell["pareto"]``: on the (wall time, scene score) front of its scene."""
    for scene in {c["scene"] for c in cells}:
        group = [c for c in cells if c["scene"] == scene and c.get("psnr") is not None]
        key = scene_score(group)
        for cell, flag in zip(group, pareto_front([(c["wall_seconds"], c[key]) for c in group])):
            cell["pareto"] = flag


def build_results(bench: Any, cells: list[dict[str, Any]]) -> dict[str, Any]:
    # Presets in the matrix's order: the first is the baseline the ablation table compares against.
    order = {preset: i for i, preset in enumerate(getattr(bench, "presets", ()))}
    cells = sorted(cells, key=lambda c: (c["scene"], order.get(c["preset"], len(order)), c["preset"],
                                         c.get("seed", 0), c["budget"]))
    mark_pareto(cells)
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(bench).items()}
    return {"version": RESULTS_VERSION, "bench": settings, "cells": cells}


def load_results(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if path.is_dir():
        path = path / "results.json"
    try:
        document = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise HicoError(f"{path}: cannot read a hico-bench results.json ({err.__class__.__name__})") from None
    if not isinstance(document, dict) or not isinstance(document.get("cells"), list):
        raise HicoError(f"{path}: not a hico-bench results.json (expected a 'cells' list)")
    return document


def _fmt(value: Any, digits: int = 2) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


def _presets(cells: list[dict[str, Any]]) -> list[str]:
    return list(dict.fromkeys(c["preset"] for c in cells))


def _final(cells: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each (preset, scene, seed)'s cell at the largest budget."""
    best: dict[tuple[str, str, Any], dict[str, Any]] = {}
    for cell in cells:
        key = (cell["preset"], cell["scene"], cell.get("seed"))
        if key not in best or cell["budget"] > best[key]["budget"]:
            best[key] = cell
    return list(best.values())


def ablation_table(cells: list[dict[str, Any]]) -> str:
    """Paper shape: one row per preset, PSNR (``scene_score``: colour-corrected on a scene with
    per-image exposure) and normal error per scene at the largest budget as mean ± std over seeds, the
    difference to the first preset ± its standard error (* = beyond two standard errors), mean wall
    time and ms / step."""
    final = _final(cells)
    scenes = list(dict.fromkeys(c["scene"] for c in final))
    score = {s: scene_score([c for c in final if c["scene"] == s]) for s in scenes}
    presets = _presets(final)
    group = {(p, s): [c for c in final if c["preset"] == p and c["scene"] == s] for p in presets for s in scenes}
    rows = []
    for preset in presets:
        row = [preset]
        for scene in scenes:
            mine, base, key = group[(preset, scene)], group[(presets[0], scene)], score[scene]
            row += [format_mean_std(values_of(mine, key)),
                    "" if preset == presets[0] else format_difference(values_of(mine, key), values_of(base, key)),
                    format_mean_std(values_of(mine, "normal_error_deg"), 1),
                    format_mean_std(values_of(mine, "surface_f1"), 3)]
        mine = [c for c in final if c["preset"] == preset]
        row += [format_mean_std(values_of(mine, "wall_seconds"), 1), format_mean_std(values_of(mine, "step_ms"), 0)]
        rows.append(row)
    header = ["method"]
    for scene in scenes:
        header += [f"{scene} {_score_label(score[scene])}", f"Δ vs {presets[0]}", f"{scene} normal err (°)",
                   f"{scene} mesh F1"]
    return _table(header + ["train time (s)", "ms / step"], rows)


def accuracy_time_table(cells: list[dict[str, Any]]) -> str:
    header = ["scene", "method", "seed", "steps", "PSNR", "SSIM", "LPIPS", "depth AbsRel", "normal err (°)",
              "mesh F1", "anchors", "Gaussians", "wall (s)", "FPS", "Pareto"]
    rows = [[c["scene"], c["preset"], str(c.get("seed", "–")), str(c["budget"]), _fmt(c["psnr"]), _fmt(c["ssim"], 3), _fmt(c["lpips"], 3),
             _fmt(c["depth_abs_rel"], 3), _fmt(c["normal_error_deg"], 1), _fmt(c.get("surface_f1"), 3),
             _fmt(c["num_anchors"], 0),
             _fmt(c["num_gaussians"], 0), _fmt(c["wall_seconds"], 1), _fmt(c["fps"], 1),
             "★" if c.get("pareto") else ""] for c in cells]
    return _table(header, rows)


def reach_seconds(run: list[dict[str, Any]], key: str, target: float) -> float | None:
    """Training wall time at which one run's cells (its budgets) first reach ``target`` in ``key``:
    linear between the two evaluations that straddle it, the first evaluation's time when that one
    already does, None when none does."""
    before = None
    for cell in sorted(run, key=lambda c: c["budget"]):
        value, seconds = cell.get(key), cell["wall_seconds"]
        if value is None:
            continue
        if value >= target:
            if before is None or value == before[1]:
                return seconds
            return before[0] + (target - before[1]) * (seconds - before[0]) / (value - before[1])
        before = (seconds, value)
    return None


def quality_targets(cells: list[dict[str, Any]], key: str, targets: tuple[float, ...] = ()) -> list[float]:
    """``targets``, or by default the lowest final mean ``key`` over presets (a level every method
    reaches on average) and 1 dB below it, rounded to 0.1 dB."""
    if targets:
        return sorted(targets)
    final = _final(cells)
    means = [sum(v) / len(v) for p in _presets(final) if (v := values_of([c for c in final if c["preset"] == p], key))]
    if not means:
        return []
    low = math.floor(10 * min(means)) / 10
    return [round(low - 1.0, 1), low]


def time_to_quality_table(cells: list[dict[str, Any]], targets: tuple[float, ...] = ()) -> str:
    """Per scene and preset, the training wall time to reach each quality target (``scene_score``),
    mean ± std over the seeds that reach it, with how many do."""
    rows = []
    for scene in dict.fromkeys(c["scene"] for c in cells):
        mine = [c for c in cells if c["scene"] == scene]
        key = scene_score(mine)
        levels = quality_targets(mine, key, targets)
        for preset in _presets(mine):
            runs: dict[Any, list[dict[str, Any]]] = {}
            for cell in mine:
                if cell["preset"] == preset:
                    runs.setdefault(cell.get("seed"), []).append(cell)
            row = [scene, preset]
            for level in levels:
                times = [t for run in runs.values() if (t := reach_seconds(run, key, level)) is not None]
                row.append(f"{_score_label(key)} {level:.1f}: "
                           + (f"{format_mean_std(times, 0)} s ({len(times)}/{len(runs)})" if times
                              else f"not reached (0/{len(runs)})"))
            rows.append(row)
    if not rows:
        return "(no cells)"
    width = max(len(r) for r in rows)
    return _table(["scene", "method"] + [f"time to target {i + 1}" for i in range(width - 2)],
                  [r + [""] * (width - len(r)) for r in rows])


def stage_means(cells: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """preset -> stage -> ms per step, averaged over scenes at the largest budget."""
    out = {}
    for preset in _presets(cells):
        mine = [c for c in _final(cells) if c["preset"] == preset]
        out[preset] = {s: sum(c["stage_ms"].get(s, 0.0) for c in mine) / len(mine) for s in STAGES}
    return out


def breakdown_table(cells: list[dict[str, Any]]) -> str:
    means = stage_means(cells)
    final = _final(cells)
    rows = []
    for preset, ms in means.items():
        walls = [c["wall_ms_per_step"] for c in final if c["preset"] == preset and "wall_ms_per_step" in c]
        rows.append([preset] + [_fmt(ms[s], 1) for s in STAGES] + [_fmt(sum(ms.values()), 1),
                                                                   _fmt(sum(walls) / len(walls), 1) if walls else "–"])
    return _table(["method"] + list(STAGES) + ["total", "wall / step"], rows)


def component_costs(cells: list[dict[str, Any]]) -> list[str]:
    """What CLCA and DNGC cost per step and bought in PSNR, each against the octree-gs baseline."""
    means, final = stage_means(cells), _final(cells)
    if "octree-gs" not in means:
        return ["(no octree-gs baseline in this matrix: component costs not computed)"]

    def psnr(preset: str) -> float | None:
        values = [c["psnr"] for c in final if c["preset"] == preset and c["psnr"] is not None]
        return sum(values) / len(values) if values else None

    base_ms, base_psnr, lines = sum(means["octree-gs"].values()), psnr("octree-gs"), []
    for preset, label in (("hico-gs-clca", "CLCA"), ("hico-gs-dngc", "DNGC"), ("hico-gs", "CLCA + DNGC")):
        if preset not in means:
            continue
        ms, gain = sum(means[preset].values()), psnr(preset)
        delta = "–" if gain is None or base_psnr is None else f"{gain - base_psnr:+.2f} dB"
        lines.append(f"- {label} ({preset}): {ms - base_ms:+.1f} ms/step ({100 * (ms / base_ms - 1):+.0f}%) vs "
                     f"octree-gs; PSNR {delta}; its clca stage {means[preset]['clca']:.1f} ms, losses "
                     f"{means[preset]['losses']:.1f} ms (baseline {means['octree-gs']['losses']:.1f} ms)")
    return lines


def write_plots(cells: list[dict[str, Any]], out_dir: Path, targets: tuple[float, ...] = ()) -> list[str]:
    """PNG figures; [] when matplotlib is not installed. The PSNR figure is the time-to-quality view:
    each scene's score (``scene_score``) against training wall time, with the quality targets of
    ``time_to_quality_table`` as dotted lines."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    scenes = list(dict.fromkeys(c["scene"] for c in cells))
    names, colours = [], {}
    for key, label, name in (("psnr", "test PSNR (dB)", "psnr_vs_time.png"),
                             ("normal_error_deg", "normal error (deg)", "normal_vs_time.png")):
        if all(c.get(key) is None for c in cells):
            continue
        fig, axes = plt.subplots(1, len(scenes), figsize=(5 * len(scenes), 4), squeeze=False)
        for ax, scene in zip(axes[0], scenes):
            scene_key = scene_score([c for c in cells if c["scene"] == scene]) if key == "psnr" else key
            for preset in _presets(cells):
                for number, seed in enumerate(dict.fromkeys(c.get("seed") for c in cells)):  # a curve per run
                    mine = sorted((c for c in cells if c["scene"] == scene and c["preset"] == preset
                                   and c.get("seed") == seed and c.get(scene_key) is not None),
                                  key=lambda c: c["budget"])
                    ax.plot([c["wall_seconds"] for c in mine], [c[scene_key] for c in mine], "o-", alpha=0.8,
                            label=preset if number == 0 else "_nolegend_",
                            color=colours.setdefault(preset, f"C{len(colours)}"))
            if key == "psnr":
                for level in quality_targets([c for c in cells if c["scene"] == scene], scene_key, targets):
                    ax.axhline(level, color="grey", linestyle=":", linewidth=1)
            front = sorted((c for c in cells if c["scene"] == scene and c.get("pareto") and c.get(key) is not None),
                           key=lambda c: c["wall_seconds"])
            if key == "psnr" and front:
                ax.step([c["wall_seconds"] for c in front], [c[scene_key] for c in front], "k--", where="post",
                        linewidth=1, label="Pareto front")
                ax.scatter([c["wall_seconds"] for c in front], [c[scene_key] for c in front], s=120,
                           facecolors="none", edgecolors="k")
            ax.set(title=scene, xlabel="training wall time (s)",
                   ylabel=f"test {_score_label(scene_key)} (dB)" if key == "psnr" else label)
            ax.grid(alpha=0.3)
        axes[0][0].legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out_dir / name, dpi=100)
        plt.close(fig)
        names.append(name)
    means = stage_means(cells)
    fig, ax = plt.subplots(figsize=(1.4 * len(means) + 3, 4))
    bottom = [0.0] * len(means)
    for stage in STAGES:
        heights = [ms[stage] for ms in means.values()]
        ax.bar(list(means), heights, bottom=bottom, label=stage)
        bottom = [b + h for b, h in zip(bottom, heights)]
    ax.set(ylabel="ms per training step", title="where a training step's time goes")
    ax.legend(fontsize=8, bbox_to_anchor=(1.02, 1), loc="upper left")
    plt.setp(ax.get_xticklabels(), rotation=20, ha="right")
    fig.tight_layout()
    fig.savefig(out_dir / "stage_breakdown.png", dpi=100)
    plt.close(fig)
    return names + ["stage_breakdown.png"]


def effects_table(cells: list[dict[str, Any]]) -> str:
    """One row per (scene, effects setting) at the largest budget: what each effect costs."""
    rows = [[c["scene"], c.get("effects", "auto"), ", ".join(c.get("effects_on", [])) or "none", str(c["budget"]),
             _fmt(c["psnr"]), _fmt(c.get("psnr_cc")), _fmt(c["step_ms"], 0), _fmt(c.get("wall_ms_per_step"), 0),
             str(c.get("num_params", "–"))]
            for c in sorted(_final(cells), key=lambda c: (c["scene"], c.get("effects", "auto")))]
    return _table(["scene", "--model.effects", "on", "steps", "PSNR raw", "PSNR colour-corr.", "ms / step",
                   "wall ms / step", "parameters"], rows)


def mesh_settings_line(bench: dict[str, Any], cells: list[dict[str, Any]]) -> str:
    """How mesh F1 was measured (the rules and, per scene, the voxel edge and tau they gave)."""
    if not bench.get("mesh"):
        return "- mesh F1: off (--no-mesh)"
    scored = {c["scene"]: c for c in cells if c.get("surface_f1") is not None}
    per_scene = "; ".join(f"{scene}: voxel {_fmt(c['mesh_voxel'], 4)}, tau {_fmt(c['surface_tau'], 4)}"
                          for scene, c in scored.items()) or "no scene has a ground-truth surface"
    return ("- mesh F1: hico-export mesh defaults (TSDF of the training views' plane depth at full LOD, voxel = "
            "scene extent / 512 with extent = 2 x the 99th percentile of the sparse points' distances from "
            "their mean, truncation 4 voxels) scored as hico-eval does (F1 at tau = 1.5 x the mean ground-truth "
            f"surface spacing), COLMAP units: {per_scene}")


def settings_lines(bench: dict[str, Any], cells: list[dict[str, Any]]) -> list[str]:
    """The settings the matrix ran with, as a Markdown list, so a report shows what it answers."""
    data = bench.get("data")
    return [f"- presets: {', '.join(bench.get('presets', ()))}",
            f"- scenes: {data if data is not None else ', '.join(bench.get('scenes', ()))}",
            f"- effects: {', '.join(bench.get('effects', ('auto',)))}",
            f"- budgets: {', '.join(map(str, bench.get('budgets', ())))} steps ({bench.get('schedule')} schedule)",
            f"- downscale: {bench.get('downscale')}; LPIPS: {bench.get('lpips')}; "
            f"eval views: at most {bench.get('max_eval_views')}; "
            f"seeds: {', '.join(map(str, bench.get('seeds', ())))}",
            mesh_settings_line(bench, cells)]


def render_report(results: dict[str, Any], plots: list[str] | None) -> str:
    cells, bench = results["cells"], results["bench"]
    parts = ["# hico-bench report", "", *settings_lines(bench, cells), "",
             "Wall time is training time only (evaluation excluded).", "",
             "## Ablation (largest budget)", "",
             ("Mean ± std over seeds; Δ = difference to the first method ± its standard error, "
              "* = beyond two standard errors (nothing is marked with one seed)."), "",
             ablation_table(cells), "",
             "## Time to quality", "",
             ("Training wall time until the test score (colour-corrected on a scene with per-photo exposure) "
              "first reaches each level, linear between the two evaluations around it; mean ± std over the "
              "seeds that reach it (how many do in brackets). Levels: --quality-targets, else the lowest "
              "final score over the methods and 1 dB below it. The PSNR figure plots the same curves."), "",
             time_to_quality_table(cells, tuple(bench.get("quality_targets") or ())), "",
             "## Accuracy vs time", "", "★ = on the (wall time, PSNR) Pareto front of its scene.", "",
             accuracy_time_table(cells), "",
             "## Where a training step's time goes (ms per step, mean over the run)", "",
             ("Stages after the first (warm-up) step; \"wall / step\" is training wall time / steps, "
              "so the gap to \"total\" is what no stage covers (batch loading, logging, the warm-up step)."), "",
             breakdown_table(cells), "",
             "### What CLCA and DNGC cost", "", *component_costs(cells), ""]
    if len({c.get("effects", "auto") for c in cells}) > 1:
        parts += ["## What each effect costs (largest budget)", "",
                  "PSNR colour-corrected: per test view, a least-squares affine colour fit of the render to the "
                  "photo before scoring (the test photo's own exposure is unknowable).", "",
                  effects_table(cells), ""]
    parts += ["## Figures", ""]
    if plots is None or not plots:
        parts.append("matplotlib is not installed (`pip install hico_plugin[bench]`): tables only, no figures.")
    else:
        parts += [f"![{name[:-4]}]({name})" for name in plots]
    return "\n".join(parts) + "\n"


def write_outputs(bench: Any, cells: list[dict[str, Any]], out_dir: Path, plots: bool = True) -> dict[str, Any]:
    """Write results.json, the figures and report.md into ``out_dir``; returns the results."""
    out_dir.mkdir(parents=True, exist_ok=True)
    results = build_results(bench, cells)
    write_text_atomic(out_dir / "results.json", json.dumps(results, indent=2, allow_nan=True) + "\n")
    names = write_plots(results["cells"], out_dir, tuple(results["bench"].get("quality_targets") or ())) if plots else []
    write_text_atomic(out_dir / "report.md", render_report(results, names))
    return results


def _delta(old: dict[str, Any], new: dict[str, Any], field: str, digits: int) -> str:
    if old.get(field) is None or new.get(field) is None:
        return "–"
    return f"{old[field]:.{digits}f} → {new[field]:.{digits}f} ({new[field] - old[field]:+.{digits}f})"


def compare_results(a: dict[str, Any], b: dict[str, Any], name_a: str = "A", name_b: str = "B") -> str:
    """Markdown table of the cells both results hold (matched by preset, scene, budget, seed): B - A."""
    index_a = {(c["preset"], c["scene"], c["budget"], c.get("seed")): c for c in a["cells"]}
    rows = []
    for cell in b["cells"]:
        key = (cell["preset"], cell["scene"], cell["budget"], cell.get("seed"))
        if key not in index_a:
            continue
        old = index_a[key]
        rows.append([*map(str, key), _delta(old, cell, "psnr", 2), _delta(old, cell, "ssim", 3),
                     _delta(old, cell, "normal_error_deg", 1), _delta(old, cell, "wall_seconds", 1),
                     _delta(old, cell, "step_ms", 0)])
    if not rows:
        return f"No cell (preset, scene, budget, seed) is in both {name_a} and {name_b}.\n"
    header = ["method", "scene", "steps", "seed", "PSNR", "SSIM", "normal err (°)", "wall (s)", "ms / step"]
    only = len(a["cells"]) + len(b["cells"]) - 2 * len(rows)
    return (f"# {name_b} vs {name_a}\n\n" + _table(header, rows)
            + f"\n\n{len(rows)} cells matched; {only} in only one of the two.\n")
