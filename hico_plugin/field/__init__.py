"""The anchor octree field: LOD selection, cross-level context aggregation (CLCA), Gaussian decoding.

    field = FieldConfig().setup(points=points, train_cameras=cameras, schedule_scale=1.0)
    visible_ids = field.select(camera, step)
    gaussians = field.decode(camera, visible_ids)      # NeuralGaussians

See field.py for the training-side API (param_groups, after_update, resize); densification is a strategy
beside the field (``hico_plugin.strategy``).
"""

from hico_plugin.field.context import (
    CONTEXT_AGGREGATORS, ContextAggregator, ContextConfig, ContextLookup, context_lookup, context_triplet)
from hico_plugin.field.context_graph import ContextGraph, ContextIndex, context_graph, dense_cell_ids, parent_edges
from hico_plugin.field.decoder import DecoderConfig, GaussianDecoder, NeuralGaussians
from hico_plugin.field.field import ANCHOR_GROUPS, AnchorField, FieldConfig
from hico_plugin.field.octree import OctreeBuildConfig, OctreeGrid, build_octree

__all__ = [
    "ANCHOR_GROUPS", "AnchorField", "CONTEXT_AGGREGATORS", "ContextAggregator", "ContextConfig",
    "ContextGraph", "ContextIndex", "ContextLookup", "context_graph", "context_lookup", "parent_edges",
    "DecoderConfig", "FieldConfig", "GaussianDecoder", "NeuralGaussians",
    "OctreeBuildConfig", "OctreeGrid", "build_octree", "context_triplet", "dense_cell_ids",
]
