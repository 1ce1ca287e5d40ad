"""The step loop: batches, optimisers, resume, eval, callbacks, distributed.

Its neighbours hold the rest: ``run_dir`` (where a run lives, its lock, the log trimmed on resume),
``checkpoints`` (files), ``stopping`` (SIGINT / SIGTERM / SIGHUP, the interrupted exit code),
``controls`` (pause / checkpoint / stop from the viewer), ``loading`` (a trained run for the CLIs).

Run directory (``config.output_dir``, locked while a trainer writes it)::

    config.yml                         the resolved config tree (``load_config`` reloads it)
    metrics.jsonl                      one JSON object per logged step / eval (trimmed on resume)
    checkpoints/step-XXXXXXXXX.ckpt    named by the number of completed steps; the last few kept
    eval.json                          ns-eval layout, written after the final evaluation

Steps: ``Trainer.step`` counts completed optimizer steps; hooks and callbacks get the 0-based index of
the step just run. The model's schedules use the same optimizer-step counter.
"""

from __future__ import annotations

import dataclasses
import shutil
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Literal

import torch
from torch import nn

from hico_plugin.config import InstantiateConfig
from hico_plugin.engine import distributed as dist_utils
from hico_plugin.engine.callbacks import MetricsLog, ProgressBar, TensorBoardLog, TrainerCallback
from hico_plugin.engine.checkpoints import (
    latest_checkpoint,
    load_checkpoint,
    newest_readable_checkpoint,
    rng_state,
    save_checkpoint,
    seed_everything,
    set_rng_state,
)
from hico_plugin.engine.config_io import save_config
from hico_plugin.engine.controls import TrainerControls
from hico_plugin.engine.data import batch_positions, make_batch, rank_slice
from hico_plugin.engine.evaluation import evaluate, write_eval_json
from hico_plugin.engine.optimizers import Optimizers
from hico_plugin.engine.protocol import StepOutput, TrainableModel, TrainDataset
from hico_plugin.engine.run_dir import RunLock, trim_metrics
from hico_plugin.engine.stopping import stop_on_signals
from hico_plugin.errors import HicoError


@dataclass
class TrainerConfig(InstantiateConfig):
    """A whole training run: what to train (``data``, ``model``) and how (the rest).

    Presets subclass this with concrete ``data`` / ``model`` config types. ``build`` makes the
    dataset with ``data.setup()`` and the model with ``model.setup(dataset=dataset)``; override it
    when a model needs more.
    """

    method_name: str = "hico-gs"
    """Method name recorded in eval.json."""
    experiment_name: str = "unnamed"
    """Experiment (scene) name recorded in eval.json."""
    output_dir: Path = Path("outputs/unnamed")
    """Run directory: config.yml, metrics.jsonl, checkpoints/, eval.json (hico-train's default:
    outputs/<experiment>/<method>/<timestamp>)."""
    timestamp: str = ""
    """Run folder name under outputs/<experiment>/<method>/ when --output-dir is not given (default:
    the start time, YYYY-MM-DD_HHMMSS; with --resume, the newest run there)."""
    data: InstantiateConfig | None = None
    """Dataset config; ``data.setup()`` returns the dataset."""
    model: InstantiateConfig | None = None
    """Model config; ``model.setup(dataset=...)`` returns the model."""
    max_steps: int = 30_000
    """Number of optimizer steps."""
    batch_size: int = 1
    """Views per step on each worker; the global batch is batch_size x number of workers."""
    seed: int = 42
    """Seed of python / numpy / torch and of the view order."""
    device: str = "auto"
    """'auto' (CUDA when available, else CPU), 'cpu', 'cuda' or 'cuda:N'."""
    eval_every: int = 0
    """Evaluate on the test split every N steps (0: only at the end)."""
    save_every: int = 2_000
    """Write a checkpoint every N steps (0: only at the end / on Ctrl-C)."""
    keep_checkpoints: int = 3
    """How many of the newest checkpoints to keep (0: keep all)."""
    log_every: int = 10
    """Write a metrics.jsonl line every N steps."""
    progress: Literal["auto", "rich", "none"] = "auto"
    """Progress bar: 'auto' shows it when stdout is a terminal."""
    vis: Literal["auto", "viewer", "tensorboard", "viewer+tensorboard", "none"] = "auto"
    """Live visualisation: 'auto' is 'viewer' on a terminal and 'none' otherwise."""
    resume: bool = False
    """Continue the run in output_dir from its latest checkpoint."""
    overwrite: bool = False
    """Start afresh in an output_dir that already holds checkpoints (deletes them)."""
    max_nonfinite_steps: int = 10
    """Stop the run after this many non-finite losses in a row (each such step is skipped)."""
    distributed_timeout_minutes: float = 30.0
    """Under torchrun: how long a worker waits for the others at a collective before failing."""

    def wants_viewer(self) -> bool:
        return "viewer" in self.vis or (self.vis == "auto" and sys.stdout.isatty())

    def wants_tensorboard(self) -> bool:
        return "tensorboard" in self.vis

    def build(self, device: torch.device) -> tuple[TrainableModel, TrainDataset]:
        """The model (on ``device``) and dataset this config describes."""
        if self.data is None or self.model is None:
            raise HicoError("config: 'data' and 'model' must be set to build a run")
        dataset = self.data.setup()
        model = self.model.setup(dataset=dataset)
        return model.to(device), dataset

    def setup(self, **kwargs: Any) -> "Trainer":
        """The Trainer of this run; ``model=`` / ``dataset=`` / ``callbacks=`` override ``build``."""
        return Trainer(self, **kwargs)


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise HicoError(f"config.device: '{name}' is not a device (expected auto, cpu, cuda or cuda:N)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise HicoError(f"config.device: '{name}' asked for but CUDA is not available")
    return device


@dataclass
class TrainResult:
    """How ``Trainer.train`` ended."""

    step: int
    """Completed optimizer steps."""
    interrupted: bool
    """True when stopped early (a stop signal / ``request_stop``) after saving a checkpoint."""
    checkpoint: Path | None
    """The last checkpoint written (rank 0; None elsewhere or when none was written)."""
    eval_results: dict[str, Any] | None
    """The final evaluation (rank 0, when not interrupted and the test split is not empty)."""


def _validate(config: TrainerConfig) -> None:
    for name in ("max_steps", "eval_every", "save_every", "keep_checkpoints"):
        if getattr(config, name) < 0:
            raise HicoError(f"config.{name}: expected >= 0, got {getattr(config, name)}")
    for name in ("batch_size", "log_every", "max_nonfinite_steps"):
        if getattr(config, name) < 1:
            raise HicoError(f"config.{name}: expected >= 1, got {getattr(config, name)}")


class Trainer:
    """Drives a ``TrainableModel`` over a ``TrainDataset``.

    Controls for the viewer (thread-safe): ``lock`` is held for the whole of every training step, so
    a render that holds it sees a consistent model and delays training by at most one render;
    ``pause()`` / ``resume_training()`` / ``is_paused``; ``request_checkpoint()`` (written at the end of
    the current step); ``request_stop()`` (checkpoint, then return). ``latest_metrics`` and
    ``last_eval`` hold the newest figures.
    """

    def __init__(
        self,
        config: TrainerConfig,
        model: TrainableModel | None = None,
        dataset: TrainDataset | None = None,
        callbacks: Iterable[TrainerCallback] = (),
    ):
        _validate(config)
        self.config = config
        self.device = dist_utils.local_device(resolve_device(config.device))
        self.distributed = dist_utils.init_distributed(self.device, config.distributed_timeout_minutes)
        self.rank = dist_utils.get_rank()
        self.world_size = dist_utils.get_world_size()
        seed_everything(config.seed)
        if model is None or dataset is None:
            built_model, built_dataset = config.build(self.device)
            model = built_model if model is None else model
            dataset = built_dataset if dataset is None else dataset
        self.model = model.to(self.device) if isinstance(model, nn.Module) else model
        self.dataset = dataset
        self.train_indices = [int(i) for i in dataset.train_indices]
        self.test_indices = [int(i) for i in dataset.test_indices]
        self.run_dir = Path(config.output_dir)
        self.checkpoint_dir = self.run_dir / "checkpoints"
        self.callbacks: list[TrainerCallback] = []
        self.step = 0
        self.train_seconds = 0.0
        self.last_checkpoint: Path | None = None
        self._saved_step = -1
        self.latest_metrics: dict[str, float] = {}
        self.last_eval: dict[str, Any] | None = None
        self.lock = threading.RLock()
        self.controls = TrainerControls(self.device)
        self.run_lock = RunLock(self.run_dir)
        if self.is_main:
            self.run_lock.acquire()
        try:
            self._start_run()
            if self.is_main:
                self._add_default_callbacks()
                self.callbacks += list(callbacks)
        except BaseException:
            self.run_lock.release()
            raise

    # ----------------------------------------------------------------- controls (viewer, signals)
    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def is_paused(self) -> bool:
        return self.controls.paused.is_set()

    def pause(self) -> None:
        self.controls.paused.set()

    def resume_training(self) -> None:
        self.controls.paused.clear()

    def request_checkpoint(self) -> None:
        self.controls.checkpoint_requested.set()

    def request_stop(self) -> None:
        self.controls.request_stop()

    def add_callback(self, callback: TrainerCallback) -> None:
        """Add a callback (rank 0 only: on other ranks callbacks are not run)."""
        if self.is_main:
            self.callbacks.append(callback)

    # ----------------------------------------------------------------- run directory and resume
    def _start_run(self) -> None:
        newest = None
        if self.is_main:
            # Fresh runs only ask whether checkpoints exist; resumes skip unreadable newer ones.
            newest = (newest_readable_checkpoint(self.checkpoint_dir) or (None, None))[0] if self.config.resume \
                else latest_checkpoint(self.checkpoint_dir)
        latest = dist_utils.broadcast_object(newest)
        if latest is not None and not self.config.resume:
            if not self.config.overwrite:
                raise HicoError(
                    f"{self.checkpoint_dir}: already holds checkpoints; pass --resume to continue that "
                    "run, --overwrite to start afresh, or choose another --output-dir"
                )
            if self.is_main:
                shutil.rmtree(self.checkpoint_dir)
            latest = None
        if latest is None and self.is_main:  # a fresh run: no stale logs of an earlier attempt
            for name in ("metrics.jsonl", "eval.json"):
                (self.run_dir / name).unlink(missing_ok=True)
        dist_utils.barrier()
        if latest is not None:
            self.load_checkpoint(latest)
            if self.is_main:
                trim_metrics(self.run_dir / "metrics.jsonl", self.step)
        else:
            if self.config.resume and self.is_main:
                print(f"note: no checkpoint in {self.checkpoint_dir}; starting a new run", file=sys.stderr)
            if isinstance(self.model, nn.Module):
                dist_utils.broadcast_module_(self.model)
            self.optimizers = self._make_optimizers()
        if self.is_main:  # resume / overwrite are one-off actions, not properties of the run
            try:
                save_config(dataclasses.replace(self.config, resume=False, overwrite=False), self.run_dir / "config.yml")
            except OSError as err:
                raise HicoError(f"{self.run_dir / 'config.yml'}: cannot write ({err.strerror or err})") from None

    def _make_optimizers(self) -> Optimizers:
        return Optimizers(self.model.param_groups(), self.model.lr_schedules(self.config.max_steps))

    def _add_default_callbacks(self) -> None:
        config = self.config
        self.callbacks.append(MetricsLog(self.run_dir / "metrics.jsonl", config.log_every))
        if config.progress == "rich" or (config.progress == "auto" and sys.stdout.isatty()):
            self.callbacks.append(ProgressBar(config.max_steps))
        if config.wants_tensorboard():
            try:
                import tensorboard  # noqa: F401  (only checks that the optional package is there)
            except ImportError:
                raise HicoError("config.vis: 'tensorboard' needs the tensorboard package (pip install tensorboard)") from None
            self.callbacks.append(TensorBoardLog(self.run_dir / "tensorboard", config.log_every))

    def load_checkpoint(self, path: Path) -> None:
        """Restore model, optimizers, step, train time and RNG states from ``path``."""
        from hico_plugin.engine.loading import restore_model

        payload = load_checkpoint(Path(path))
        restore_model(self.model, payload, Path(path))
        self.optimizers = self._make_optimizers()  # after loading: the model may hold new Parameters
        self.optimizers.load_state_dict(payload["optimizers"])
        self.step = int(payload["step"])
        self.train_seconds = float(payload.get("train_seconds", 0.0))
        rng_states = payload.get("rng", [])
        if len(rng_states) == self.world_size:
            set_rng_state(rng_states[self.rank])
        elif rng_states:  # resumed with another number of workers: the best we can do
            set_rng_state(rng_states[0])
        self.last_checkpoint = Path(path)
        self._saved_step = self.step

    def save_checkpoint(self) -> Path | None:
        """Write the checkpoint of the current step (a collective: every rank must call it)."""
        states = dist_utils.gather_objects(rng_state())
        self._saved_step = self.step  # on every rank, so all agree on whether a final save is due
        if not self.is_main:
            return None
        payload = {
            "step": self.step,
            "model": self.model.state_dict(),
            "optimizers": self.optimizers.state_dict(),
            "schedules": {k: dataclasses.asdict(v) for k, v in self.optimizers.schedules.items()},
            "rng": states,
            "train_seconds": self.train_seconds,
            "world_size": self.world_size,
        }
        self.last_checkpoint = save_checkpoint(
            self.checkpoint_dir, self.step, payload, self.config.keep_checkpoints
        )
        return self.last_checkpoint

    # ----------------------------------------------------------------- the step
    def _reduce_step_scalars(self, output: StepOutput) -> tuple[dict[str, float], bool]:
        """One all-reduce for the loss, the metrics (means over ranks; the metric names must be the
        same on every rank) and whether any rank's loss is non-finite.

        Returns (metrics, loss finite on every rank).
        """
        metric_names = sorted(output.metrics)
        values = [output.loss.detach().float().reshape(())]
        values += [torch.as_tensor(output.metrics[k], dtype=torch.float32).detach().reshape(-1).mean() for k in metric_names]
        nonfinite = (~torch.isfinite(output.loss.detach())).any().float().reshape(())
        vector = torch.stack([v.to(self.device) for v in values] + [nonfinite.to(self.device)])
        dist_utils.all_reduce_sum_(vector)
        vector = vector.cpu()
        means = (vector[:-1] / self.world_size).tolist()
        return dict(zip(["loss", *metric_names], means)), bool(vector[-1] == 0)

    def _train_step(self, step: int) -> tuple[dict[str, float], bool]:
        positions = batch_positions(
            len(self.train_indices), self.config.batch_size * self.world_size, self.config.seed, step
        )
        mine = rank_slice(positions, self.rank, self.world_size).tolist()
        batch = make_batch(self.dataset, [self.train_indices[p] for p in mine], self.device)
        self.optimizers.zero_grad()
        output = self.model.train_step(batch, step)
        metrics, finite = self._reduce_step_scalars(output)
        if not finite:
            self.optimizers.zero_grad()
            return metrics, False
        output.loss.backward()
        self.model.after_backward(step, output)
        dist_utils.average_gradients_(self.optimizers.all_params())
        lrs = self.optimizers.step(step)
        self.model.after_optimizer_step(step, self.optimizers)
        metrics.update({f"lr/{name}": lr for name, lr in lrs.items()})
        return metrics, True

    # ----------------------------------------------------------------- the loop
    def train(self) -> TrainResult:
        """Train from ``self.step`` to ``config.max_steps``; a stop signal (Ctrl-C, SIGTERM, SIGHUP)
        saves a checkpoint and returns with ``interrupted`` set. Releases the run directory's lock."""
        try:
            with stop_on_signals(self.controls.request_stop, announce=self.is_main):
                return self._train_loop()
        finally:
            self.run_lock.release()

    def _train_loop(self) -> TrainResult:
        config = self.config
        self._run_callbacks("on_train_start", self, self.step)
        nonfinite_streak = 0
        it_per_s = None
        stop, checkpoint, paused = self.controls.flags()
        if checkpoint:
            self.save_checkpoint()
        while self.step < config.max_steps and not stop:
            if paused and self.controls.wait_while_paused(self.save_checkpoint):
                stop = True
                break
            step = self.step
            start = time.perf_counter()
            with self.lock:
                try:
                    metrics, finite = self._train_step(step)
                except HicoError as err:  # a bad training image: keep what was trained so far
                    if self._saved_step != self.step:
                        self.save_checkpoint()
                    raise HicoError(f"{err} -- training stopped at step {self.step}, saved in "
                                    f"{self.last_checkpoint}; fix the file, then hico-train --resume") from None
            seconds = time.perf_counter() - start
            self.step += 1
            self.train_seconds += seconds
            it_per_s = 1.0 / seconds if it_per_s is None else 0.9 * it_per_s + 0.1 / seconds
            metrics.update({k: float(v) for k, v in self.model.stats().items()})
            metrics.update(it_per_s=it_per_s, train_seconds=self.train_seconds)
            if finite:
                nonfinite_streak = 0
            else:
                nonfinite_streak += 1
                metrics["skipped"] = 1.0
                if self.is_main:
                    print(f"warning: step {step}: non-finite loss, step skipped", file=sys.stderr)
            self.latest_metrics = metrics
            self._run_callbacks("on_step_end", step, metrics)
            if nonfinite_streak >= config.max_nonfinite_steps:
                self._run_callbacks("on_train_end", step)
                raise HicoError(
                    f"training: {nonfinite_streak} non-finite losses in a row (last at step {step}); "
                    f"stopped without saving; the last good checkpoint is {self.last_checkpoint or 'none'}"
                )
            stop, checkpoint, paused = self.controls.flags()  # after the callbacks, which may ask
            if checkpoint or stop or (config.save_every and self.step % config.save_every == 0):
                self.save_checkpoint()
            if not stop and config.eval_every and self.step % config.eval_every == 0 and self.step < config.max_steps:
                self._evaluate_keeping_model(step, write_json=False)
        interrupted = stop and self.step < config.max_steps
        if self._saved_step != self.step:
            self.save_checkpoint()
        try:
            eval_results = None if interrupted else self._evaluate_keeping_model(max(self.step - 1, 0), write_json=True)
        finally:
            self._run_callbacks("on_train_end", max(self.step - 1, 0))
        return TrainResult(self.step, interrupted, self.last_checkpoint if self.is_main else None, eval_results)

    def _evaluate_keeping_model(self, step: int, write_json: bool) -> dict[str, Any] | None:
        """``_evaluate_and_report``; a bad test file found while evaluating never loses the trained
        model: the checkpoint is written first and the error says how to re-run the evaluation."""
        try:
            return self._evaluate_and_report(step, write_json)
        except HicoError as err:
            if self._saved_step != self.step:
                self.save_checkpoint()
            raise HicoError(f"{err} -- evaluation failed, the model of step {self.step} is saved in "
                            f"{self.last_checkpoint}; fix the file, then run hico-eval --load-config "
                            f"{self.run_dir / 'config.yml'} (or --resume to train on)") from None

    def _evaluate_and_report(self, step: int, write_json: bool) -> dict[str, Any] | None:
        """Evaluate on rank 0 (others go on to the next collective and wait there)."""
        if not self.is_main or not self.test_indices:
            return None
        with self.lock:
            results = evaluate(self.model, self.dataset, self.test_indices, self.device)
        results["train_seconds"] = self.train_seconds
        results["step"] = self.step
        self.last_eval = results
        if write_json:
            self.write_eval_json(results)
        self._run_callbacks("on_eval", step, results)
        return results

    def write_eval_json(self, results: dict[str, Any]) -> Path:
        return write_eval_json(
            self.run_dir / "eval.json",
            self.config.experiment_name,
            self.config.method_name,
            str(self.last_checkpoint) if self.last_checkpoint else None,
            results,
        )

    def _run_callbacks(self, hook: str, *args: Any) -> None:
        if not self.is_main:
            return
        for callback in self.callbacks:
            method = getattr(callback, hook, None)  # duck-typed callbacks may leave hooks out
            if method is not None:
                method(*args)

