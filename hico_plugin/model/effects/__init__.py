"""Image-formation effects the model simulates, chosen from the data (``--model.effects``): the
contract in ``base``, one file per built-in effect, each imported here so that it registers itself
(a new effect is a new file in this folder; a plug-in's is a module named by an entry point)."""

import importlib
import pkgutil

from hico_plugin.model.effects.base import (
    EFFECTS, RENAMED_EFFECTS, Effect, EffectChoice, EffectInputs, EffectsReport, analyze_effects, choose_effects,
    data_background, parse_effects,
)

for _module in sorted(info.name for info in pkgutil.iter_modules(__path__) if info.name != "base"):
    importlib.import_module(f"{__name__}.{_module}")

__all__ = ["EFFECTS", "RENAMED_EFFECTS", "Effect", "EffectChoice", "EffectInputs", "EffectsReport", "analyze_effects",
           "choose_effects", "data_background", "parse_effects"]
