"""How training scales to a district: what a step costs for the anchors its view does not see, and how
wall time and memory grow with the photos.

    python benchmarks/scaling.py [--quick] [--parts overhead photos] [--out DIR]

``overhead``: one district view stepped on the whole district model and on a model holding only the
anchors that view sees (the same pixels, the same visible anchors, the same Gaussians), alternating
blocks of steps so a drift of the machine's speed weighs on both; prints the stage profile of both and
``invisible overhead: 1.07x at 1,250,000 anchors``. The model's octree is built from the scene's exact
surface samples (a trained district's density), densification off during the timed steps, all
levels active and DNGC on, as late in a run. ``--dense`` times the dense update of the paper
(every anchor's Adam rows) and culling by testing every anchor, the code path before chunks.

``photos``: ``hico-train hico-gs-lite`` on the district at 100 / 300 / 1,000 photos with the same
steps per photo (``--steps-per-photo``), each in its own process: wall, peak RSS, anchors, test PSNR
and normal error.

Time it on a quiet machine: anything else on the cores inflates torch's threaded stages unevenly.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from hico_plugin.bench.stage_timer import STAGES, StageTimer
from hico_plugin.data.sources import DataSourceConfig
from hico_plugin.engine.data import make_batch
from hico_plugin.engine.optimizers import Optimizers
from hico_plugin.engine.step import optimizer_step
from hico_plugin.presets import PRESETS
from hico_plugin.scenes.generate import generate_scene

QUICK = {"blocks": 5, "num_views": 120}
"""The quick run's district: minutes, not hours."""


def _config(data_dir: Path, dense: bool):
    config = PRESETS["hico-gs-lite"][1]
    field = config.model.field
    field = dataclasses.replace(field, densify=dataclasses.replace(field.densify, enabled=False),
                                **({"sparse_grad": False, "chunk_size": 0} if dense else {}))
    return dataclasses.replace(config, data=DataSourceConfig(data=data_dir), vis="none", progress="none",
                               model=dataclasses.replace(config.model, field=field))


def _surface_seeded(dataset, stride: int):
    """The dataset with every ``stride``-th of the scene's exact surface samples as seed points: the
    octree of a district as dense as a trained one, not of its sparse SfM points."""
    surface = dataset.gt_surface_points
    if surface is None:
        raise SystemExit("scaling: the scene has no surface points")
    dataset.points = surface.float()[::stride]
    return dataset


def _time_steps(model, batch, step: int, steps: int, timer: StageTimer) -> list[float]:
    optimizers = Optimizers(model.param_groups(), model.lr_schedules(step + steps + 1))
    seconds = []
    with timer.attach(model, optimizers):
        for _ in range(steps):
            start = time.perf_counter()
            optimizer_step(model, optimizers, batch, step, torch.device("cpu"), 1)
            seconds.append(time.perf_counter() - start)
    return seconds


