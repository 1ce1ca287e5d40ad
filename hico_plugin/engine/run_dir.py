"""The run directory: where a run lives, one trainer at a time, and its log trimmed on resume.

Like nerfstudio, a run without ``--output-dir`` gets its own folder
``outputs/<experiment>/<method>/<timestamp>/``; ``--resume`` without one continues the newest there.
While a trainer writes a run it holds an exclusive ``flock`` on ``RUN/.lock`` (the kernel drops it
when the process dies, however it dies, so a crash never leaves a stale lock); a second trainer on
the same folder refuses in one line.
"""

from __future__ import annotations

import fcntl
import json
import os
import time
from pathlib import Path
from typing import IO

from hico_plugin.engine.config_io import write_text_atomic
from hico_plugin.errors import HicoError

TIMESTAMP_FORMAT = "%Y-%m-%d_%H%M%S"
LOCK_NAME = ".lock"


def run_directory(base: Path, timestamp: str, resume: bool) -> Path:
    """``base/<timestamp>``: the given timestamp, else (resume) the newest run under ``base`` holding
    a config.yml, else the current time."""
    if timestamp:
        if Path(timestamp).name != timestamp or timestamp in (".", ".."):
            raise HicoError(f"--timestamp: {timestamp!r} must be a plain folder name")
        return base / timestamp
    if resume:
        runs = sorted(p.parent for p in base.glob("*/config.yml"))
        if not runs:
            raise HicoError(f"--resume: no run under {base} to resume (pass --output-dir RUN)")
        return runs[-1]
    return base / time.strftime(TIMESTAMP_FORMAT)


class RunLock:
    """An exclusive lock on a run directory while a trainer writes it."""

    def __init__(self, run_dir: Path):
        self.path = Path(run_dir) / LOCK_NAME
        self._stream: IO[str] | None = None

    def acquire(self) -> None:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            stream = self.path.open("a+", encoding="utf-8")
        except OSError as err:
            raise HicoError(f"{self.path.parent}: cannot create the run directory ({err.strerror or err})") from None
        try:
            fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            stream.seek(0)
            owner = stream.read().strip() or "another process"
            stream.close()
            raise HicoError(f"{self.path.parent}: another trainer ({owner}) is writing this run; wait for it, "
                            "or choose another --output-dir") from None
        stream.seek(0)
        stream.truncate()
        stream.write(f"pid {os.getpid()}")
        stream.flush()
        self._stream = stream

    def release(self) -> None:
        if self._stream is not None:
            fcntl.flock(self._stream.fileno(), fcntl.LOCK_UN)
            self._stream.close()
            self._stream = None


def trim_metrics(path: Path, step: int) -> int:
    """Drop the records of ``path`` (metrics.jsonl) logged at or after ``step`` (0-based index of the
    first step a resumed run will redo), so a resume logs no step twice. Returns how many went."""
    if not path.is_file():
        return 0
    kept, dropped = [], 0
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            record_step = json.loads(line).get("step", -1)
        except (ValueError, AttributeError):
            dropped += 1  # a half-written last line of a killed run
            continue
        if isinstance(record_step, int) and record_step >= step:
            dropped += 1
        else:
            kept.append(line)
    if dropped:
        write_text_atomic(path, "".join(f"{line}\n" for line in kept))
    return dropped
