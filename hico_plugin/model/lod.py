"""The LOD effect: how many octree levels the anchors get, from the spread of camera distances."""

from __future__ import annotations

import dataclasses

from hico_plugin.model.effects import EFFECTS


@EFFECTS.register("lod")
class LevelOfDetail:
    """On: the octree's level count from the camera-to-point distance spread (Octree-GS's
    round(log2(d_max / d_min)) + 1); off: one level, a flat anchor grid (Scaffold-GS)."""

    finding = "lod"

    @staticmethod
    def field_config(field_config, on: bool):
        octree = field_config.octree
        if on or octree.num_levels > 0:  # an explicit --model.field.octree.num_levels wins
            return field_config
        octree = dataclasses.replace(octree, num_levels=1, init_level=0)
        return dataclasses.replace(field_config, octree=octree)
