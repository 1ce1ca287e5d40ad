"""Checkpoints ``RUN/checkpoints/step-XXXXXXXXX.ckpt``: written atomically, the last few kept."""

from __future__ import annotations

import os
import random
import re
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hico_plugin.errors import HicoError

_CHECKPOINT_NAME = re.compile(r"^step-(\d{9})\.ckpt$")


def checkpoint_path(checkpoint_dir: Path, step: int) -> Path:
    return checkpoint_dir / f"step-{step:09d}.ckpt"


def list_checkpoints(checkpoint_dir: Path) -> list[Path]:
    """The checkpoints in ``checkpoint_dir``, oldest step first."""
    if not checkpoint_dir.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in checkpoint_dir.iterdir() if (m := _CHECKPOINT_NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def latest_checkpoint(checkpoint_dir: Path) -> Path | None:
    checkpoints = list_checkpoints(checkpoint_dir)
    return checkpoints[-1] if checkpoints else None


def save_checkpoint(checkpoint_dir: Path, step: int, payload: dict[str, Any], keep_last: int) -> Path:
    """Write ``payload`` as the checkpoint of ``step`` (temp file + ``os.replace``, so a crash never
    leaves a torn file under the final name), then delete all but the newest ``keep_last``."""
    checkpoint_dir.mkdir(parents=True, exist_ok=True)
    path = checkpoint_path(checkpoint_dir, step)
    fd, tmp = tempfile.mkstemp(dir=checkpoint_dir, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as stream:
            torch.save(payload, stream)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if keep_last > 0:
        for old in list_checkpoints(checkpoint_dir)[:-keep_last]:
            old.unlink(missing_ok=True)
    return path


def load_checkpoint(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise HicoError(f"{path}: checkpoint not found")
    try:
        # weights_only=False: the payload holds numpy / python RNG states, and checkpoints are our own.
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # a truncated or foreign file
        raise HicoError(f"{path}: not a readable checkpoint ({type(err).__name__}: {err})") from None
    if not isinstance(payload, dict) or "step" not in payload or "model" not in payload:
        raise HicoError(f"{path}: not a hico checkpoint (expected keys 'step' and 'model')")
    return payload


def rng_state() -> dict[str, Any]:
    """The RNG states of python, numpy and torch (CPU and, when present, CUDA)."""
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
