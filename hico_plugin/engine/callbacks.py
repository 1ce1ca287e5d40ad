"""Trainer callbacks: progress bar, JSON-lines metrics log, TensorBoard. They run on rank 0 only.

A callback overrides any of the hooks; the viewer joins the same way (``trainer.add_callback``).
``metrics`` holds floats: the step's loss and model metrics (averaged over ranks), ``lr/<group>``,
the model's ``stats()``, ``it_per_s`` and ``train_seconds``.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from hico_plugin.errors import HicoError

if TYPE_CHECKING:
    from hico_plugin.engine.trainer import Trainer


def default_callbacks(run_dir: Path, max_steps: int, log_every: int, progress: str, tensorboard: bool) -> list[TrainerCallback]:
    """The callbacks of every run: the metrics log, the progress display (``progress``: 'auto' is a
    rich bar on a terminal and plain lines otherwise, or 'rich' / 'lines' / 'none') and TensorBoard."""
    callbacks: list[TrainerCallback] = [MetricsLog(run_dir / "metrics.jsonl", log_every)]
    if progress == "rich" or (progress == "auto" and sys.stdout.isatty()):
        callbacks.append(ProgressBar(max_steps))
    elif progress in ("auto", "lines"):
        callbacks.append(ProgressLines(max_steps))
    if tensorboard:
        try:
            import tensorboard  # noqa: F401  (only checks that the optional package is there)
        except ImportError:
            raise HicoError("config.vis: 'tensorboard' needs the tensorboard package (pip install tensorboard)") from None
        callbacks.append(TensorBoardLog(run_dir / "tensorboard", log_every))
    return callbacks


class TrainerCallback:
    """Hooks the Trainer calls on rank 0; every one defaults to doing nothing."""

    def on_train_start(self, trainer: "Trainer", step: int) -> None:
        pass

    def on_step_end(self, step: int, metrics: dict[str, float]) -> None:
        pass

    def on_eval(self, step: int, results: dict[str, Any]) -> None:
        pass

    def on_train_end(self, step: int) -> None:
        pass


class MetricsLog(TrainerCallback):
    """Appends one JSON object per logged step / eval to ``RUN/metrics.jsonl``.

    Step lines: ``{"step", "time", <metrics>}``; eval lines: ``{"step", "time", "eval/<key>": ...}``.
    A resumed run appends to the same file.
    """

    def __init__(self, path: Path, log_every: int):
        self.path = path
        self.log_every = max(1, log_every)
        self._stream: IO[str] | None = None

    def _write(self, record: dict[str, Any]) -> None:
        if self._stream is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._stream = self.path.open("a", encoding="utf-8")
        self._stream.write(json.dumps(record, allow_nan=True) + "\n")
        self._stream.flush()

    def on_step_end(self, step: int, metrics: dict[str, float]) -> None:
        if step % self.log_every == 0 or metrics.get("skipped"):
            self._write({"step": step, "time": time.time(), **metrics})

    def on_eval(self, step: int, results: dict[str, Any]) -> None:
        self._write({"step": step, "time": time.time(), **{f"eval/{k}": v for k, v in results.items()}})

    def on_train_end(self, step: int) -> None:
        if self._stream is not None:
            self._stream.close()
            self._stream = None


class TensorBoardLog(TrainerCallback):
    """Scalars to TensorBoard event files in ``RUN/tensorboard`` (needs the ``tensorboard`` package)."""

    def __init__(self, log_dir: Path, log_every: int):
        from torch.utils.tensorboard import SummaryWriter  # imports tensorboard; checked by the caller

        self.writer = SummaryWriter(log_dir=str(log_dir))
        self.log_every = max(1, log_every)

    def on_step_end(self, step: int, metrics: dict[str, float]) -> None:
        if step % self.log_every == 0:
            for key, value in metrics.items():
                if isinstance(value, (int, float)) and math.isfinite(value):
                    self.writer.add_scalar(f"train/{key}", value, step)

    def on_eval(self, step: int, results: dict[str, Any]) -> None:
        for key, value in results.items():
            if isinstance(value, (int, float)) and math.isfinite(value):
                self.writer.add_scalar(f"eval/{key}", value, step)

    def on_train_end(self, step: int) -> None:
        self.writer.close()


# Shown in the progress bar when present, in this order, with their short labels.
_BAR_FIELDS = (("loss", "loss"), ("psnr", "psnr"), ("num_anchors", "anchors"), ("num_gaussians", "gaussians"))


def format_bar_metrics(metrics: dict[str, float]) -> str:
    """A compact one-line summary: loss terms, PSNR, #anchors, #Gaussians."""
    parts = []
    for key, label in _BAR_FIELDS:
        if key in metrics:
            value = metrics[key]
            parts.append(f"{label} {int(value):,}" if key.startswith("num_") else f"{label} {value:.4g}")
    parts += [f"{k[5:]} {v:.3g}" for k, v in metrics.items() if k.startswith("loss/")]
    return " | ".join(parts)


