"""The LOD effect: how many octree levels the anchors get, from the spread of camera distances."""

from __future__ import annotations

import dataclasses
from typing import Any

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding
from hico_plugin.analysis.view_distances import lod_finding
from hico_plugin.model.effects.base import EFFECTS, Effect, EffectChoice


# The measured rule (--model.lod-rule measured): each level's anchors train on the views at its distance
# only, so levels split a run's steps between them and pay only on views at several distances and runs
# this long (the comparison: benchmarks/RESULTS.md, "Figures behind the defaults").
LOD_MIN_STEPS = 1_000


@EFFECTS.register("lod")
class LevelOfDetailEffect(Effect):
    """On: the octree's level count from the camera-to-point distance spread (Octree-GS's
    round(log2(d_max / d_min)) + 1); off: one level, a flat anchor grid (Scaffold-GS)."""

    finding = "lod"

    def detect(self, evidence: DatasetEvidence) -> EffectFinding:
        return lod_finding(evidence)

    def auto_choice(self, name: str, finding: EffectFinding, total_steps: int | None, model_config: Any) -> EffectChoice:
        if finding.present and getattr(model_config, "lod_rule", "octree") == "measured":
            if not finding.figures.get("views_multi_distance"):
                return EffectChoice(name, False, f"{finding.reason}: the views stand at about one distance, one level")
            if total_steps is not None and total_steps < LOD_MIN_STEPS:
                return EffectChoice(name, False, f"{finding.reason}: a run of {total_steps} steps is too short to "
                                                 f"train levels (from {LOD_MIN_STEPS} steps)")
        return EffectChoice(name, finding.present, finding.reason)

    def configure_field(self, field_config: Any, on: bool) -> Any:
        octree = field_config.octree
        if on or octree.num_levels > 0:  # an explicit --model.field.octree.num_levels wins
            return field_config
        octree = dataclasses.replace(octree, num_levels=1, init_level=0)
        return dataclasses.replace(field_config, octree=octree)
