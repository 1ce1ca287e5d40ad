"""Whether the disk holding a run directory has room for what the run will write, checked before the
run starts: a run that fills the disk stops at its first checkpoint after the model was built and
trained for a while, where the check costs a ``statvfs``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from hico_plugin.errors import HicoError

OUTPUTS_BYTES = 64 * 2**20
"""What a run writes besides checkpoints: config.yml, effects.json, eval.json and metrics.jsonl (one
~300-byte line every log_every steps: 30,000 steps at log_every 10 are ~1 MB) and tensorboard's
event files, with room to spare."""


def free_bytes(folder: Path) -> int:
    """Free bytes for an unprivileged writer on the file system of ``folder`` (or of its nearest
    existing parent: the run directory may not exist yet)."""
    folder = Path(folder).absolute()
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return shutil.disk_usage(folder).free


def run_bytes_needed(checkpoint_bytes: int, keep_checkpoints: int, max_steps: int, save_every: int) -> int:
    """Bytes a run writes at most at one time: its checkpoints plus ``OUTPUTS_BYTES``.

    A run keeps the newest ``keep_checkpoints`` (0: every one it writes, one per ``save_every`` steps
    and the final one), and a new checkpoint is written in full to a temporary file before the oldest
    is deleted, so one more than the kept number exists at once."""
    written = (max_steps // save_every if save_every else 0) + 1
    kept = min(keep_checkpoints, written) if keep_checkpoints else written
    return (kept + 1) * checkpoint_bytes + OUTPUTS_BYTES


def check_free_space(run_dir: Path, needed: int, reclaimable: int = 0) -> None:
    """Refuse, naming the folder, what is free and what is needed, when the disk of ``run_dir`` has less
    than ``needed`` bytes free; ``reclaimable`` bytes (the run's own earlier checkpoints, which a resumed
    run rotates out and an overwrite deletes) count as free."""
    free = free_bytes(run_dir)
    if free + reclaimable < needed:
        have = f"{_size(free)} free" + (f" (+{_size(reclaimable)} of its old checkpoints)" if reclaimable else "")
        raise HicoError(f"{run_dir}: not enough disk space for the run: {have}, about {_size(needed)} needed "
                        "(its checkpoints and logs); free some space or choose another --output-dir")


def _size(count: int) -> str:
    for unit, scale in (("GB", 2**30), ("MB", 2**20), ("kB", 2**10)):
        if count >= scale:
            return f"{count / scale:.1f} {unit}"
    return f"{count} B"
