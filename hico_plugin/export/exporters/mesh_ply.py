"""``hico-export mesh``: a TSDF mesh of the rendered depth (hico_plugin.mesh), as a PLY."""

from __future__ import annotations

from hico_plugin.export.exporters.base import EXPORTERS
from hico_plugin.mesh import MeshExportConfig

# The mesh package keeps the config (extract_mesh reads its options); it already has run(run).
EXPORTERS.register("mesh")(MeshExportConfig)
