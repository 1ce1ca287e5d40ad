"""Image-formation effects the model simulates, chosen from the data (``--model.effects``).

Each effect is one registered component (``EFFECTS``) tied to one finding of
``hico_plugin.analysis.effects``: ``sky`` (model/sky.py), ``exposure`` (model/appearance.py) and
``lod`` (model/lod.py). ``auto`` turns on exactly the effects the analysis found; ``NAME=on|off``
forces one::

    --model.effects auto                   # the default
    --model.effects auto,sky=off           # detect, but never learn a sky
    --model.effects sky=on,exposure=on,lod=on   # no analysis for forced effects
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hico_plugin.errors import HicoError
from hico_plugin.registry import Registry

EFFECTS: Registry[type] = Registry("effect")


@dataclass
class EffectChoice:
    """Whether one effect is simulated, and why (forced, or what the analysis measured)."""

    name: str
    on: bool
    reason: str

    def line(self) -> str:
        return f"{self.name}: {'on' if self.on else 'off'} — {self.reason}"


def parse_effects(spec: str) -> dict[str, str]:
    """``"auto,sky=off"`` -> {effect: "auto" | "on" | "off"} for every registered effect."""
    choices = {name: "auto" for name in EFFECTS.names()}
    for token in (t.strip() for t in spec.split(",")):
        if token in ("", "auto"):
            continue
        name, sep, value = token.partition("=")
        if not sep or value not in ("on", "off", "auto"):
            raise HicoError(f"--model.effects: expected 'auto' or NAME=on|off|auto items, got {token!r}")
        if name not in EFFECTS:
            raise HicoError(f"--model.effects: unknown effect {name!r}; registered: {', '.join(EFFECTS.names())}")
        choices[name] = value
    return choices


def choose_effects(spec: str, dataset: Any) -> tuple[dict[str, EffectChoice], Any]:
    """Resolve ``spec`` against ``dataset``: (choice per effect, the analysis report or None when
    every effect was forced)."""
    choices = parse_effects(spec)
    report = None
    if any(value == "auto" for value in choices.values()):
        from hico_plugin.analysis.effects import analyze_effects

        report = analyze_effects(dataset)
    out = {}
    for name, value in choices.items():
        finding = EFFECTS.get(name).finding
        if value == "auto":
            found = report.effects[finding]
            out[name] = EffectChoice(name, found.present, found.reason)
        else:
            out[name] = EffectChoice(name, value == "on", "forced by --model.effects")
    return out, report
