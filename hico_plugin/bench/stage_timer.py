"""Per-stage wall time of training steps, measured from outside the model.

``StageTimer`` wraps the callables of one model and optimiser *instance* (never the classes) and adds synchronised
``perf_counter`` intervals per stage: lod_select (LOD, Eq. 1, + frustum culling), clca (Sec. 3.3), decode (minus
clca), rasterize, losses, backward, stats (densification statistics), optimizer, densify (grow / prune). Each
stage also runs under ``torch.profiler.record_function(f"hico/{stage}")``; nested stages (clca inside decode) are
subtracted from their parent.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import torch

STAGES = ("lod_select", "clca", "decode", "rasterize", "losses", "backward", "stats", "optimizer", "densify")
"""Stage names in step order."""


def _sync(device: torch.device) -> None:
    # Asynchronous devices would otherwise charge queued kernels to whichever stage waits first.
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class StageTimer:
    """Accumulates seconds per stage over the steps it watched, after ``warmup_steps`` (their
    one-off costs, e.g. kernel compilation and allocator growth, would bias short runs).

    ``totals``: stage -> summed seconds; ``steps``: number of ``train_step`` calls counted.
    """

    def __init__(self, device: torch.device | str = "cpu", warmup_steps: int = 1):
        self.device = torch.device(device)
        self.warmup_steps = warmup_steps
        self._seen = 0
        self.totals = {stage: 0.0 for stage in STAGES}
        self.steps = 0
        self._stack: list[list[float]] = []  # per open stage: [start, seconds of nested stages]
        self._forward_end: float | None = None
        self._paused = False

    @contextmanager
    def paused(self) -> Iterator[None]:
        """Calls inside the block (e.g. evaluation renders) are not timed."""
        self._paused = True
        try:
            yield
        finally:
            self._paused = False

    def wrap(self, stage: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        """``fn`` timed as ``stage`` (time spent in nested timed stages is not charged twice)."""

        def timed(*args: Any, **kwargs: Any) -> Any:
            if self._paused:
                return fn(*args, **kwargs)
            _sync(self.device)
            frame = [time.perf_counter(), 0.0]
            self._stack.append(frame)
            try:
                with torch.profiler.record_function(f"hico/{stage}"):
                    return fn(*args, **kwargs)
            finally:
                _sync(self.device)
                elapsed = time.perf_counter() - frame[0]
                self._stack.pop()
                self.totals[stage] += elapsed - frame[1]
                if self._stack:
                    self._stack[-1][1] += elapsed
        return timed

    def mean_ms(self) -> dict[str, float]:
        """Milliseconds per training step of every stage (zeros before the first step)."""
        return {stage: 1e3 * seconds / max(self.steps, 1) for stage, seconds in self.totals.items()}

    def reset(self) -> None:
        self.totals = {stage: 0.0 for stage in STAGES}
        self.steps = 0

    @contextmanager
    def attach(self, model: Any, optimizers: Any | None = None) -> Iterator[StageTimer]:
        """Time ``model`` (a HiCoModel) and ``optimizers`` while inside the block; restores them after.

        Instance attributes shadow the class methods, so other models are untouched; modules are
        timed through their ``forward`` so ``module(...)`` hooks keep working.
        """
        patches: list[tuple[Any, str, Any]] = []
        missing = object()

        def patch(obj: Any, name: str, new: Any) -> None:
            patches.append((obj, name, vars(obj).get(name, missing)))
            setattr(obj, name, new)

        field = model.field
        patch(field, "select", self.wrap("lod_select", field.select))
        patch(field, "decode", self.wrap("decode", field.decode))
        patch(field.context, "forward", self.wrap("clca", field.context.forward))
        patch(field.context, "graph", self.wrap("clca", field.context.graph))  # which anchors it reads
        # Renderer and Losses are plain callable objects: ``__call__`` is looked up on the type, so
        # the model's attribute is replaced by a proxy.
        patch(model, "renderer", _TimedCall(model.renderer, self.wrap("rasterize", model.renderer)))
        patch(model, "losses", _TimedCall(model.losses, self.wrap("losses", model.losses)))
        patch(model, "train_step", self._train_step(model.train_step))
        patch(model, "after_backward", self._after_backward(self.wrap("stats", model.after_backward)))
        patch(model, "after_optimizer_step", self.wrap("densify", model.after_optimizer_step))
        if optimizers is not None:
            patch(optimizers, "step", self.wrap("optimizer", optimizers.step))
        try:
            yield self
        finally:
            for obj, name, original in reversed(patches):
                if original is missing:
                    delattr(obj, name)
                else:
                    setattr(obj, name, original)

    def _train_step(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            if self._paused:
                return fn(*args, **kwargs)
            if self._seen == self.warmup_steps:
                self.reset()
            self._seen += 1
            out = fn(*args, **kwargs)
            _sync(self.device)
            self.steps += 1
            self._forward_end = time.perf_counter()
            return out
        return timed

    def _after_backward(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            if self._forward_end is not None:
                _sync(self.device)
                self.totals["backward"] += time.perf_counter() - self._forward_end
                self._forward_end = None
            return fn(*args, **kwargs)
        return timed


class _TimedCall:
    """``target`` with its call replaced by ``timed``; every other attribute is ``target``'s."""

    def __init__(self, target: Any, timed: Callable[..., Any]):
        self._target, self._timed = target, timed

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._timed(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._target, name)
