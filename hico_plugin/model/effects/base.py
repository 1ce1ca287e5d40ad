"""The effect contract: an image-formation effect the model simulates when the capture calls for it.

An effect is one registered class (``EFFECTS``; a ``hico_plugin.components`` entry point from outside): the
finding it answers and how it detects it, its changes to the field config, its module, parameter groups and
default learning rates, where it acts on the image and its cost; ``HiCoModel`` names none. ``--model.effects
auto`` (the default) learns exactly what the analysis finds; ``auto,environment=off`` detects but never learns a
directional background; ``environment=on,exposure=on,lod=on`` forces all (no full analysis).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

from torch import Tensor, nn

from hico_plugin.analysis.evidence import DatasetEvidence, EffectFinding
from hico_plugin.engine.config_io import RENAMED_EFFECTS
from hico_plugin.errors import HicoError
from hico_plugin.registry import Registry

if TYPE_CHECKING:
    from hico_plugin.cameras import Camera
    from hico_plugin.engine.optimizers import ParamGroupOptimizerConfig
    from hico_plugin.rasterizer import RenderOutputs


@dataclass
class EffectInputs:
    """What an effect's module is built from."""

    dataset: Any  # hico_plugin.data.Dataset
    train_ids: Tensor  # [C] int64 dataset indices of the training views, in training-slot order
    report: "EffectsReport | None"  # the analysis (None when every effect was forced)
    model_config: Any  # the HiCoModelConfig (an effect's own options live there)
    evidence: DatasetEvidence  # the dataset's measurements, shared with the analysis and computed on first use


class Effect:
    """Base of a registered effect. Subclasses set ``finding`` (and ``stage`` when they act on the
    image) and override what they need; the defaults change nothing."""

    finding: str = ""
    """The analysis finding that decides ``auto``; an effect may answer a finding of its own by
    overriding ``detect``."""
    stage: int = 0
    """Order of ``apply`` in image formation, lower first: what lies behind the Gaussians (environment) comes
    before the camera's response to the whole image (exposure)."""
    replaces_background: bool = False
    """True when ``apply`` composites what lies behind the Gaussians (the rasterizer then renders
    without its constant background and the step renders alpha)."""

    def detect(self, evidence: DatasetEvidence) -> EffectFinding:
        """Whether the dataset shows this effect. The built-in findings are measured in
        ``hico_plugin.analysis``; an effect without one of them must override this."""
        raise HicoError(f"effect answering '{self.finding or type(self).__name__}': no measurement of it; "
                        f"the effect must define detect()")

    def auto_choice(self, name: str, finding: EffectFinding, total_steps: int | None, model_config: Any) -> "EffectChoice":
        """What ``auto`` decides from the finding for a run of ``total_steps`` (None: unknown); the
        default follows the finding alone."""
        return EffectChoice(name, finding.present, finding.reason)

    def background_when_off(self, finding: EffectFinding) -> tuple[float, float, float] | None:
        """Off, the colour the learned constant behind the Gaussians starts at, from this effect's
        finding (None: no opinion; an effect with ``replaces_background`` may have one)."""
        return None

    def configure_field(self, field_config: Any, on: bool) -> Any:
        """The anchor field's config with this effect on or off (called for every registered effect)."""
        return field_config

    def build(self, inputs: EffectInputs) -> nn.Module | None:
        """The module that simulates the effect (None: it only configures the field)."""
        return None

    def default_lrs(self) -> dict[str, "ParamGroupOptimizerConfig"]:
        """Learning-rate schedule of each parameter group the module trains, by group name."""
        return {}

    def param_groups(self, module: nn.Module) -> dict[str, list[nn.Parameter]]:
        """The module's parameters by group name (one group per entry of ``default_lrs``)."""
        names = list(self.default_lrs())
        return {names[0]: list(module.parameters())} if len(names) == 1 else {}

    def apply(self, module: nn.Module, out: "RenderOutputs", camera: "Camera") -> Tensor:
        """The rendered image [H, W, 3] with the effect applied (``out.rgb`` holds the image so far)."""
        return out.rgb

    def bake_colors(self, module: nn.Module | None, colors: Tensor, camera: "Camera") -> Tensor:
        """Per-Gaussian colours [N, 3] with the effect folded in for ``camera``'s photo, where that
        can be done (an export baking a reference photo's appearance). The default leaves them
        unchanged: an effect behind the Gaussians, like the environment, is no part of them."""
        return colors

    def cost(self, module: nn.Module | None) -> dict[str, float]:
        """What the effect adds to the model: its trained parameters (its time shows in the run's
        step times and in hico-bench's effect cells)."""
        return {"parameters": float(sum(p.numel() for p in module.parameters())) if module is not None else 0.0}


