"""Resumable stages: a stage's result is kept with a key of everything it depends on.

A stage writes ``OUT/.hico_process/<stage>.json`` (its key, summary and time) only after its outputs are
complete, so re-running after a crash skips finished stages whose inputs and options are unchanged
and redoes the one that was interrupted (the matching stage keeps the pairs it had matched, matching.py).
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

from hico_plugin.storage import write_text_atomic

Report = Callable[[int, int], None]  # (done, total)


def stage_key(*parts: Any) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def write_json_atomic(path: Path, data: Any) -> None:
    write_text_atomic(path, json.dumps(data, indent=2))


def duration(seconds: float) -> str:
    """``seconds`` as a person reads it: 8.2 s, 12 min 05 s, 2 h 03 min."""
    if seconds < 60:
        return f"{seconds:.1f} s"
    minutes = int(seconds // 60)
    return f"{minutes} min {int(seconds % 60):02d} s" if minutes < 60 else f"{minutes // 60} h {minutes % 60:02d} min"


class StageRunner:
    """Runs named stages in order, skipping those already done. A running stage shows a progress bar on
    a terminal, or else a line when it starts and one every ``every_s`` seconds with its count so far;
    every stage ends with a line of its time and counts."""

    def __init__(self, out: Path, console: Console | None = None, every_s: float = 60.0,
                 clock: Callable[[], float] = time.perf_counter):
        self.state_dir = out / ".hico_process"
        self.console = console or Console(stderr=True)
        self.every_s = every_s
        self.clock = clock
        self.timings: dict[str, float] = {}
        self.reused: list[str] = []
        self._started = False

    def say(self, text: str) -> None:
        """One line of the run's log, as is (no markup)."""
        self.console.print(text, markup=False, highlight=False, soft_wrap=True)

    def run(self, name: str, key: str, work: Callable[[Report], dict[str, Any] | None], unit: str = "",
            describe: Callable[[dict[str, Any]], str] | None = None) -> dict[str, Any]:
        """``work(report)`` unless stage ``name`` finished before with the same ``key``; returns the
        stage's summary dict (stored, so a reused stage still reports its figures). ``report(done,
        total)`` counts ``unit``; ``describe(summary)`` words the stage's counts for its last line."""
        marker = self.state_dir / f"{name}.json"
        counts = (lambda summary: f": {describe(summary)}" if describe else "")
        if marker.is_file():
            try:
                stored = json.loads(marker.read_text())
                if stored.get("key") == key:
                    summary = stored.get("summary", {})
                    self.say(f"{name:<12} reused (finished before with the same inputs){counts(summary)}")
                    self.reused.append(name)
                    self.timings[name] = 0.0
                    return summary
            except (ValueError, KeyError, TypeError):
                pass  # a damaged marker: redo the stage
        marker.unlink(missing_ok=True)
        if not self._started:  # what the lines below are, once, before the first stage that runs
            self._started = True
            self.say(f"hico-process: writing {self.state_dir.parent} one stage at a time; a stage that finished "
                     "is kept, so the same command resumes after a stop")
        start = self.clock()
        last = [(0, 0)]
        if self.console.is_terminal:
            columns = (SpinnerColumn(), TextColumn(f"{name:<12}"), BarColumn(), MofNCompleteColumn(),
                       TimeElapsedColumn())
            with Progress(*columns, console=self.console, transient=True) as progress:
                task = progress.add_task(name, total=None)

                def report(done: int, total: int) -> None:
                    last[0] = (done, total)
                    progress.update(task, completed=done, total=total)

                summary = work(report) or {}
        else:
            shown = [None]

            def report(done: int, total: int) -> None:
                last[0] = (done, total)
                now = self.clock()
                if shown[0] is None:
                    self.say(f"{name:<12} started ({total:,} {unit})")
                elif now - shown[0] >= self.every_s:
                    share = f" ({100 * done / total:.0f} %)" if total else ""
                    self.say(f"{name:<12} {done:,} of {total:,} {unit}{share}, {duration(now - start)} so far")
                else:
                    return
                shown[0] = now

            summary = work(report) or {}
        self.timings[name] = self.clock() - start
        done, total = last[0]
        tally = f"{done:,} {unit}" if done == total else f"{done:,} of {total:,} {unit}"
        self.say(f"{name:<12} done in {duration(self.timings[name])}" + (counts(summary) or f": {tally}"))
        write_json_atomic(marker, {"key": key, "summary": summary, "seconds": self.timings[name]})
        return summary
