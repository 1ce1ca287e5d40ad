"""Where a training step's time goes: milliseconds per stage at chosen steps of a run, and how each
stage grows with pixels and with Gaussians.

    python benchmarks/step_profile.py RUN_DIR [--at 0 1000 3000] [--downscales 0 2] [--steps 20] [--warmup 3]

RUN_DIR is a finished ``hico-train`` run: its config.yml, and a checkpoint for every step of ``--at``
but 0 (train it with ``--save-every 1000 --keep-checkpoints 0``). Step 0 is the run's config started
afresh; a later step resumes a copy of that checkpoint in a scratch directory (the run is only read).
Every (step, downscale) point runs in its own process, so its peak RSS is its own (the process's
whole life: data loading, model set-up and the timed steps), and times
``--steps`` training steps after ``--warmup`` with ``bench.StageTimer``. ``--downscales`` lists the
data's ``--downscale`` values (0: the run's own); each extra one is profiled at every step, which
gives the growth with pixels at a fixed model.

Printed: a table of stages x points (mean ms per step; ``wall`` is the whole step with batch loading
and logging), then per stage the exponent ``a`` of ``ms ~ x^a`` between the points that differ only
in pixels (x = pixels per view) or only in step (x = Gaussians per view). A window without a
densification step shows ``densify`` as 0; its cost is spread over a whole run every
``densify.interval`` steps.

Time it on a quiet machine: anything else on the cores inflates torch's threaded stages unevenly.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hico_plugin.bench.stage_timer import STAGES, StageTimer
from hico_plugin.engine import TrainerCallback
from hico_plugin.engine.checkpoints import checkpoint_path
from hico_plugin.engine.config_io import load_config
from hico_plugin.errors import HicoError


class _Window(TrainerCallback):
    """Counts the wall time of the timed steps and stops the run after the last of them."""

    def __init__(self, timer: StageTimer, first_timed: int, last: int):
        self.timer, self.first_timed, self.last = timer, first_timed, last
        self.trainer = None
        self.start: float | None = None
        self.seconds = 0.0
        self.pixels = 0
        self.gaussians = 0
        self.anchors = 0

    def on_train_start(self, trainer, step: int) -> None:
        self.trainer = trainer

    def on_step_end(self, step: int, metrics: dict[str, float]) -> None:
        now = time.perf_counter()
        if step + 1 == self.first_timed:
            self.start = now
        if step + 1 == self.last:
            self.seconds = now - self.start
            model = self.trainer.model
            self.gaussians = int(getattr(model, "last_num_gaussians", 0))
            self.anchors = int(model.field.num_anchors)
            self.trainer.request_stop()


def profile_point(run_dir: Path, step: int, downscale: int, steps: int, warmup: int) -> dict:
    """One point, in this process: the run's model at ``step`` trained ``warmup + steps`` steps."""
    config = load_config(run_dir / "config.yml")
    with tempfile.TemporaryDirectory(prefix="step_profile_") as scratch:
        scratch = Path(scratch)
        data = config.data if not downscale else dataclasses.replace(config.data, downscale=downscale)
        config = dataclasses.replace(config, output_dir=scratch, data=data, resume=step > 0, overwrite=False,
                                     progress="none", vis="none", eval_every=0, save_every=0, log_every=10**9)
        if step > 0:
            source = checkpoint_path(run_dir / "checkpoints", step)
            if not source.is_file():
                raise HicoError(f"{source}: no checkpoint of step {step} (train with --save-every)")
            (scratch / "checkpoints").mkdir()
            shutil.copy2(source, checkpoint_path(scratch / "checkpoints", step))
        # a point at the run's last step trains a little past it: the schedules stretch by that much
        config = dataclasses.replace(config, max_steps=max(config.max_steps, step + warmup + steps))
        timer = StageTimer(warmup_steps=warmup)
        window = _Window(timer, step + warmup, step + warmup + steps)
        trainer = config.setup(callbacks=[window])
        timer.device = trainer.device
        camera = trainer.dataset.cameras
        pixels = int((camera.widths * camera.heights).float().mean())
        with timer.attach(trainer.model, trainer.optimizers):
            trainer.train()
    return {"step": step, "downscale": downscale, "pixels": pixels, "anchors": window.anchors,
            "gaussians": window.gaussians, "stage_ms": timer.mean_ms(), "wall_ms": 1e3 * window.seconds / steps,
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def _table(points: list[dict]) -> str:
    heads = [f"step {p['step']} @ {p['pixels'] / 1e3:.0f}k px" for p in points]
    width = max(14, *(len(h) + 2 for h in heads))
    lines = ["stage".ljust(12) + "".join(h.rjust(width) for h in heads)]
    for stage in STAGES:
        lines.append(stage.ljust(12) + "".join(f"{p['stage_ms'][stage]:{width}.1f}" for p in points))
    rows = (("sum", lambda p: f"{sum(p['stage_ms'].values()):.1f}"), ("wall", lambda p: f"{p['wall_ms']:.1f}"),
            ("anchors", lambda p: f"{p['anchors']:,}"), ("gaussians", lambda p: f"{p['gaussians']:,}"),
            ("peak RSS MiB", lambda p: f"{p['peak_rss_mib']:.0f}"))
    for name, cell in rows:
        lines.append(name.ljust(12) + "".join(cell(p).rjust(width) for p in points))
    return "\n".join(lines)


def _exponent(ms_a: float, ms_b: float, x_a: float, x_b: float) -> str:
    if min(ms_a, ms_b) < 0.05 or x_a == x_b:  # too small to time, or nothing changed
        return "-"
    return f"{math.log(ms_b / ms_a) / math.log(x_b / x_a):+.2f}"


def _growth(points: list[dict]) -> str:
    """Exponents between neighbouring points that differ in one thing only."""
    pairs = []
    for a in points:
        for b in points:
            if a["step"] == b["step"] and a["pixels"] < b["pixels"]:
                pairs.append((f"pixels x{b['pixels'] / a['pixels']:.1f} at step {a['step']}", a, b, "pixels"))
            if a["downscale"] == b["downscale"] and a["step"] < b["step"]:
                if a["gaussians"] and b["gaussians"] > a["gaussians"]:
                    pairs.append((f"Gaussians x{b['gaussians'] / a['gaussians']:.2f} (step {a['step']} -> "
                                  f"{b['step']}) at {a['pixels'] / 1e3:.0f}k px", a, b, "gaussians"))
    lines = []
    for label, a, b, key in pairs:
        cells = ", ".join(f"{stage} {_exponent(a['stage_ms'][stage], b['stage_ms'][stage], a[key], b[key])}"
                          for stage in STAGES)
        lines.append(f"{label}: {cells}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--at", type=int, nargs="+", default=[0, 1000, 3000], help="steps to profile at")
    parser.add_argument("--downscales", type=int, nargs="+", default=[0], help="data --downscale values (0: the run's)")
    parser.add_argument("--steps", type=int, default=20, help="timed steps per point")
    parser.add_argument("--warmup", type=int, default=3, help="untimed steps before them")
    parser.add_argument("--json", type=Path, default=None, help="also write the points here")
    parser.add_argument("--point", action="store_true", help=argparse.SUPPRESS)  # one point, JSON on stdout
    args = parser.parse_args()
    if not (args.run_dir / "config.yml").is_file():
        sys.exit(f"step_profile: {args.run_dir}/config.yml not found (expected a hico-train run directory)")
    try:
        if args.point:
            print(json.dumps(profile_point(args.run_dir, args.at[0], args.downscales[0], args.steps, args.warmup)))
            return
        points = []
        for downscale in args.downscales:
            for step in args.at:
                print(f"profiling step {step}, downscale {downscale or 'as trained'} ...", file=sys.stderr, flush=True)
                done = subprocess.run([sys.executable, __file__, str(args.run_dir), "--point", "--at", str(step),
                                       "--downscales", str(downscale), "--steps", str(args.steps),
                                       "--warmup", str(args.warmup)], capture_output=True, text=True)
                if done.returncode != 0:
                    sys.exit(f"step_profile: step {step}, downscale {downscale}: {done.stderr.strip().splitlines()[-1]}")
                points.append(json.loads(done.stdout.strip().splitlines()[-1]))
    except HicoError as err:
        sys.exit(f"step_profile: {err}")
    print(f"{args.run_dir}: {args.steps} steps per point after {args.warmup} warm-up, ms per step")
    print(_table(points))
    growth = _growth(points)
    if growth:
        print("\ngrowth, ms ~ x^a:")
        print(growth)
    if args.json is not None:
        args.json.write_text(json.dumps(points, indent=2) + "\n")


if __name__ == "__main__":
    main()