def overhead(data_dir: Path, dense: bool, steps: int, blocks: int, stride: int) -> dict:
    config = _config(data_dir, dense)
    dataset = _surface_seeded(config.build_dataset(announce=False), stride)
    full = config.build_model(dataset, torch.device("cpu"))
    step = int(0.9 * config.max_steps)  # every level on, DNGC on, past the densification window
    field = full.field
    # the drone view whose visible share is the median of the training views' (a typical step)
    counts = [(int(field.select(full.appearance_camera(dataset.cameras[i]), step).numel()), i)
              for i in dataset.train_indices]
    counts.sort()
    visible, index = counts[len(counts) // 2]
    camera = full.appearance_camera(dataset.cameras[index])
    rows = field.select(camera, step)
    part = copy.deepcopy(full)
    part.keep_anchors(rows)
    assert torch.equal(part.field.select(camera, step), torch.arange(rows.numel())), "the subset sees otherwise"
    batch = make_batch(dataset, [index], torch.device("cpu"))
    results = {"whole": [], "visible only": []}
    timers = {name: StageTimer(warmup_steps=2) for name in results}
    for _ in range(blocks):  # alternate, so a drift of the machine's speed weighs on both
        for name, model in (("whole", full), ("visible only", part)):
            results[name] += _time_steps(model, batch, step, steps + 2, timers[name])[2:]
    medians = {name: 1e3 * statistics.median(times) for name, times in results.items()}
    return {"anchors": field.num_anchors, "visible": visible, "view": index, "step": step,
            "gaussians": int(getattr(full, "last_num_gaussians", 0)), "median_ms": medians,
            "stage_ms": {name: timer.mean_ms() for name, timer in timers.items()},
            "ratio": medians["whole"] / medians["visible only"], "dense": dense,
            "bytes_per_anchor": full.bytes_per_anchor()}


def _print_overhead(result: dict) -> None:
    print(f"district view {result['view']} at step {result['step']}: {result['visible']:,} of "
          f"{result['anchors']:,} anchors visible, {result['gaussians']:,} Gaussians"
          f"{' (dense Adam, every anchor tested)' if result['dense'] else ''}")
    print(f"{'stage':<12}{'whole model':>14}{'visible only':>14}")
    for stage in STAGES:
        print(f"{stage:<12}{result['stage_ms']['whole'][stage]:>14.1f}{result['stage_ms']['visible only'][stage]:>14.1f}")
    print(f"{'step median':<12}{result['median_ms']['whole']:>14.1f}{result['median_ms']['visible only']:>14.1f}")
    memory = result["bytes_per_anchor"]
    print(f"bytes per anchor: {memory['total']} (parameters {memory['parameters']}, Adam {memory['adam']}, "
          f"statistics {memory['statistics']}, culling {memory['culling']})")
    print(f"invisible overhead: {result['ratio']:.2f}x at {result['anchors']:,} anchors")


def photos(scene_args: dict, counts: list[int], steps_per_photo: float, out: Path) -> list[dict]:
    """One hico-train run per photo count, in its own process (its peak RSS its own)."""
    rows = []
    for count in counts:
        data_dir = generate_scene("district", num_views=count, **scene_args)
        run = out / f"photos-{count}"
        train_photos = count - len(range(0, count, 8))  # test_every 8
        steps = max(1, round(steps_per_photo * train_photos))
        command = [sys.executable, "-c", "from hico_plugin.cli.train import entrypoint; entrypoint()",
                   "hico-gs-lite", "--max-steps", str(steps), "--steps-photos", "0", "--vis", "none",
                   "--progress", "none", "--output-dir", str(run), "--overwrite", "--data", str(data_dir)]
        start = time.perf_counter()
        done = subprocess.run(["/usr/bin/time", "-f", "%M", *command], capture_output=True, text=True)
        wall = time.perf_counter() - start
        if done.returncode != 0:
            print(done.stdout[-2000:], done.stderr[-2000:], file=sys.stderr)
            raise SystemExit(f"scaling: training on {count} photos failed ({done.returncode})")
        peak_mib = int(done.stderr.strip().splitlines()[-1]) / 1024
        evaluation = json.loads((run / "eval.json").read_text())["results"]
        rows.append({"photos": count, "steps": steps, "wall_s": wall, "peak_rss_mib": peak_mib,
                     "anchors": evaluation.get("num_anchors"), "psnr": evaluation.get("psnr"),
                     "normal_error_deg": evaluation.get("normal_error_deg")})
        print(f"photos {count:>5}  steps {steps:>6}  wall {wall:>8.0f} s  peak RSS {peak_mib:>6.0f} MiB  "
              f"anchors {rows[-1]['anchors'] or 0:>9,.0f}  PSNR {rows[-1]['psnr'] or 0:.2f}  "
              f"normal error {rows[-1]['normal_error_deg'] or 0:.1f} deg", flush=True)
    if len(rows) > 1:
        first, last = rows[0], rows[-1]
        print(f"wall({last['photos']}) / wall({first['photos']}) = {last['wall_s'] / first['wall_s']:.2f} "
              f"for {last['photos'] / first['photos']:.1f}x the photos")
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a small district and short windows (minutes)")
    parser.add_argument("--parts", nargs="+", choices=("overhead", "photos"), default=["overhead", "photos"])
    parser.add_argument("--dense", action="store_true", help="time the dense update and per-anchor culling")
    parser.add_argument("--steps", type=int, default=10, help="timed steps per block")
    parser.add_argument("--seed-stride", type=int, default=None,
                        help="every n-th surface sample seeds the octree (default: all; 8 with --quick)")
    parser.add_argument("--blocks", type=int, default=3, help="alternating blocks of timed steps")
    parser.add_argument("--photo-counts", type=int, nargs="+", default=[100, 300, 1000])
    parser.add_argument("--steps-per-photo", type=float, default=10.0)
    parser.add_argument("--out", type=Path, default=None, help="folder for the runs (a temporary one if omitted)")
    args = parser.parse_args(argv)
    scene_args = dict(QUICK) if args.quick else {}
    counts = [min(c, scene_args.get("num_views", c)) for c in args.photo_counts] if args.quick else args.photo_counts
    report = {}
    with tempfile.TemporaryDirectory(prefix="scaling_") as scratch:
        out = args.out or Path(scratch)
        if "overhead" in args.parts:
            data_dir = generate_scene("district", **scene_args)
            stride = args.seed_stride or (8 if args.quick else 1)
            result = overhead(data_dir, args.dense, 3 if args.quick else args.steps, args.blocks, stride)
            _print_overhead(result)
            report["overhead"] = result
        if "photos" in args.parts:
            report["photos"] = photos({k: v for k, v in scene_args.items() if k != "num_views"},
                                      sorted(set(counts)), args.steps_per_photo, out)
    report["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(report, default=float))


if __name__ == "__main__":
    main()
