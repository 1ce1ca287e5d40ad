"""The loss component contract and its registry.

A loss is one file registering its ``LossConfig`` (``enabled`` plus its options) in ``LOSSES``, so each, a
plug-in's too, is a ``--model.losses.NAME...`` option. Its component, built by ``setup(schedule_scale=...)`` when
enabled, answers per step ``required_outputs(step)`` (the render outputs it reads, so only those are rendered) and
``__call__(outputs, target, step)`` (a dict of named, already weighted terms; empty when inactive at this step).
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
