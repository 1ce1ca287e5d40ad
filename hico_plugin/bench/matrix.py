"""The benchmark matrix: presets x scenes x training budgets, one cached JSON per cell.

``schedule="nested"`` (default) trains one run per (preset, scene) to the largest budget, evaluated as it passes
each smaller one: cheap, though such a checkpoint has not finished its schedule (schedules scale with
``max_steps``); ``"separate"`` trains each budget as its own run. ``max_steps`` is in each cell key's hash, so the
modes never mix. Under ``OUTPUT/``: ``cells/<preset>__<scene>__b<budget>__s<seed>__<hash>.json`` (a finished cell,
written atomically) and ``runs/<scene>/<preset>-s<seed>-<hash>/`` (its run).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch

from hico_plugin.bench.stage_timer import StageTimer
from hico_plugin.config import InstantiateConfig
from hico_plugin.data.parser import FormatChoice
from hico_plugin.engine import TrainerCallback, evaluate
from hico_plugin.errors import HicoError
from hico_plugin.mesh import MeshExportConfig, extract_mesh, surface_results
from hico_plugin.mesh.extract import default_voxel_size
from hico_plugin.presets import HiCoTrainerConfig, all_presets
from hico_plugin.storage import write_text_atomic

ABLATION_PRESETS = ("octree-gs", "hico-gs-clca", "hico-gs-dngc", "hico-gs", "hico-gs-max", "hico-gs-attn")
"""The paper's ablation rows (Table 5), baseline first."""

METRIC_KEYS = ("psnr", "psnr_cc", "ssim", "lpips", "depth_abs_rel", "normal_error_deg", "num_anchors", "num_gaussians", "fps")
"""Evaluation figures every cell records (None where unavailable, e.g. no ground-truth normals)."""
SURFACE_KEYS = ("surface_f1", "surface_precision", "surface_recall", "surface_tau", "mesh_voxel")
"""Mesh figures every cell records (None without --mesh, a ground-truth surface or a mesh); tau and
the voxel edge are in the scene's COLMAP units."""


@dataclass
class BenchConfig(InstantiateConfig):
    """A benchmark matrix. Defaults: the paper's ablation rows on both built-in scenes."""

    presets: tuple[str, ...] = ABLATION_PRESETS
    """Presets to compare (rows of the ablation table)."""
    scenes: tuple[str, ...] = ("city-block", "pagoda")
    """Built-in scenes (ignored when --data is given)."""
    data: Path | None = None
    """A dataset directory (any registered format) to benchmark instead of the built-in scenes."""
    format: FormatChoice = None
    """Layout of --data; default: detected from the directory's contents."""
    effects: tuple[str, ...] = ("auto",)
    """The effects axis: each value is one --model.effects setting (e.g. "auto,environment=off"); every
    preset x scene runs once per value. A value other than "auto" names its rows "PRESET [VALUE]"."""
    budgets: tuple[int, ...] = (100, 200, 400)
    """Training budgets in optimizer steps (checkpoints of one run when schedule is nested). A report's
    ms / step column tells the step time on your machine: scale the budgets by it."""
    schedule: Literal["nested", "separate"] = "nested"
    """nested: one run per (preset, scene) to the largest budget, evaluated at each budget (its
    schedules scaled to the largest budget); separate: one run per budget with its own schedule."""
    seeds: tuple[int, ...] = (42,)
    """Seeds: every cell is run once per seed (the same seeds for all presets, so they see the same view
    orders); the report gives mean +- std over seeds and marks a difference to the first preset as
    significant only beyond two standard errors."""
    downscale: int = 2
    """Image downscale factor of the training data."""
    max_eval_views: int = 8
    """Evaluate on at most this many test views (evenly spaced over the test split)."""
    lpips: Literal["vgg", "alex", "none"] = "alex"
    """LPIPS backbone at evaluation ("none" skips LPIPS)."""
    mesh: bool = True
    """Mesh every cell as hico-export ... mesh does by default and score it against the scene's
    ground-truth surface as hico-eval does (mesh F1 / precision / recall), so a change that costs
    geometry shows in the tables; scenes without a ground-truth surface are skipped."""
    quality_targets: tuple[float, ...] = ()
    """Test PSNR levels (dB) of the report's time-to-quality table; default: the lowest final score over
    the methods of each scene and 1 dB below it."""
    output_dir: Path = Path("bench_out")
    """Where cells/, runs/, results.json and report.md go."""
    device: str = "auto"
    """Training device (as hico-train --device)."""

    def resolved(self) -> BenchConfig:
        """This config with its fields checked and its budgets sorted."""
        config = self
        unknown = [p for p in config.presets if p not in all_presets()]
        if unknown:
            raise HicoError(f"--presets: unknown {unknown}; expected some of {sorted(all_presets())}")
        if not config.presets or not config.budgets:
            raise HicoError("--presets / --budgets: expected at least one value each")
        if min(config.budgets) < 1:
            raise HicoError(f"--budgets: expected positive step counts, got {list(config.budgets)}")
        if config.data is not None and not Path(config.data).is_dir():
            raise HicoError(f"--data {config.data}: not a directory (expected a dataset folder)")
        if config.max_eval_views < 1 or config.downscale < 1:
            raise HicoError("--max-eval-views / --downscale: expected >= 1")
        if not config.seeds:
            raise HicoError("--seeds: expected at least one seed")
        return dataclasses.replace(config, budgets=tuple(sorted(set(config.budgets))),
                                   seeds=tuple(dict.fromkeys(config.seeds)))

    def scene_names(self) -> tuple[str, ...]:
        return (Path(self.data).name,) if self.data is not None else tuple(self.scenes)


