"""``hico-eval --load-config RUN/config.yml [--checkpoint PATH] [--render-dir DIR] [--data DIR]``.

Evaluates the run on its test views as at the end of training and rewrites RUN/eval.json (ns-eval layout, with
surface metrics when a mesh and a ground-truth surface exist). ``--render-dir`` saves per view the render, the
ground truth and the depth and normal maps; ``--data`` scores another dataset of the same views in the same scene
frame (say the photos as taken rather than undistorted), so two preparations compare on one pixel grid.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import tyro

import hico_plugin.presets  # noqa: F401  (loads the config classes a config.yml may name)
from hico_plugin.cli import run_cli
from hico_plugin.cli.render import FrameRequest
from hico_plugin.engine import LoadedRun, evaluate, load_run, write_eval_json
from hico_plugin.engine.checkpoints import check_frame, load_checkpoint
from hico_plugin.engine.data import load_view
from hico_plugin.errors import HicoError
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
    lpips: Literal["vgg", "alex", "none"] | None = None
    """LPIPS backbone to score with (default the run's --model.eval-lpips: alex for hico-gs-lite, vgg,
    as CityGS-X reports it, for the paper's presets)."""
    data: Path | None = None
    """Score on the test views of this dataset instead of the run's own: the same views (image names)
    in the same scene frame, with their own photos and cameras, read with the run's data settings;
    results go to RUN/eval_on_<folder name>.json unless --output-path is given."""


def checkpoint_info(path: Path) -> dict[str, Any]:
    """``step`` and ``train_seconds`` recorded in a checkpoint (memory-mapped: tensors stay on disk)."""
    payload = load_checkpoint(Path(path), mmap=True)
    return {key: payload[key] for key in ("step", "train_seconds") if key in payload}


def other_dataset(run: LoadedRun, data: Path) -> Any:
    """The run's data settings read on ``data``; a HicoError unless it holds the run's views (the
    same image names, so a view keeps its index and appearance slot) in the checkpoint's scene frame."""
    if not dataclasses.is_dataclass(run.config.data) or not hasattr(run.config.data, "data"):
        raise HicoError(f"--data: the run's data config ({type(run.config.data).__name__}) reads no dataset folder")
    payload = load_checkpoint(run.checkpoint, mmap=True)
    frame = {"frame": payload["frame"]} if payload.get("frame") is not None else {}
    dataset = dataclasses.replace(run.config.data, data=Path(data)).setup(announce=False, **frame)
    ours, theirs = list(run.dataset.image_names), list(dataset.image_names)
    if ours != theirs:
        differ = sorted(set(ours) ^ set(theirs)) or ["(the same names in another order)"]
        raise HicoError(f"--data {data}: holds other views than the run's dataset ({len(theirs)} images against "
                        f"{len(ours)}; e.g. {differ[0]}); it must hold the same views under the same names")
    try:
        check_frame(payload, dataset, run.checkpoint)
    except HicoError as err:
        raise HicoError(f"--data {data}: {err}") from None
    return dataset


@torch.no_grad()
def save_test_renders(run: LoadedRun, render_dir: Path, dataset: Any = None) -> int:
    """Write the test views' render | ground truth, depth and normal PNGs of ``dataset`` (default the
    run's); returns the view count."""
    dataset = run.dataset if dataset is None else dataset
    request = FrameRequest(outputs=("alpha", "depth", "normal", "rgb"))
    options = {name: RenderOptions(output=name) for name in ("rgb", "depth", "normal")}
    indices = [int(i) for i in dataset.test_indices]
    for index in indices:
        images = run.model.render_for_display(dataset.cameras[index], request)
        gt, _ = load_view(dataset, index)
        gt_picture = visualize({"rgb": gt}, options["rgb"])
        stem = Path(dataset.image_names[index]).with_suffix("").as_posix().replace("/", "_")
        write_png(render_dir / f"{stem}_rgb_gt.png", np.concatenate([visualize(images, options["rgb"]), gt_picture], 1))
        for name in ("depth", "normal"):
            write_png(render_dir / f"{stem}_{name}.png", visualize(images, options[name]))
    return len(indices)


def main(args: EvalArgs) -> dict[str, Any]:
    if args.mesh is not None and not args.mesh.is_file():
        raise HicoError(f"--mesh: {args.mesh} is not a file (expected a PLY written by hico-export ... mesh)")
    run = load_run(args.load_config, args.checkpoint, args.device)
    if args.lpips is not None:
        run.model.config = dataclasses.replace(run.model.config, eval_lpips=args.lpips)
    dataset = run.dataset if args.data is None else other_dataset(run, args.data)
    indices = [int(i) for i in dataset.test_indices]
    if not indices:
        raise HicoError(f"{args.data or args.load_config}: the dataset has no test views to evaluate")
    device = run.model.background.device
    with torch.no_grad():  # untimed warm-up: the first render compiles the rasterizer's kernels
        run.model.render(dataset.cameras[indices[0]], ("rgb",))
    results = evaluate(run.model, dataset, indices, device)
    results.update(checkpoint_info(run.checkpoint))
    results.update(surface_results(dataset, args.mesh or run.run_dir / "exports" / "mesh.ply"))
    default_name = "eval.json" if args.data is None else f"eval_on_{Path(args.data).resolve().name}.json"
    output_path = args.output_path or run.run_dir / default_name
    write_eval_json(output_path, run.config.experiment_name, run.config.method_name, str(run.checkpoint), results)
    for key, value in results.items():
        if key.endswith("_std") or not isinstance(value, (int, float)):
            continue  # None, and the model's choices (effects), which eval.json holds as they are
        std = results.get(f"{key}_std")
        print(f"{key:26s} {value:.4g}" + (f" ± {std:.3g}" if isinstance(std, float) else ""))
    scored = "" if args.data is None else f" (views of {args.data})"
    print(f"eval: {len(indices)} test views{scored} of {run.checkpoint} -> {output_path}")
    if args.render_dir is not None:
        count = save_test_renders(run, args.render_dir, dataset)
        print(f"renders: {count} test views -> {args.render_dir}")
    return json.loads(output_path.read_text())


def parse(args: Sequence[str]) -> EvalArgs:
    return tyro.cli(EvalArgs, args=list(args), prog="hico-eval")


def entrypoint(argv: Sequence[str] | None = None) -> None:
    run_cli(lambda: main(parse(sys.argv[1:] if argv is None else argv)))
