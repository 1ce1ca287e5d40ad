"""Checkpoints ``RUN/checkpoints/step-XXXXXXXXX.ckpt``: written atomically, the last few kept.

A checkpoint holds only tensors, numbers, strings and containers, so it is read with
``torch.load(weights_only=True)``: a crafted file cannot run code (the config lives in config.yml).
What it holds of a training run (``training_payload``): the step, model, optimizers, their schedules,
every rank's RNG states, the training wall time, the number of workers and the dataset's frame (the
scene normalisation the model lives in, ``check_frame``).
"""

from __future__ import annotations

import dataclasses
import os
import random
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hico_plugin.engine.optimizers import Optimizers
from hico_plugin.errors import HicoError
from hico_plugin.storage import atomic_path

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


def checkpoint_due(completed_steps: int, save_every: int) -> bool:
    """Whether a run writes a checkpoint after ``completed_steps`` besides the asked-for and final ones:
    every ``save_every`` steps (0: never)."""
    return bool(save_every) and completed_steps % save_every == 0


def save_checkpoint(checkpoint_dir: Path, step: int, payload: dict[str, Any], keep_last: int) -> Path:
    """Write ``payload`` as the checkpoint of ``step`` (``storage.atomic_path``, synced to disk, so a crash
    never leaves a torn file under the final name), then delete all but the newest ``keep_last``.

    An OSError (disk full, read-only, permission) is a HicoError naming the path; the earlier
    checkpoints are left as they were."""
    path = checkpoint_path(checkpoint_dir, step)
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as stream:
            torch.save(payload, stream)
            stream.flush()
            os.fsync(stream.fileno())
    except BaseException as err:
        cause = _os_error(err)  # torch.save turns the stream's OSError into a RuntimeError
        if cause is not None:
            raise HicoError(f"{path}: cannot write the checkpoint ({cause.strerror or cause}); "
                            "earlier checkpoints are kept") from None
        if isinstance(err, RuntimeError) and "write" in str(err).lower():
            raise HicoError(f"{path}: cannot write the checkpoint ({str(err).splitlines()[0]}); "
                            "earlier checkpoints are kept") from None
        raise
    if keep_last > 0:
        for old in list_checkpoints(checkpoint_dir)[:-keep_last]:
            old.unlink(missing_ok=True)
    return path


def _os_error(err: BaseException) -> OSError | None:
    """``err`` or the OSError it was raised while handling (torch.save's writer reports a failed
    write as "unexpected pos" with the disk's ENOSPC as its context)."""
    seen = 0
    while err is not None and seen < 8:
        if isinstance(err, OSError):
            return err
        err, seen = err.__cause__ or err.__context__, seen + 1
    return None


def load_checkpoint(path: Path, mmap: bool = False) -> dict[str, Any]:
    """The payload of ``path``; HicoError for a missing, truncated, foreign or code-carrying file."""
    if not path.is_file():
        raise HicoError(f"{path}: checkpoint not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except Exception as err:  # noqa: BLE001 - truncated, random bytes, or a pickle naming code
        first = (str(err).strip().splitlines() or [type(err).__name__])[0][:160]
        if "Unsupported global" in str(err):  # a pickle naming code, not merely a broken file
            first = "it holds Python objects other than tensors and numbers; refused without running them"
        elif "Weights only load failed" in str(err) or "zip archive" in str(err):
            first = "truncated or corrupt, not a complete torch checkpoint file"
        raise HicoError(f"{path}: not a readable checkpoint ({first})") from None
    if not isinstance(payload, dict) or "step" not in payload or "model" not in payload:
        raise HicoError(f"{path}: not a hico checkpoint (expected keys 'step' and 'model')")
    return payload


def newest_readable_checkpoint(checkpoint_dir: Path) -> tuple[Path, dict[str, Any]] | None:
    """(path, payload) of the newest checkpoint that loads; each newer unreadable one is skipped with
    a warning naming it. None when the folder holds no checkpoint; HicoError when none is readable."""
    checkpoints = list_checkpoints(checkpoint_dir)
    errors = []
    for path in reversed(checkpoints):
        try:
            return path, load_checkpoint(path)
        except HicoError as err:
            errors.append(str(err))
            print(f"warning: skipping {err}", file=sys.stderr)
    if errors:
        raise HicoError(f"{checkpoint_dir}: none of the {len(errors)} checkpoints is readable ({errors[0]})")
    return None


def rng_state() -> dict[str, Any]:
    """The RNG states of python, numpy and torch (CPU and, when present, CUDA), as tensors, numbers
    and lists only (what ``weights_only`` loading accepts)."""
    version, internal, gauss = random.getstate()
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    state = {
        "python": [version, torch.tensor(internal, dtype=torch.int64), gauss],
        "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss), float(cached)],
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(int(v) for v in internal.tolist()), gauss))
    kind, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def dataset_frame(dataset: Any) -> dict[str, Any] | None:
    """What a model trained on ``dataset`` depends on besides its weights: the dataset's ``frame()``
    (e.g. the scene normalisation), None for a dataset without one."""
    frame = getattr(dataset, "frame", None)
    return frame() if callable(frame) else None


def check_frame(payload: dict[str, Any], dataset: Any, path: Path) -> None:
    """Refuse a checkpoint trained in another frame than the one ``dataset`` is loaded in today (say the
    cameras or the normalisation's rule changed since): its weights would render and resume silently
    wrong. The dataset judges which differences matter (its ``frame_differences(stored)``: the parts
    that differ); a dataset without frames is not checked."""
    stored = payload.get("frame")
    differences = getattr(dataset, "frame_differences", None)
    if stored is None or not callable(differences):  # checkpoints from before frames were recorded; frameless data
        return
    changed = differences(stored)
    if changed:
        raise HicoError(f"{path}: the model was trained in another scene frame than the dataset is loaded in "
                        f"now ({', '.join(changed)} differ); load it with the settings and version it was trained with")


def training_payload(step: int, model: Any, optimizers: Optimizers, rng_states: list[dict[str, Any]],
                     train_seconds: float, world_size: int, frame: dict[str, Any] | None = None) -> dict[str, Any]:
    """The checkpoint of a training run after ``step`` completed steps; ``rng_states`` per rank; ``frame``
    the dataset's (``dataset_frame``)."""
    return {
        "step": step,
        "model": model.state_dict(),
        "optimizers": optimizers.state_dict(),
        "schedules": {k: dataclasses.asdict(v) for k, v in optimizers.schedules.items()},
        "rng": rng_states,
        "train_seconds": train_seconds,
        "world_size": world_size,
        **({"frame": frame} if frame is not None else {}),
    }


def restore_model(model: Any, payload: dict[str, Any], path: Path) -> None:
    """Load the checkpoint ``payload`` (read from ``path``) into ``model``."""
    try:
        model.load_state_dict(payload["model"])
    except (RuntimeError, KeyError, TypeError, ValueError) as err:
        raise HicoError(f"{path}: checkpoint does not fit the configured model ({str(err).splitlines()[0]})") from None


def restore_rank_rng(payload: dict[str, Any], rank: int, world_size: int) -> None:
    """Set this rank's RNG states from ``payload``; resumed with another number of workers, rank 0's
    (the best that can be done)."""
    rng_states = payload.get("rng", [])
    if len(rng_states) == world_size:
        set_rng_state(rng_states[rank])
    elif rng_states:
        set_rng_state(rng_states[0])