BENCH_MODES: dict[str, BenchConfig] = {
    "full": BenchConfig(),
    # every effect off, each alone on, all on, and auto, on a scene that has sky and exposure (pagoda), on
    # one whose walls and ceiling no point explains (room) and on one with neither (tiny). At 1,000 steps:
    # 200 rank how fast a setting starts, not what it models.
    "effects": BenchConfig(presets=("hico-gs-lite",), scenes=("pagoda", "room", "tiny"), budgets=(1000,), lpips="none",
                           effects=("environment=off,exposure=off,lod=off", "environment=on,exposure=off,lod=off",
                                    "environment=off,exposure=on,lod=off", "environment=off,exposure=off,lod=on",
                                    "environment=on,exposure=on,lod=on", "auto")),
    "quick": BenchConfig(presets=("octree-gs", "hico-gs"), scenes=("tiny",), budgets=(20, 40), lpips="none",
                         downscale=1, max_eval_views=2),
}
"""The default settings of each mode (``hico-bench full`` / ``hico-bench quick``). A mode is chosen before
the command line is parsed, so every flag the user types overrides it, whatever its value."""


def run_config(bench: BenchConfig, preset: str, scene: str, max_steps: int, seed: int,
               effects: str = "auto") -> HiCoTrainerConfig:
    """The training config of one run of the matrix (output_dir not yet set)."""
    config = copy.deepcopy(all_presets()[preset][1])
    data = dataclasses.replace(config.data, downscale=bench.downscale,
                               data=Path(bench.data) if bench.data is not None else None, format=bench.format,
                               scene=config.data.scene if bench.data is not None else scene)
    model = dataclasses.replace(config.model, eval_lpips=bench.lpips, effects=effects)
    return dataclasses.replace(config, data=data, model=model, max_steps=max_steps, seed=seed,
                               experiment_name=scene, eval_every=0, save_every=0, keep_checkpoints=1,
                               vis="none", progress="none", overwrite=True, resume=False, device=bench.device,
                               output_dir=Path("."))


def config_hash(config: HiCoTrainerConfig, bench: BenchConfig) -> str:
    """Short hash of everything that changes a cell's figures (the run config + how it is evaluated)."""
    text = (repr(dataclasses.replace(config, output_dir=Path("."))) + f"|eval_views={bench.max_eval_views}"
            + f"|mesh={bench.mesh}")
    return hashlib.sha1(text.encode()).hexdigest()[:10]


def cell_path(bench: BenchConfig, preset: str, scene: str, budget: int, digest: str, seed: int) -> Path:
    return Path(bench.output_dir) / "cells" / f"{preset}__{scene}__b{budget}__s{seed}__{digest}.json"


def eval_indices(test_indices: list[int], limit: int) -> list[int]:
    """At most ``limit`` of ``test_indices``, evenly spaced (all of them when there are fewer)."""
    if len(test_indices) <= limit:
        return list(test_indices)
    positions = torch.linspace(0, len(test_indices) - 1, limit).round().long().tolist()
    return [test_indices[i] for i in positions]


