"""Exporters of a trained run (``hico-export NAME``): decoded Gaussians and anchors as PLY, a TSDF mesh,
and those installed plug-ins register in ``EXPORTERS`` (see ``base``)."""

from __future__ import annotations

import importlib
import pkgutil

from hico_plugin.export.exporters.base import EXPORTERS, Exporter, output_path

# Every module of this package registers its exporter on import, so a new exporter is one file here.
for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")

__all__ = ["EXPORTERS", "Exporter", "output_path"]
