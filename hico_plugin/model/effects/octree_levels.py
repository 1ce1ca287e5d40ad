"""The LOD effect: how many octree levels the anchors get, from the spread of camera distances."""

from __future__ import annotations

import dataclasses
from typing import Any

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding
from hico_plugin.analysis.view_distances import lod_finding
from hico_plugin.model.effects.base import EFFECTS, Effect, EffectChoice


@EFFECTS.register("lod")
class LevelOfDetailEffect(Effect):
    """On: the octree's level count from the camera-to-point distance spread (Octree-GS's
    round(log2(d_max / d_min)) + 1); off: one level, a flat anchor grid (Scaffold-GS)."""

    finding = "lod"

    def detect(self, evidence: DatasetEvidence) -> EffectFinding:
        return lod_finding(evidence)

    def auto_choice(self, name: str, finding: EffectFinding, total_steps: int | None, model_config: Any) -> EffectChoice:
        # Each level's anchors see only the views at its distance, so levels split the run's steps
        # between them; a run shorter than lod_min_steps trains one flat level better.
        minimum = getattr(model_config, "lod_min_steps", 0)
        if finding.present and total_steps is not None and total_steps < minimum:
            return EffectChoice(name, False, f"{finding.reason}, but a run of {total_steps} steps is too short to "
                                             f"train them (levels from {minimum} steps: --model.lod-min-steps)")
        return EffectChoice(name, finding.present, finding.reason)

    def configure_field(self, field_config: Any, on: bool) -> Any:
        octree = field_config.octree
        if on or octree.num_levels > 0:  # an explicit --model.field.octree.num_levels wins
            return field_config
        octree = dataclasses.replace(octree, num_levels=1, init_level=0)
        return dataclasses.replace(field_config, octree=octree)
