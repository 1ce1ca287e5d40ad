"""``hico-train PRESET [--data DIR] [--output-dir DIR] [--max-steps N] [any config override]``.

Flags may stand before or after the preset name (unlike ns-train): the preset is moved to the front
before tyro parses. Under ``torchrun --nproc_per_node=P hico-train ...`` every worker trains its share
of the batch; only rank 0 writes files and serves the viewer.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

import tyro

from hico_plugin.cli import run_cli
from hico_plugin.engine import distributed as dist_utils
from hico_plugin.engine.run_dir import run_directory
from hico_plugin.engine.stopping import EXIT_INTERRUPTED
from hico_plugin.presets import HiCoTrainerConfig, all_presets

# Options whose value may coincide with a preset name; such a value is not the preset.
_VALUE_OPTIONS = ("--method-name", "--experiment-name", "--method_name", "--experiment_name")


def preset_first(args: Sequence[str]) -> list[str]:
    """``args`` with the first preset name moved to the front, so flag order does not matter."""
    args, presets = list(args), all_presets()
    for i, arg in enumerate(args):
        if arg in presets and (i == 0 or args[i - 1] not in _VALUE_OPTIONS):
            return [arg] + args[:i] + args[i + 1:]
    return args


def parse(args: Sequence[str]) -> HiCoTrainerConfig:
    """The training config that ``hico-train args`` describes (defaults for naming filled in)."""
    # tyro.extras.overridable_config_cli without its AvoidSubcommands: the dataset format is a subcommand
    # (``hico-train hico-gs-lite --data DIR transforms``).
    presets = all_presets()
    config = tyro.cli(
        tyro.extras.subcommand_type_from_defaults(
            defaults={name: preset for name, (_, preset) in presets.items()},
            descriptions={name: description for name, (description, _) in presets.items()}),
        args=preset_first(args), prog="hico-train", config=(tyro.conf.CascadeSubcommandArgs,),
        description="Train HiCo-GS (or one of its ablations) on a dataset (COLMAP, transforms.json, "
                    "hico-process output, ...) or a built-in scene.")
    if config.experiment_name == "unnamed":
        config.experiment_name = config.data.data.name if config.data.data is not None else config.data.scene
    if config.output_dir == Path("outputs/unnamed"):  # nerfstudio's layout: one folder per run
        base = Path("outputs") / config.experiment_name / config.method_name
        config.output_dir = run_directory(base, config.timestamp, config.resume)
    return config


def train(config: HiCoTrainerConfig) -> None:
    finished = False
    try:
        trainer = config.setup()
        viewer = None
        if trainer.is_main and config.wants_viewer():
            from hico_plugin.viewer.viewer import attach_viewer

            viewer = attach_viewer(trainer, config.viewer)
        try:
            result = trainer.train()
        finally:
            if viewer is not None:
                viewer.stop()
        finished = True
    finally:
        dist_utils.shutdown(wait_for_peers=finished)  # under torchrun; nothing on one process
    if trainer.is_main and result.eval_results is not None:
        summary = ", ".join(f"{k} {v:.4g}" for k, v in result.eval_results.items() if isinstance(v, float))
        print(f"eval: {summary}")
        print(f"run: {config.output_dir}")
    if result.interrupted:
        if trainer.is_main:
            print(f"stopped at step {result.step}, saved {result.checkpoint}; continue with: hico-train "
                  f"{config.method_name} --resume --output-dir {config.output_dir} (exit {EXIT_INTERRUPTED})",
                  file=sys.stderr)
        raise SystemExit(EXIT_INTERRUPTED)


def entrypoint(argv: Sequence[str] | None = None) -> None:
    run_cli(lambda: train(parse(sys.argv[1:] if argv is None else argv)))
