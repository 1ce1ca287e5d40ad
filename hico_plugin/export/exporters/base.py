"""The exporter contract and its registry.

An exporter is one file that registers a dataclass in ``EXPORTERS``: its fields are its options (each
with a default; field docstrings become ``hico-export NAME --help``), and ``run(run)`` writes what it
exports of a trained run (a ``LoadedRun``: config, model, dataset, checkpoint, run_dir) and returns
the path. ``hico-export`` offers every registered exporter, an installed plug-in's too, as a
subcommand by its name.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from hico_plugin.config import InstantiateConfig
from hico_plugin.engine.loading import LoadedRun
from hico_plugin.registry import Registry


@dataclass
class Exporter(InstantiateConfig):
    """Base of a registered exporter."""

    def run(self, run: LoadedRun) -> Path:
        """Write the export of ``run``; returns the path written."""
        raise NotImplementedError


EXPORTERS: Registry[type] = Registry("exporter")
"""Exporters by name ("gaussians", "anchors", "mesh"); ``EXPORTERS.get(name)().run(run)`` exports."""


def output_path(output: Path | None, run: LoadedRun, default_name: str) -> Path:
    """``output`` when given, else RUN/exports/``default_name``."""
    return output or run.run_dir / "exports" / default_name