EFFECTS: Registry[type[Effect]] = Registry("effect")

# Findings measured and reported for every capture that no model component simulates.
REPORTED_ONLY = ("noise", "distortion", "multi_distance")


@dataclass
class EffectChoice:
    """Whether one effect is simulated, and why (forced, or what the analysis measured)."""

    name: str
    on: bool
    reason: str

    def line(self) -> str:
        return f"{self.name}: {'on' if self.on else 'off'} — {self.reason}"


@dataclass
class EffectsReport:
    """What ``analyze_effects`` found, by finding name; ``per_image`` holds the photos' measured gains."""

    effects: dict[str, EffectFinding]
    per_image: list[dict[str, Any]]

    def lines(self) -> list[str]:
        return [f"{name:<15}{'yes' if f.present else 'no '} — {f.reason}" for name, f in self.effects.items()]

    def to_json(self) -> dict[str, Any]:
        return {"effects": {name: asdict(f) for name, f in self.effects.items()}, "per_image": self.per_image}

    def present(self, name: str) -> bool:
        return name in self.effects and self.effects[name].present


def analyze_effects(dataset: Any, evidence: DatasetEvidence | None = None) -> EffectsReport:
    """Every finding of ``dataset``: the one each registered effect answers, then those only reported."""
    from hico_plugin.analysis.image_quality import distortion_finding, noise_finding
    from hico_plugin.analysis.photo_gains import photo_gains
    from hico_plugin.analysis.view_distances import multi_distance_finding

    evidence = evidence or DatasetEvidence(dataset)
    findings: dict[str, EffectFinding] = {}
    for _, effect_class in EFFECTS.items():
        effect = effect_class()
        if effect.finding not in findings:
            findings[effect.finding] = effect.detect(evidence)
    reported = {"noise": noise_finding, "distortion": distortion_finding, "multi_distance": multi_distance_finding}
    for name in REPORTED_ONLY:
        findings.setdefault(name, reported[name](evidence))
    return EffectsReport(findings, photo_gains(evidence)[1])


def data_background(choices: dict[str, EffectChoice], report: EffectsReport | None,
                    evidence: DatasetEvidence) -> tuple[float, float, float] | None:
    """The colour the data says lies behind the Gaussians, from the first effect that is off and has an
    opinion (the environment: the median colour of the photo cells no point explains); None without one.
    Measured from ``evidence`` when every effect was forced and nothing was analysed."""
    for name, choice in choices.items():
        effect = EFFECTS.get(name)()
        if choice.on or not effect.replaces_background:
            continue
        finding = report.effects[effect.finding] if report is not None else effect.detect(evidence)
        colour = effect.background_when_off(finding)
        if colour is not None:
            return colour
    return None


def parse_effects(spec: str) -> dict[str, str]:
    """``"auto,environment=off"`` -> {effect: "auto" | "on" | "off"} for every registered effect (a
    renamed effect's old name is read as today's)."""
    choices = {name: "auto" for name in EFFECTS.names()}
    for token in (t.strip() for t in spec.split(",")):
        if token in ("", "auto"):
            continue
        name, sep, value = token.partition("=")
        name = RENAMED_EFFECTS.get(name, name)
        if not sep or value not in ("on", "off", "auto"):
            raise HicoError(f"--model.effects: expected 'auto' or NAME=on|off|auto items, got {token!r}")
        if name not in EFFECTS:
            raise HicoError(f"--model.effects: unknown effect {name!r}; registered: {', '.join(EFFECTS.names())}")
        choices[name] = value
    return choices


def choose_effects(spec: str, dataset: Any, total_steps: int | None = None, model_config: Any = None,
                   evidence: DatasetEvidence | None = None) -> tuple[dict[str, EffectChoice], EffectsReport | None]:
    """Resolve ``spec`` against ``dataset`` for a run of ``total_steps``: (choice per effect, the
    analysis report or None when every effect was forced)."""
    choices = parse_effects(spec)
    report = None
    if any(value == "auto" for value in choices.values()):
        report = analyze_effects(dataset, evidence)
    out = {}
    for name, value in choices.items():
        if value == "auto":
            effect = EFFECTS.get(name)()
            out[name] = effect.auto_choice(name, report.effects[effect.finding], total_steps, model_config)
        else:
            out[name] = EffectChoice(name, value == "on", "forced by --model.effects")
    return out, report
