"""The training run: its config and the loop that drives the steps, checkpoints and evaluations.

Its neighbour modules hold the parts: ``step``, ``data``, ``run_dir``, ``checkpoints``, ``disk_space``,
``evaluation``, ``controls``, ``stopping``, ``timing``, ``callbacks``, ``loading``. ``Trainer.step`` counts
completed optimizer steps, as the model's schedules do; hooks and callbacks get the 0-based index of the step just
run.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import threading
from dataclasses import dataclass, field as dataclass_field
from pathlib import Path
from typing import Any, Iterable, Literal

import torch
from torch import nn

from hico_plugin.config import InstantiateConfig
from hico_plugin.engine import distributed as dist_utils
from hico_plugin.engine.callbacks import TrainerCallback, default_callbacks
from hico_plugin.engine.checkpoints import (
    checkpoint_due,
    check_frame,
    dataset_frame,
    list_checkpoints,
    load_checkpoint,
    restore_model,
    restore_rank_rng,
    rng_state,
    save_checkpoint,
    seed_everything,
    training_payload,
)
from hico_plugin.engine.controls import TrainerControls
from hico_plugin.engine.data import rank_batch
from hico_plugin.engine.disk_space import check_free_space, run_bytes_needed
from hico_plugin.engine.evaluation import evaluate, periodic_eval_due, write_eval_json
from hico_plugin.engine.memory import keep_freed_memory
from hico_plugin.engine.optimizers import Optimizers
from hico_plugin.engine.protocol import TrainableModel, TrainDataset
from hico_plugin.engine.resolution import ResolutionSchedule, downscale_batch
from hico_plugin.engine.run_dir import (
    RunLock,
    start_checkpoint,
    trim_metrics,
    write_run_files,
)
from hico_plugin.engine.step import optimizer_step
from hico_plugin.engine.stopping import stop_on_signals
from hico_plugin.engine.timing import StepClock
from hico_plugin.errors import HicoError


@dataclass
class TrainerConfig(InstantiateConfig):
    """A whole training run: what to train (``data``, ``model``) and how (the rest).

    Presets subclass this with concrete ``data`` / ``model`` config types. ``build_dataset`` makes the
    dataset with ``data.setup()`` and ``build_model`` the model with ``model.setup(dataset=dataset)``;
    override the latter when a model needs more.
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
    """Number of optimizer steps (for a capture of up to steps_photos training photos)."""
    steps_photos: int = 0
    """Training photos up to which max_steps is the run's length: a capture with more trains
    proportionally longer, each photo seen as often, and every schedule scaled by the run's length
    (densification, octree levels, DNGC, learning-rate decay) follows. 0: max_steps whatever the capture."""
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
    progress: Literal["auto", "rich", "lines", "none"] = "auto"
    """Progress: 'auto' is a rich bar on a terminal and plain lines (with the expected wall time) otherwise."""
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
    resolution: ResolutionSchedule = dataclass_field(default_factory=ResolutionSchedule)
    """Coarse-to-fine training images (evaluation is always at full resolution)."""

    def validate(self) -> None:
        """A HicoError naming the first field out of range (run before anything is read)."""
        for name in ("max_steps", "steps_photos", "eval_every", "save_every", "keep_checkpoints"):
            if getattr(self, name) < 0:
                raise HicoError(f"config.{name}: expected >= 0, got {getattr(self, name)}")
        for name in ("batch_size", "log_every", "max_nonfinite_steps"):
            if getattr(self, name) < 1:
                raise HicoError(f"config.{name}: expected >= 1, got {getattr(self, name)}")
        self.resolution.validate()
        for part in (self.data, self.model):  # their own fields, when they check them
            validate_part = getattr(part, "validate", None)
            if callable(validate_part):
                validate_part()

    def sized_for(self, num_photos: int) -> "TrainerConfig":
        """This config with the run's length for ``num_photos`` training photos (``steps_photos``'s
        rule); the result is its own fixed point, so a resumed run keeps its length."""
        if self.steps_photos <= 0 or num_photos <= self.steps_photos:
            return self
        steps = math.ceil(self.max_steps * num_photos / self.steps_photos)
        return dataclasses.replace(self, max_steps=steps, steps_photos=num_photos)

    def wants_viewer(self) -> bool:
        return "viewer" in self.vis or (self.vis == "auto" and sys.stdout.isatty())

    def wants_tensorboard(self) -> bool:
        return "tensorboard" in self.vis

    def build_dataset(self, announce: bool = True, frame: dict | None = None) -> TrainDataset:
        """The dataset: cameras, poses and seed points parsed, images left on disk (cheap, so the checks
        that need the dataset's frame or size run before the model is built). Its notes are printed
        when ``announce``. ``frame``: a checkpoint's scene frame to load the views in (``data.setup``
        takes it as ``frame=``), None to normalise afresh."""
        if self.data is None or self.model is None:
            raise HicoError("config: 'data' and 'model' must be set to build a run")
        if frame is None:
            return self.data.setup(announce=announce)
        return self.data.setup(announce=announce, frame=frame)

    def build_model(self, dataset: TrainDataset, device: torch.device) -> TrainableModel:
        """The model of ``dataset`` on ``device`` (the slow part: data analyses, the model's setup)."""
        return self.model.setup(dataset=dataset).to(device)

    def run_bytes_needed(self, dataset: TrainDataset) -> int:
        """Disk space the run will need (``disk_space.run_bytes_needed``), from the model config's
        checkpoint size estimate for the dataset's seed points when it has one, else logs only."""
        estimate = getattr(self.model, "checkpoint_bytes", None)
        points = getattr(dataset, "points", None)
        checkpoint = estimate(len(points)) if callable(estimate) and points is not None else 0
        return run_bytes_needed(checkpoint, self.keep_checkpoints, self.max_steps, self.save_every)

    def setup(self, **kwargs: Any) -> "Trainer":
        """The Trainer of this run; ``model=`` / ``dataset=`` / ``callbacks=`` override
        ``build_model`` / ``build_dataset``."""
        return Trainer(self, **kwargs)


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
        config.validate()
        self.config = config
        self.device = dist_utils.local_device(dist_utils.resolve_device(config.device))
        self.distributed = dist_utils.init_distributed(self.device, config.distributed_timeout_minutes)
        self.rank = dist_utils.get_rank()
        self.world_size = dist_utils.get_world_size()
        self.run_dir = Path(config.output_dir)
        self.checkpoint_dir = self.run_dir / "checkpoints"
        self.callbacks: list[TrainerCallback] = []
        self.step = 0
        self.clock = StepClock()
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
            # Every check that can refuse the run comes before anything slow (decoding images, the data
            # analyses, building the model) and before the dataset's notes are printed, so a refusal is
            # the one line a refused run prints: the lock above, how the run starts (fresh / resumed /
            # overwritten), the checkpoint's frame against a parse of the cameras, the free space.
            latest, payload = start_checkpoint(self.run_dir, config.resume, config.overwrite, self.is_main)
            if latest is not None and payload is None:  # a rank other than 0 reads the checkpoint itself
                payload = load_checkpoint(latest)
            seed_everything(config.seed)
            if dataset is None:
                dataset = config.build_dataset(announce=False, frame=(payload or {}).get("frame"))
            if payload is not None:
                check_frame(payload, dataset, latest)
            self.config = config = config.sized_for(len(dataset.train_indices))
            self._check_free_space(dataset)
            if self.is_main:
                if config.resume and latest is None:
                    print(f"note: no checkpoint in {self.checkpoint_dir}; starting a new run", file=sys.stderr)
                for note in getattr(dataset, "notes", ()):
                    print(note, file=sys.stderr)
            if model is None:
                model = config.build_model(dataset, self.device)
            self.model = model.to(self.device) if isinstance(model, nn.Module) else model
            self.dataset = dataset
            self.train_indices = [int(i) for i in dataset.train_indices]
            self.test_indices = [int(i) for i in dataset.test_indices]
            self._start_run(latest, payload)
            if self.is_main:
                self.callbacks += default_callbacks(self.run_dir, config.max_steps, config.log_every,
                                                    config.progress, config.wants_tensorboard())
                self.callbacks += list(callbacks)
        except BaseException:
            self.run_lock.abandon()
            raise

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def train_seconds(self) -> float:
        """Wall time spent in training steps, over every session of the run."""
        return self.clock.train_seconds

    # ----------------------------------------------------------------- controls (viewer, signals)
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

    # ----------------------------------------------------------------- start, checkpoints
    def _check_free_space(self, dataset: TrainDataset) -> None:
        """Refuse (on every rank) when rank 0's run directory lacks the space the run needs; its own
        checkpoints count as free (a resumed run rotates them out)."""
        problem = None
        if self.is_main:
            try:
                reclaimable = sum(path.stat().st_size for path in list_checkpoints(self.checkpoint_dir))
                check_free_space(self.run_dir, self.config.run_bytes_needed(dataset), reclaimable)
            except HicoError as err:
                problem = str(err)
        problem = dist_utils.broadcast_object(problem)
        if problem is not None:
            raise HicoError(problem)

    def _start_run(self, latest: Path | None, payload: dict[str, Any] | None) -> None:
        """Restore the checkpoint ``latest`` (its ``payload``, frame already checked) or start afresh."""
        if latest is not None and payload is not None:  # both or neither
            self._restore(latest, payload)
            if self.is_main:
                trim_metrics(self.run_dir / "metrics.jsonl", self.step)
        else:
            if isinstance(self.model, nn.Module):
                dist_utils.broadcast_module_(self.model)
            self.optimizers = self._make_optimizers()
        if self.is_main:
            write_run_files(self.run_dir, self.config, self.model)

    def _make_optimizers(self) -> Optimizers:
        return Optimizers(self.model.param_groups(), self.model.lr_schedules(self.config.max_steps))

    def _restore(self, path: Path, payload: dict[str, Any]) -> None:
        """Restore model, optimizers, step, train time and RNG states from ``payload`` (read from ``path``)."""
        restore_model(self.model, payload, Path(path))
        self.optimizers = self._make_optimizers()  # after loading: the model may hold new Parameters
        renamed = getattr(self.model, "renamed_param_groups", dict)()  # an older checkpoint's group names
        self.optimizers.load_state_dict({renamed.get(name, name): state for name, state in payload["optimizers"].items()})
        self.step = int(payload["step"])
        self.clock = StepClock(float(payload.get("train_seconds", 0.0)))
        restore_rank_rng(payload, self.rank, self.world_size)
        self.last_checkpoint = Path(path)
        self._saved_step = self.step

    def save_checkpoint(self) -> Path | None:
        """Write the checkpoint of the current step (a collective: every rank must call it)."""
        states = dist_utils.gather_objects(rng_state())
        self._saved_step = self.step  # on every rank, so all agree on whether a final save is due
        if not self.is_main:
            return None
        payload = training_payload(self.step, self.model, self.optimizers, states, self.train_seconds, self.world_size,
                                   dataset_frame(self.dataset))
        self.last_checkpoint = save_checkpoint(self.checkpoint_dir, self.step, payload, self.config.keep_checkpoints)
        return self.last_checkpoint

    def _keep_model(self, err: HicoError, message: str) -> HicoError:
        """A bad file found while training or evaluating never loses the trained model: the checkpoint
        of this step is written (when not yet), and the error returned says where it is and how to go
        on (``message`` with {step} and {checkpoint})."""
        if self._saved_step != self.step:
            self.save_checkpoint()
        return HicoError(f"{err} -- {message.format(step=self.step, checkpoint=self.last_checkpoint)}")

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
        keep_freed_memory()  # every step frees and reallocates the same large temporaries
        self._run_callbacks("on_train_start", self, self.step)
        nonfinite_streak = 0
        stop, checkpoint, paused = self.controls.flags()
        if checkpoint:
            self.save_checkpoint()
        while self.step < config.max_steps and not stop:
            if paused and self.controls.wait_while_paused(self.save_checkpoint):
                stop = True
                break
            step = self.step
            self.clock.start()
            with self.lock:
                try:
                    batch = rank_batch(self.dataset, self.train_indices, config.batch_size, config.seed, step,
                                       self.rank, self.world_size, self.device, getattr(self.model, "train_gt", None))
                    long_side = max(batch.cameras[0].width, batch.cameras[0].height)
                    scale = config.resolution.scale(step, config.max_steps, long_side)
                    batch = downscale_batch(batch, scale)
                    metrics, finite = optimizer_step(self.model, self.optimizers, batch, step, self.device,
                                                     self.world_size)
                except HicoError as err:  # a bad training image: keep what was trained so far
                    raise self._keep_model(err, "training stopped at step {step}, saved in {checkpoint}; "
                                                "fix the file, then hico-train --resume") from None
            timing = self.clock.stop()
            self.step += 1
            metrics.update({k: float(v) for k, v in self.model.stats().items()})
            metrics.update(timing)
            if scale < 1.0:  # the coarse-to-fine schedule's image size of this step (metrics.jsonl)
                metrics["resolution_scale"] = scale
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
            if checkpoint or stop or checkpoint_due(self.step, config.save_every):
                self.save_checkpoint()
            if not stop and periodic_eval_due(self.step, config.eval_every, config.max_steps):
                self._evaluate(step, write_json=False)
        interrupted = stop and self.step < config.max_steps
        if self._saved_step != self.step:
            self.save_checkpoint()
        if not interrupted:
            # The run is complete and its last checkpoint holds the moments: the final evaluation
            # does not hold them beside its own peak.
            self.optimizers.release_state()
        try:
            eval_results = None if interrupted else self._evaluate(max(self.step - 1, 0), write_json=True)
        finally:
            self._run_callbacks("on_train_end", max(self.step - 1, 0))
        return TrainResult(self.step, interrupted, self.last_checkpoint if self.is_main else None, eval_results)

    # ----------------------------------------------------------------- evaluation
    def _evaluate(self, step: int, write_json: bool) -> dict[str, Any] | None:
        """Evaluate on rank 0 (others go on to the next collective and wait there)."""
        if not self.is_main or not self.test_indices:
            return None
        try:
            with self.lock:
                self.optimizers.zero_grad()  # the last step's are spent (the next step starts with this): not held while evaluating
                results = evaluate(self.model, self.dataset, self.test_indices, self.device)
            results["train_seconds"] = self.train_seconds
            results["step"] = self.step
            self.last_eval = results
            if write_json:
                self.write_eval_json(results)
            self._run_callbacks("on_eval", step, results)
        except HicoError as err:
            raise self._keep_model(err, "evaluation failed, the model of step {step} is saved in {checkpoint}; "
                                        f"fix the file, then run hico-eval --load-config {self.run_dir / 'config.yml'} "
                                        "(or --resume to train on)") from None
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
