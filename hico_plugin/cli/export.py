"""``hico-export --load-config RUN/config.yml EXPORTER [...]``: exports of a trained run.

    hico-export --load-config outputs/city-block/hico-gs-lite/config.yml gaussians --camera-index 3
    hico-export --load-config outputs/city-block/hico-gs-lite/config.yml mesh --depth-filter

Every registered exporter (``hico_plugin.export.exporters.EXPORTERS``, plug-ins' included) is a subcommand by its
name; run options may stand before or after it. Built-in outputs are PLY files in COLMAP's frame.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, Sequence, TypeVar

import tyro

import hico_plugin.presets  # noqa: F401  (loads the config classes a config.yml may name)
from hico_plugin.cli import run_cli
from hico_plugin.engine import load_run
from hico_plugin.export.exporters import EXPORTERS

TargetT = TypeVar("TargetT")


@dataclass
class ExportArgs(Generic[TargetT]):
    """Export a trained HiCo-GS run (PLY files in the original COLMAP frame, or what an installed
    plug-in's exporter writes)."""

    target: TargetT
    load_config: Path
    """The run's config.yml (written by hico-train next to its checkpoints)."""
    checkpoint: Path | None = None
    """Checkpoint to export instead of the run's newest."""
    device: str | None = None
    """Device to decode on (default: the run's)."""


def parse(args: Sequence[str]) -> ExportArgs[Any]:
    targets = EXPORTERS.subcommands()
    # Cascade: run options may follow the exporter name; no "target:" prefix on the exporter names.
    return tyro.cli(ExportArgs[targets], args=list(args), prog="hico-export",
                    config=(tyro.conf.CascadeSubcommandArgs, tyro.conf.OmitSubcommandPrefixes))


def main(args: ExportArgs[Any]) -> Path:
    run = load_run(args.load_config, args.checkpoint, args.device)
    return args.target.run(run)


def entrypoint(argv: Sequence[str] | None = None) -> None:
    run_cli(lambda: main(parse(sys.argv[1:] if argv is None else argv)))