class CheckpointRecorder(TrainerCallback):
    """Evaluates the run when it completes each budget and writes that cell; stops after the last.

    Wall time is the trainer's ``train_seconds`` (training only: evaluation is excluded) and the stage
    breakdown is the mean over the steps so far; evaluation renders are not timed.
    """

    def __init__(self, timer: StageTimer, cells: dict[int, Path], base: dict[str, Any], max_eval_views: int,
                 log: Callable[[str], None], mesh: bool = True):
        self.timer, self.cells, self.base = timer, cells, base
        self.max_eval_views, self.log, self.mesh = max_eval_views, log, mesh
        self.trainer: Any = None

    def on_train_start(self, trainer: Any, step: int) -> None:
        self.trainer = trainer

    def on_step_end(self, step: int, metrics: dict[str, float]) -> None:
        budget = step + 1
        if budget not in self.cells:
            return
        trainer = self.trainer
        with self.timer.paused():
            results = evaluate(trainer.model, trainer.dataset,
                               eval_indices(trainer.test_indices, self.max_eval_views), trainer.device)
            if self.mesh:
                results.update(self.surface(trainer.model, trainer.dataset))
        stage_ms = self.timer.mean_ms()
        model = trainer.model
        record = {**self.base, "budget": budget,
                  "wall_seconds": float(metrics.get("train_seconds", trainer.train_seconds)),
                  **{key: _float(results.get(key)) for key in METRIC_KEYS + SURFACE_KEYS},
                  "stage_ms": stage_ms, "step_ms": sum(stage_ms.values()),
                  # includes what no stage covers (batch loading, logging, warm-up): compare with step_ms
                  "wall_ms_per_step": 1e3 * float(metrics.get("train_seconds", trainer.train_seconds)) / budget,
                  "eval_views": int(results.get("num_views", 0)),
                  "num_params": int(sum(p.numel() for p in model.parameters())),
                  "effects_on": sorted(n for n, c in getattr(model, "effect_choices", {}).items() if c.on)}
        write_text_atomic(self.cells[budget], json.dumps(record, indent=2, allow_nan=True) + "\n")
        psnr, f1 = record["psnr"], record["surface_f1"]
        self.log(f"  {record['preset']} / {record['scene']} @ {budget} steps: PSNR "
                 f"{psnr if psnr is None else round(psnr, 2)}, mesh F1 {f1 if f1 is None else round(f1, 3)}, "
                 f"{record['wall_seconds']:.1f} s, "
                 f"{record['step_ms']:.0f} ms/step")
        if budget == max(self.cells):
            trainer.request_stop()  # the trainer's own full-test-split evaluation is not needed


    def surface(self, model: Any, dataset: Any) -> dict[str, float]:
        """hico-eval's surface entries for the mesh hico-export would write now, plus its voxel edge;
        empty when the scene has no ground-truth surface or no mesh can be made yet (said in the log)."""
        if dataset.gt_surface_points is None:
            return {}
        try:
            mesh = extract_mesh(model, dataset, MeshExportConfig())
        except HicoError as error:  # e.g. too early in training for any opaque pixel, or no Open3D
            self.log(f"  mesh: not scored: {error}")
            return {}
        return {**surface_results(dataset, mesh), "mesh_voxel": default_voxel_size(dataset) / dataset.transform.scale}


def _float(value: Any) -> float | None:
    return None if value is None else float(value)


def plan(bench: BenchConfig) -> list[dict[str, Any]]:
    """The runs the matrix needs: each {preset, scene, max_steps, budgets, hash, cells{budget: path},
    run_dir, config}, with ``todo`` False when every one of its cells is cached."""
    runs = []
    groups = [bench.budgets] if bench.schedule == "nested" else [(b,) for b in bench.budgets]
    for seed in bench.seeds:  # seed-major: a matrix stopped early has whole seeds done
        for scene in bench.scene_names():
            for base_preset, effects in ((p, e) for p in bench.presets for e in bench.effects):
                preset = base_preset if effects == "auto" else f"{base_preset} [{effects}]"
                file_name = (base_preset if effects == "auto"
                             else f"{base_preset}-fx{hashlib.sha1(effects.encode()).hexdigest()[:6]}")
                for budgets in groups:
                    config = run_config(bench, base_preset, scene, max(budgets), seed, effects)
                    digest = config_hash(config, bench)
                    cells = {b: cell_path(bench, file_name, scene, b, digest, seed) for b in budgets}
                    run_dir = Path(bench.output_dir) / "runs" / scene / f"{file_name}-s{seed}-{digest}"
                    runs.append({"preset": preset, "effects": effects, "scene": scene, "seed": seed,
                                 "max_steps": max(budgets), "hash": digest, "cells": cells, "run_dir": run_dir,
                                 "config": dataclasses.replace(config, output_dir=run_dir),
                                 "todo": not all(p.is_file() for p in cells.values())})
    return runs


def run_matrix(bench: BenchConfig, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Train and evaluate every uncached cell of ``bench`` (already ``resolved()``); returns all cells."""
    runs = plan(bench)
    todo = [r for r in runs if r["todo"]]
    log(f"hico-bench: {len(runs)} runs, {len(runs) - len(todo)} cached, {len(todo)} to train")
    for number, run in enumerate(todo, 1):
        log(f"[{number}/{len(todo)}] {run['preset']} on {run['scene']}, {run['max_steps']} steps, seed {run['seed']}")
        start = time.perf_counter()
        config = run["config"]
        timer = StageTimer()
        base = {"preset": run["preset"], "effects": run["effects"], "scene": run["scene"], "seed": run["seed"],
                "config_hash": run["hash"],
                "schedule": bench.schedule, "max_steps": run["max_steps"], "run_dir": str(run["run_dir"])}
        recorder = CheckpointRecorder(timer, run["cells"], base, bench.max_eval_views, log, bench.mesh)
        trainer = config.setup(callbacks=[recorder])
        timer.device = trainer.device
        with timer.attach(trainer.model, trainer.optimizers):
            trainer.train()
        missing = [b for b, p in run["cells"].items() if not p.is_file()]
        if missing:
            raise HicoError(f"{run['run_dir']}: run ended before budgets {missing} (interrupted?)")
        log(f"  done in {time.perf_counter() - start:.0f} s")
    return [json.loads(p.read_text()) for run in runs for p in run["cells"].values()]