class ProgressBar(TrainerCallback):
    """A rich progress bar: step / total, it/s, ETA and ``format_bar_metrics``."""

    def __init__(self, max_steps: int, refresh_every: int = 1, stream: IO[str] | None = None):
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.max_steps = max_steps
        self.refresh_every = max(1, refresh_every)
        self.progress = Progress(
            TextColumn("[bold]train"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[speed]}"),
            TimeRemainingColumn(),
            TextColumn("{task.fields[summary]}"),
            console=Console(file=stream or sys.stdout),
            transient=False,
        )
        self.task = None

    def on_train_start(self, trainer: "Trainer", step: int) -> None:
        self.progress.start()
        self.task = self.progress.add_task("train", total=self.max_steps, completed=step, speed="", summary="")

    def on_step_end(self, step: int, metrics: dict[str, float]) -> None:
        if self.task is None or (step + 1) % self.refresh_every:
            return
        speed = f"{metrics['it_per_s']:.2f} it/s" if "it_per_s" in metrics else ""
        self.progress.update(self.task, completed=step + 1, speed=speed, summary=format_bar_metrics(metrics))

    def on_eval(self, step: int, results: dict[str, Any]) -> None:
        if self.task is not None and results.get("psnr") is not None:
            self.progress.console.print(f"step {step + 1}: test PSNR {results['psnr']:.2f} dB")

    def on_train_end(self, step: int) -> None:
        if self.task is not None:
            self.progress.stop()
            self.task = None


class ProgressLines(TrainerCallback):
    """Plain progress lines for logs (stdout not a terminal): the expected wall time of the run once
    the first steps are timed, then a line every ``every_seconds`` (and at the last step).

    Every estimate of the time left counts the steps after the first only: the first carries one-off
    costs (kernel builds on a first run, caches filling)."""

    def __init__(self, max_steps: int, timed_steps: int = 5, every_seconds: float = 60.0,
                 stream: IO[str] | None = None, clock=time.perf_counter):
        self.max_steps = max_steps
        self.timed_steps = timed_steps
        self.every_seconds = every_seconds
        self.stream = stream or sys.stdout
        self.clock = clock
        self._start = self._timing_start = self._last = 0.0
        self._first_step = 0
        self._full_steps = lambda start, stop: float(stop - start)

    def _print(self, text: str) -> None:
        print(text, file=self.stream, flush=True)

    def on_train_start(self, trainer: "Trainer", step: int) -> None:
        self._start = self._last = self.clock()
        self._first_step = step
        if trainer is not None:
            # Under the coarse-to-fine schedule a step's cost grows with its pixels, so the time left
            # is counted in full-resolution steps, not steps.
            cameras = trainer.dataset.cameras
            long_side = int(max(cameras.widths.max(), cameras.heights.max()))
            schedule, max_steps = trainer.config.resolution, self.max_steps
            self._full_steps = lambda start, stop: schedule.full_steps(start, stop, max_steps, long_side)
        self._print(f"train: {self.max_steps - step} steps to go; timing the first {self.timed_steps} for an estimate")

    def on_step_end(self, step: int, metrics: dict[str, float]) -> None:
        now = self.clock()
        done = step + 1 - self._first_step
        if done == 1:
            self._timing_start = now
        elif done == 1 + self.timed_steps:
            per_step = (now - self._timing_start) / self.timed_steps
            remaining = per_step * self._left_over(self._first_step + 1, step + 1)
            scale = metrics.get("resolution_scale", 1.0)
            coarse = (f", images at {scale:.2f} of full size, later steps weighed by their pixels"
                      if scale < 1.0 else "")
            self._print(f"train: expected wall time {_duration(now - self._start + remaining)} "
                        f"({per_step:.2f} s/step over steps 2-{done}{coarse}; {_duration(remaining)} left)")
        if now - self._last >= self.every_seconds or step + 1 == self.max_steps:
            self._last = now
            elapsed = now - self._start
            if done == 1 and step + 1 < self.max_steps:
                eta = "the first step, one-off setup included; the time left follows from the next steps"
            else:
                timed = now - self._timing_start  # the steps after the first
                left = timed / max(done - 1, 1) * self._left_over(self._first_step + 1, step + 1)
                eta = f"~{_duration(left)} left"
            self._print(f"step {step + 1}/{self.max_steps}  {_duration(elapsed)} elapsed, {eta}  "
                        f"{format_bar_metrics(metrics)}")

    def on_eval(self, step: int, results: dict[str, Any]) -> None:
        if results.get("psnr") is not None:
            self._print(f"step {step + 1}: test PSNR {results['psnr']:.2f} dB")

    def _left_over(self, timed_from: int, next_step: int) -> float:
        """Steps left after ``next_step - 1``, in units of the mean step of ``timed_from..next_step-1``."""
        timed = self._full_steps(timed_from, next_step)
        return self._full_steps(next_step, self.max_steps) * (next_step - timed_from) / max(timed, 1e-12)


def _duration(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}" if seconds >= 3600 else \
        f"{seconds // 60}:{seconds % 60:02d}"
