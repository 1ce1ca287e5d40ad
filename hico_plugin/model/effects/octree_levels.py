"""The LOD effect: how many octree levels the anchors get, from the spread of camera distances."""

from __future__ import annotations

import dataclasses
from typing import Any

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding
from hico_plugin.analysis.view_distances import lod_finding
from hico_plugin.model.effects.base import EFFECTS, Effect


@EFFECTS.register("lod")
class LevelOfDetailEffect(Effect):
    """On: the octree's level count from the camera-to-point distance spread (Octree-GS's
    round(log2(d_max / d_min)) + 1); off: one level, a flat anchor grid (Scaffold-GS)."""

    finding = "lod"

    def detect(self, evidence: DatasetEvidence) -> EffectFinding:
        return lod_finding(evidence)

    def configure_field(self, field_config: Any, on: bool) -> Any:
        octree = field_config.octree
        if on or octree.num_levels > 0:  # an explicit --model.field.octree.num_levels wins
            return field_config
        octree = dataclasses.replace(octree, num_levels=1, init_level=0)
        return dataclasses.replace(field_config, octree=octree)
