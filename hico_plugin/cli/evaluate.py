"""``hico-eval --load-config RUN/config.yml [--checkpoint PATH] [--render-dir DIR]``.

Evaluates the run on its test views (the engine's ``evaluate``, as at the end of training) and
rewrites RUN/eval.json in nerfstudio's ns-eval layout, with surface metrics when a mesh exists and
the scene has a ground-truth surface; ``--render-dir`` also saves, per test view, the render beside
the ground truth and the depth and normal maps.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import tyro

import hico_plugin.presets  # noqa: F401  (loads the config classes a config.yml may name)
from hico_plugin.cli import run_cli
from hico_plugin.cli.render import FrameRequest
from hico_plugin.engine import evaluate, write_eval_json
from hico_plugin.engine.checkpoints import load_checkpoint
from hico_plugin.engine.data import load_view
from hico_plugin.errors import HicoError
from hico_plugin.engine import LoadedRun, load_run
from hico_plugin.export.frames import write_png
from hico_plugin.mesh.evaluate import surface_results
from hico_plugin.visualization.options import RenderOptions
from hico_plugin.visualization.visualize import visualize


@dataclass
class EvalArgs:
    """Evaluate a trained HiCo-GS run on its test views and rewrite its eval.json."""

    load_config: Path
    """The run's config.yml (written by hico-train next to its checkpoints)."""
    checkpoint: Path | None = None
    """Checkpoint to evaluate instead of the run's newest."""
    output_path: Path | None = None
    """Where to write the results (default RUN/eval.json)."""
    render_dir: Path | None = None
    """Also save per test view <name>_rgb_gt.png (render | ground truth), <name>_depth.png and
    <name>_normal.png here."""
    device: str | None = None
    """Device to evaluate on (default: the run's)."""
    mesh: Path | None = None
    """Mesh scored against the scene's ground-truth surface when it has one (P / R / F1 / chamfer);
    default RUN/exports/mesh.ply (hico-export ... mesh) when it exists."""


def checkpoint_info(path: Path) -> dict[str, Any]:
    """``step`` and ``train_seconds`` recorded in a checkpoint (memory-mapped: tensors stay on disk)."""
    payload = load_checkpoint(Path(path), mmap=True)
    return {key: payload[key] for key in ("step", "train_seconds") if key in payload}


@torch.no_grad()
def save_test_renders(run: LoadedRun, render_dir: Path) -> int:
    """Write the test views' render | ground truth, depth and normal PNGs; returns the view count."""
    request = FrameRequest(outputs=("alpha", "depth", "normal", "rgb"))
    options = {name: RenderOptions(output=name) for name in ("rgb", "depth", "normal")}
    indices = [int(i) for i in run.dataset.test_indices]
    for index in indices:
        images = run.model.render_for_display(run.dataset.cameras[index], request)
        gt, _ = load_view(run.dataset, index)
        gt_picture = visualize({"rgb": gt}, options["rgb"])
        stem = Path(run.dataset.image_names[index]).with_suffix("").as_posix().replace("/", "_")
        write_png(render_dir / f"{stem}_rgb_gt.png", np.concatenate([visualize(images, options["rgb"]), gt_picture], 1))
        for name in ("depth", "normal"):
            write_png(render_dir / f"{stem}_{name}.png", visualize(images, options[name]))
    return len(indices)


def main(args: EvalArgs) -> dict[str, Any]:
    if args.mesh is not None and not args.mesh.is_file():
        raise HicoError(f"--mesh: {args.mesh} is not a file (expected a PLY written by hico-export ... mesh)")
    run = load_run(args.load_config, args.checkpoint, args.device)
    indices = [int(i) for i in run.dataset.test_indices]
    if not indices:
        raise HicoError(f"{args.load_config}: the run's dataset has no test views to evaluate")
    device = run.model.background.device
    with torch.no_grad():  # untimed warm-up: the first render compiles the rasterizer's kernels
        run.model.render(run.dataset.cameras[indices[0]], ("rgb",))
    results = evaluate(run.model, run.dataset, indices, device)
    results.update(checkpoint_info(run.checkpoint))
    results.update(surface_results(run.dataset, args.mesh or run.run_dir / "exports" / "mesh.ply"))
    output_path = args.output_path or run.run_dir / "eval.json"
    write_eval_json(output_path, run.config.experiment_name, run.config.method_name, str(run.checkpoint), results)
    for key, value in results.items():
        if key.endswith("_std") or not isinstance(value, (int, float)):
            continue  # None, and the model's choices (effects), which eval.json holds as they are
        std = results.get(f"{key}_std")
        print(f"{key:26s} {value:.4g}" + (f" ± {std:.3g}" if isinstance(std, float) else ""))
    print(f"eval: {len(indices)} test views of {run.checkpoint} -> {output_path}")
    if args.render_dir is not None:
        count = save_test_renders(run, args.render_dir)
        print(f"renders: {count} test views -> {args.render_dir}")
    return json.loads(output_path.read_text())


def parse(args: Sequence[str]) -> EvalArgs:
    return tyro.cli(EvalArgs, args=list(args), prog="hico-eval")


def entrypoint(argv: Sequence[str] | None = None) -> None:
    run_cli(lambda: main(parse(sys.argv[1:] if argv is None else argv)))
