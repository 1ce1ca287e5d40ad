"""The run directory: where a run lives, its lock, how it starts (fresh / resumed / overwritten), its files.

Without ``--output-dir`` a run gets ``outputs/<experiment>/<method>/<timestamp>/`` (as in nerfstudio);
``--resume`` continues the newest there. A writing trainer holds an exclusive ``flock`` on ``RUN/.lock`` (the
kernel drops it however the process dies); a second one refuses. Files: ``config.yml``, ``metrics.jsonl`` (a JSON
object per logged step / eval, trimmed on resume), ``checkpoints/step-XXXXXXXXX.ckpt`` (by completed steps, the
last few kept), ``eval.json`` (ns-eval layout), ``run_documents`` (``effects.json``, ...).
"""

from __future__ import annotations

import dataclasses
import fcntl
import json
import os
import shutil
import time
from pathlib import Path
from typing import IO, Any

from hico_plugin.engine import distributed as dist_utils
from hico_plugin.engine.checkpoints import latest_checkpoint, newest_readable_checkpoint
from hico_plugin.engine.config_io import save_config
from hico_plugin.errors import HicoError
from hico_plugin.storage import write_text_atomic

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
        self._created_dir = False

    def acquire(self) -> None:
        try:
            self._created_dir = not self.path.parent.exists()
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

    def abandon(self) -> None:
        """Release a lock whose run was refused before it started, and remove the run directory when
        ``acquire`` created it and it holds nothing else: a refused command leaves no empty run behind."""
        held = self._stream is not None
        self.release()
        if held and self._created_dir:
            self.path.unlink(missing_ok=True)
            try:
                self.path.parent.rmdir()
            except OSError:  # something else was written into it: keep it
                pass


def start_checkpoint(run_dir: Path, resume: bool, overwrite: bool,
                     is_main: bool) -> tuple[Path | None, dict[str, Any] | None]:
    """The checkpoint a run starts from (the same on every rank) and, on rank 0, its payload as read
    here (other ranks read it themselves); (None, None) for a fresh run.

    Resuming takes the newest readable checkpoint; a fresh run into a folder that holds checkpoints
    needs ``overwrite`` (which deletes them). A fresh run deletes the logs of an earlier attempt."""
    checkpoint_dir = run_dir / "checkpoints"
    newest, payload = None, None
    if is_main:
        # Fresh runs only ask whether checkpoints exist; resumes skip unreadable newer ones.
        if resume:
            newest, payload = newest_readable_checkpoint(checkpoint_dir) or (None, None)
        else:
            newest = latest_checkpoint(checkpoint_dir)
    latest = dist_utils.broadcast_object(newest)
    if latest is not None and not resume:
        if not overwrite:
            raise HicoError(
                f"{checkpoint_dir}: already holds checkpoints; pass --resume to continue that "
                "run, --overwrite to start afresh, or choose another --output-dir"
            )
        if is_main:
            shutil.rmtree(checkpoint_dir)
        latest = None
    if latest is None and is_main:
        for name in ("metrics.jsonl", "eval.json"):
            (run_dir / name).unlink(missing_ok=True)
    dist_utils.barrier()
    return latest, payload


def write_run_files(run_dir: Path, config: Any, model: Any) -> None:
    """config.yml (paths absolute, without the one-off --resume / --overwrite) and the documents the
    model derived from the data (e.g. effects.json), beside it."""
    try:
        save_config(dataclasses.replace(config, resume=False, overwrite=False), run_dir / "config.yml",
                    absolute_paths=True)
        for name, document in getattr(model, "run_documents", dict)().items():
            write_text_atomic(run_dir / name, json.dumps(document, indent=2) + "\n")
    except OSError as err:
        raise HicoError(f"{run_dir}: cannot write the run's config ({err.strerror or err})") from None


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
