"""Image-formation effects the model simulates, chosen from the data (``--model.effects``): the
contract in ``base``, one file per built-in effect."""

from hico_plugin.model.effects.base import (
    EFFECTS, Effect, EffectChoice, EffectInputs, EffectsReport, analyze_effects, choose_effects, parse_effects,
)
# registers the built-ins; their order is that of the effects' optimizer groups in a config
from hico_plugin.model.effects import sky, exposure, octree_levels  # noqa: F401, E402, I001

__all__ = ["EFFECTS", "Effect", "EffectChoice", "EffectInputs", "EffectsReport", "analyze_effects",
           "choose_effects", "parse_effects"]
