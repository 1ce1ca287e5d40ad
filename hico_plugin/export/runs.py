"""Loading a trained run for hico-eval / hico-render / hico-export."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hico_plugin.engine import load_config, load_run
from hico_plugin.engine.checkpoints import latest_checkpoint
from hico_plugin.errors import HicoError


@dataclass
class LoadedRun:
    """A run as the CLIs use it: config, model (eval mode, checkpoint loaded), dataset, the
    checkpoint file and the run directory (the folder holding config.yml)."""

    config: Any
    model: Any
    dataset: Any
    checkpoint: Path
    run_dir: Path


def find_checkpoint(config_path: Path, output_dir: Path | None) -> Path:
    """The newest checkpoint of the run: in the config's ``output_dir``, else next to config.yml (a
    run folder that was moved or is read from another working directory)."""
    folders = [Path(output_dir) / "checkpoints"] if output_dir is not None else []
    folders.append(config_path.parent / "checkpoints")
    for folder in folders:
        found = latest_checkpoint(folder)
        if found is not None:
            return found
    raise HicoError(f"{config_path}: no checkpoint found (looked in {', '.join(str(f) for f in folders)}); "
                    "train the run first or pass --checkpoint")


def load_trained_run(config_path: Path, checkpoint: Path | None = None, device: str | None = None) -> LoadedRun:
    """Load the run ``config_path`` (RUN/config.yml) with ``checkpoint`` or its newest one.
    HicoError for a missing file, a config that is not a HiCo-GS run, or no checkpoint."""
    from hico_plugin.model.hico import HiCoModel

    config_path = Path(config_path)
    if not config_path.is_file():
        raise HicoError(f"--load-config: {config_path} is not a file (expected RUN/config.yml written by hico-train)")
    config = load_config(config_path)
    if not hasattr(config, "output_dir") or not hasattr(config, "model"):
        raise HicoError(f"{config_path}: not a training run's config.yml (got {type(config).__name__})")
    if checkpoint is None:
        checkpoint = find_checkpoint(config_path, config.output_dir)
    config, model, dataset = load_run(config_path, checkpoint=checkpoint, device=device)
    if not isinstance(model, HiCoModel):
        raise HicoError(f"{config_path}: model {type(model).__name__} is not a HiCo-GS model")
    return LoadedRun(config, model, dataset, Path(checkpoint), config_path.parent)
