"""Named registries of swappable components.

A component kind (renderer backend, loss, field, ...) owns one ``Registry``; each implementation registers under a
short name (``@CONTEXT_AGGREGATORS.register("mean")``) that configs hold as a plain string, so tyro exposes the
choice as a flag (``--model.renderer.backend gsplat``) and a plugin adds one without editing this package: an
entry point of group ``hico_plugin.components`` names a module whose import registers its components and presets
(``register_preset``), imported when a registry is first read (``load_plugins``; ``tests/plugin_example/``).
"""

from __future__ import annotations

import importlib.metadata
import inspect
import warnings
from typing import Any, Callable, Generic, TypeVar

import tyro

from hico_plugin.errors import HicoError

T = TypeVar("T")

PLUGIN_GROUP = "hico_plugin.components"
_plugins_loaded = False


def load_plugins() -> None:
    """Import every module named by a ``hico_plugin.components`` entry point, once per process.

    A plug-in that fails to import (missing dependency, error in its code, a name clash) is skipped
    with one warning naming it: someone else's broken package must not stop ``hico-train``.
    """
    global _plugins_loaded
    if _plugins_loaded:
        return
    # Set first: a plug-in's own import reads registries, which must not start a second round.
    _plugins_loaded = True
    for entry_point in importlib.metadata.entry_points(group=PLUGIN_GROUP):
        try:
            entry_point.load()
        except Exception as err:  # noqa: BLE001 -- any failure of foreign code is reported, not raised
            source = entry_point.dist.name if entry_point.dist is not None else "unknown distribution"
            warnings.warn(f"hico_plugin plug-in '{entry_point.name}' ({entry_point.value}, from {source}) "
                          f"was not loaded: {type(err).__name__}: {err}", stacklevel=2)


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
        load_plugins()
        try:
            return self._entries[name]
        except KeyError:
            raise HicoError(
                f"unknown {self.kind} '{name}'; registered: {', '.join(self.names()) or '(none)'}"
            ) from None

    def registered(self) -> list[tuple[str, T]]:
        """(name, implementation) in registration order, without importing plug-ins: for building
        config classes while this package is still being imported."""
        return list(self._entries.items())

    def items(self) -> list[tuple[str, T]]:
        """(name, implementation) in registration order, installed plug-ins' included."""
        load_plugins()
        return list(self._entries.items())

    def defaults(self) -> dict[str, Any]:
        """Name -> default instance of every registered config class, installed plug-ins' included; one
        whose options lack defaults (a plug-in's mistake) is left out with one warning naming it."""
        instances = {}
        for name, config in self.items():
            try:
                instances[name] = config()
            except TypeError as err:
                warnings.warn(f"{self.kind} '{name}' ({config.__module__}) left out: every option needs a default "
                              f"({err})", stacklevel=2)
        return instances

    def subcommands(self) -> Any:
        """A tyro subcommand union of the registered config classes, each named by its registered name and
        described by its docstring. Built when a command line is parsed, never at import: that is when
        plug-ins have loaded (a plug-in's module may import the module that asks)."""
        defaults = self.defaults()
        return tyro.extras.subcommand_type_from_defaults(
            defaults, descriptions={name: inspect.getdoc(type(config)) or "" for name, config in defaults.items()},
            prefix_names=False)

    def names(self) -> list[str]:
        load_plugins()
        return sorted(self._entries)

    def __contains__(self, name: object) -> bool:
        load_plugins()
        return name in self._entries
