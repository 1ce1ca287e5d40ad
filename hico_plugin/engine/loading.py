"""Loading a trained run -- the one loader every command uses (hico-eval / -render / -export /
-view / -analyze, mesh export): config.yml through the safe config loader, the newest readable
checkpoint (or the one asked for) through ``weights_only`` loading, the model restored in eval mode.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torch import nn

from hico_plugin.engine.checkpoints import (
    check_frame, load_checkpoint, newest_readable_checkpoint, restore_model, seed_everything)
from hico_plugin.engine.config_io import load_config
from hico_plugin.engine.distributed import resolve_device
from hico_plugin.engine.trainer import TrainerConfig
from hico_plugin.errors import HicoError


@dataclass
class LoadedRun:
    """A trained run: config, model (eval mode, checkpoint loaded), dataset, the checkpoint file and
    the run directory (the folder holding config.yml)."""

    config: TrainerConfig
    model: Any
    dataset: Any
    checkpoint: Path
    run_dir: Path


def _newest(config_path: Path, output_dir: Path) -> tuple[Path, dict[str, Any]]:
    """The newest readable checkpoint: in the config's ``output_dir``, else next to config.yml (a run
    folder that was moved or is read from another working directory)."""
    folders = list(dict.fromkeys([Path(output_dir) / "checkpoints", config_path.parent / "checkpoints"]))
    for folder in folders:
        found = newest_readable_checkpoint(folder)
        if found is not None:
            return found
    raise HicoError(f"{config_path}: no checkpoint found (looked in {', '.join(str(f) for f in folders)}); "
                    "train the run first or pass --checkpoint")


def load_run(config_path: str | Path, checkpoint: str | Path | None = None, device: str | None = None) -> LoadedRun:
    """The run of ``config_path`` (RUN/config.yml) with ``checkpoint`` or its newest readable one."""
    config_path = Path(config_path)
    if not config_path.is_file():
        raise HicoError(f"--load-config: {config_path} is not a file (expected RUN/config.yml written by hico-train)")
    config = load_config(config_path)
    if not isinstance(config, TrainerConfig):
        raise HicoError(f"{config_path}: expected a training run's config.yml, got {type(config).__name__}")
    if checkpoint is not None:
        path = Path(checkpoint)
        payload = load_checkpoint(path)
    else:
        path, payload = _newest(config_path, config.output_dir)
    seed_everything(config.seed)
    # Cameras and points only, so a checkpoint of another frame is refused before the data analyses
    # and the model's setup, and before anything else is printed.
    dataset = config.build_dataset(announce=False, frame=payload.get("frame"))
    check_frame(payload, dataset, path)
    for note in getattr(dataset, "notes", ()):
        print(note, file=sys.stderr)
    model = config.build_model(dataset, resolve_device(device or config.device))
    restore_model(model, payload, path)
    if isinstance(model, nn.Module):
        model.eval()
    return LoadedRun(config, model, dataset, path, config_path.parent)
