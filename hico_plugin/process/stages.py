"""Resumable stages: a stage's result is kept with a key of everything it depends on.

A stage writes ``OUT/.hico_process/<stage>.json`` (its key and summary) only after its outputs are
complete, so re-running after a crash skips finished stages whose inputs and options are unchanged
and redoes the one that was interrupted.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

Report = Callable[[int, int], None]  # (done, total)


def stage_key(*parts: Any) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def write_json_atomic(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as handle:
            json.dump(data, handle, indent=2)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


class StageRunner:
    """Runs named stages in order with a progress bar each, skipping those already done."""

    def __init__(self, out: Path, console: Console | None = None):
        self.state_dir = out / ".hico_process"
        self.console = console or Console(stderr=True)
        self.timings: dict[str, float] = {}
        self.reused: list[str] = []

    def run(self, name: str, key: str, work: Callable[[Report], dict[str, Any] | None]) -> dict[str, Any]:
        """``work(report)`` unless stage ``name`` finished before with the same ``key``; returns the
        stage's summary dict (stored, so a reused stage still reports its figures)."""
        marker = self.state_dir / f"{name}.json"
        if marker.is_file():
            try:
                stored = json.loads(marker.read_text())
                if stored.get("key") == key:
                    self.console.print(f"[dim]{name:<12} reused (finished before with the same inputs)[/dim]")
                    self.reused.append(name)
                    self.timings[name] = 0.0
                    return stored.get("summary", {})
            except ValueError:
                pass  # a damaged marker: redo the stage
        marker.unlink(missing_ok=True)
        start = time.perf_counter()
        columns = (SpinnerColumn(), TextColumn(f"{name:<12}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
        with Progress(*columns, console=self.console, transient=False) as progress:
            task = progress.add_task(name, total=None)

            def report(done: int, total: int) -> None:
                progress.update(task, completed=done, total=total)

            summary = work(report) or {}
            progress.update(task, completed=progress.tasks[0].total or 1, total=progress.tasks[0].total or 1)
        self.timings[name] = time.perf_counter() - start
        write_json_atomic(marker, {"key": key, "summary": summary})
        return summary
