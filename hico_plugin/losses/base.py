"""The loss component contract and its registry.

A loss is one file that registers its config (a ``LossConfig``: ``enabled`` plus its own options) in
``LOSSES``; the model's ``losses`` hold one config per name, so every registered loss, a plug-in's too,
is a ``--model.losses.NAME...`` option. Its component, built by ``setup(schedule_scale=...)`` when the
loss is enabled, answers two questions per step:
``required_outputs(step)`` -- which render outputs it reads (so the model renders only those), and
``__call__(outputs, target, step)`` -- a dict of named, already weighted terms that the model sums and
logs one by one (an empty dict when the component is inactive at this step).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from torch import Tensor

from hico_plugin.config import InstantiateConfig
from hico_plugin.errors import HicoError
from hico_plugin.rasterizer.base import RenderOutputs
from hico_plugin.registry import Registry


class LossComponent(Protocol):
    def required_outputs(self, step: int) -> set[str]:
        """Names of the RenderOutputs images this component reads at ``step``."""

    def __call__(self, outputs: RenderOutputs, target: Tensor, step: int) -> dict[str, Tensor]:
        """Weighted loss terms by name; their sum is the component's contribution to the loss."""


@dataclass
class LossConfig(InstantiateConfig):
    """Base of a registered loss config."""

    enabled: bool = True
    """Add this loss's terms to the training loss."""

    def setup(self, schedule_scale: float = 1.0, **kwargs: Any) -> LossComponent:
        """The component; ``schedule_scale`` (run length / reference length) scales step schedules."""
        raise NotImplementedError


LOSSES: Registry[type[LossConfig]] = Registry("loss")
"""Loss configs by name ("rgb", "dngc"); ``LOSSES.get(name)().setup()`` builds a component."""


def require_images(outputs: RenderOutputs, names: set[str], component: str) -> dict[str, Tensor]:
    """The named images of ``outputs``; a clear error if the renderer was not asked for some of them."""
    images = outputs.images()
    missing = sorted(names - images.keys())
    if missing:
        raise HicoError(
            f"loss '{component}' needs render outputs {', '.join(missing)}, which were not rendered "
            f"(render the names returned by required_outputs(step))"
        )
    return {name: images[name] for name in names}
