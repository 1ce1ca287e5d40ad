"""Named registries of swappable components.

A component kind (renderer backend, context aggregator, loss, field, model, ...) owns one
``Registry``; implementations register under a short name, and configs hold that name as a plain
string, so tyro exposes the choice as a flag (``--model.renderer.backend gsplat``) and a plugin can add
a new implementation without editing this package::

    CONTEXT_AGGREGATORS = Registry("context aggregator")

    @CONTEXT_AGGREGATORS.register("mean")
    class MeanContext(nn.Module): ...

    CONTEXT_AGGREGATORS.get("mean")  # -> MeanContext
"""

from __future__ import annotations

from typing import Callable, Generic, TypeVar

from hico_plugin.errors import HicoError

T = TypeVar("T")


class Registry(Generic[T]):
    """A mapping from a name to one implementation of a component kind."""

    def __init__(self, kind: str):
        self.kind = kind
        self._entries: dict[str, T] = {}

    def register(self, name: str) -> Callable[[T], T]:
        """Decorator: register ``obj`` under ``name``; a second registration of a name is an error."""

        def decorate(obj: T) -> T:
            if name in self._entries and self._entries[name] is not obj:
                raise ValueError(f"{self.kind} '{name}' is already registered")
            self._entries[name] = obj
            return obj

        return decorate

    def get(self, name: str) -> T:
        """The implementation registered as ``name``, or a HicoError listing the registered names."""
        try:
            return self._entries[name]
        except KeyError:
            raise HicoError(
                f"unknown {self.kind} '{name}'; registered: {', '.join(self.names()) or '(none)'}"
            ) from None

    def names(self) -> list[str]:
        return sorted(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries
