"""Wall time of the training steps: the run's total (kept in checkpoints, so a resumed run goes on
counting) and a smoothed steps-per-second figure for the progress display."""

from __future__ import annotations

import time


class StepClock:
    """Times each step between ``start()`` and ``stop()``."""

    def __init__(self, train_seconds: float = 0.0):
        self.train_seconds = train_seconds
        """Summed wall time of the timed steps."""
        self.it_per_s: float | None = None
        """Exponential moving average (0.9) of 1 / step time; None before the first step."""
        self._start = 0.0

    def start(self) -> None:
        self._start = time.perf_counter()

    def stop(self) -> dict[str, float]:
        """Count the step; returns ``{"it_per_s", "train_seconds"}`` for the step's metrics."""
        seconds = time.perf_counter() - self._start
        self.train_seconds += seconds
        self.it_per_s = 1.0 / seconds if self.it_per_s is None else 0.9 * self.it_per_s + 0.1 / seconds
        return {"it_per_s": self.it_per_s, "train_seconds": self.train_seconds}
