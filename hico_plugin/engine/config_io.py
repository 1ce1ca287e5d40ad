"""``config.yml``: the whole config dataclass tree as YAML that reloads the run exactly.

Each dataclass is tagged with its import path (``!dataclass:hico_plugin.engine.trainer.TrainerConfig``), so
``load_config`` rebuilds the same classes; ``!path`` / ``!tuple`` keep their types; missing fields take their
defaults, unknown ones are an error naming the file and the field. The file is untrusted: a tag resolves only to a
config class already loaded (an ``InstantiateConfig`` subclass, a dataclass / enum one holds, or a subclass of
that) and never imports the module it names, so a loader imports the components first (``hico_plugin.presets``).
"""

from __future__ import annotations

import dataclasses
import os
import typing
from enum import Enum
from pathlib import Path, PurePath
from typing import Any

import yaml

from hico_plugin.errors import HicoError
from hico_plugin.storage import write_text_atomic

_DATACLASS_TAG = "!dataclass:"
_ENUM_TAG = "!enum:"
# Config classes that became plain mappings; config.yml files of runs trained before still load.
_NOW_MAPPINGS = {"hico_plugin.losses.LossesConfig"}  # a model's losses became a {name: LossConfig} mapping
# Config classes that moved to another module: the path older config.yml files name -> today's.
_MOVED = {"hico_plugin.model.sky.SkyConfig": "hico_plugin.model.effects.environment.EnvironmentConfig",
          "hico_plugin.model.effects.sky.SkyConfig": "hico_plugin.model.effects.environment.EnvironmentConfig",
          "hico_plugin.viewer.viewer.ViewerConfig": "hico_plugin.viewer.config.ViewerConfig",
          "hico_plugin.field.densify.DensifyConfig": "hico_plugin.strategy.base.DensifyConfig"}
# Effects renamed since runs were trained, old name -> today's: an old run's config.yml names the model's
# field by it, its --model.effects ("auto,sky=off") parses, and its checkpoint's module keys and optimizer
# group load under the new name (model.effects).
RENAMED_EFFECTS = {"sky": "environment"}
# Fields renamed since runs were trained: class -> {the name older config.yml files use: today's}.
_RENAMED_FIELDS = {"hico_plugin.model.hico.HiCoModelConfig": RENAMED_EFFECTS}
# Fields added after runs were trained, whose default changes what such a run means: a file without the
# field gets the value that reproduces the run (its scene frame was not rotated, or rotated by the
# cameras' mean up; its anchors were not kept nested, or its kept ancestors were drawn; its background was
# a fixed colour; its environment MLP ran at every pixel), not today's default.
_ADDED_FIELDS = {
    "hico_plugin.data.parser.DataParserConfig": {"orient": False, "orient_method": "up"},
    "hico_plugin.strategy.base.DensifyConfig": {"keep_ancestors": False, "draw_ancestors": True},
    "hico_plugin.model.hico.HiCoModelConfig": {"learn_background": False, "background_start": "configured"},
    "hico_plugin.model.effects.environment.EnvironmentConfig": {"stride": 1},
}


def _inherited(table: dict[str, dict[str, Any]], cls: type) -> dict[str, Any]:
    """The entries of ``table`` for ``cls`` and the classes it derives from (a run's config.yml names the
    subclass it was built with, e.g. the data source, not the parser config that has the field)."""
    merged: dict[str, Any] = {}
    for base in reversed(cls.__mro__):
        merged.update(table.get(f"{base.__module__}.{base.__qualname__}", {}))
    return merged


class _ConfigDumper(yaml.SafeDumper):
    pass


class _ConfigLoader(yaml.SafeLoader):
    pass


def _represent_object(dumper: yaml.SafeDumper, obj: Any) -> yaml.Node:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        values = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj) if f.init}
        cls = type(obj)
        return dumper.represent_mapping(f"{_DATACLASS_TAG}{cls.__module__}.{cls.__qualname__}", values)
    if isinstance(obj, PurePath):
        return dumper.represent_scalar("!path", str(obj))
    if isinstance(obj, Enum):
        cls = type(obj)
        return dumper.represent_scalar(f"{_ENUM_TAG}{cls.__module__}.{cls.__qualname__}", obj.name)
    raise HicoError(f"config value {obj!r} of type {type(obj).__name__} cannot be saved to config.yml")


_ConfigDumper.add_multi_representer(object, _represent_object)
# SafeDumper writes tuples as plain lists; the tag keeps them tuples.
_ConfigDumper.add_representer(tuple, lambda dumper, value: dumper.represent_sequence("!tuple", list(value)))


def _qualified(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def _classes_in(annotation: Any) -> list[type]:
    """The classes a field annotation names (through ``X | None``, ``tuple[X, ...]``, ...)."""
    if isinstance(annotation, type):
        return [annotation]
    return [cls for arg in typing.get_args(annotation) for cls in _classes_in(arg)]


def allowed_config_classes() -> dict[str, type]:
    """Import path -> class of every config class a config.yml may name: the loaded subclasses of
    ``InstantiateConfig`` and the dataclasses / enums their fields hold and those dataclasses' loaded
    subclasses, transitively."""
    from hico_plugin.config import InstantiateConfig
    from hico_plugin.registry import load_plugins

    load_plugins()  # installed plug-ins' config classes are loaded classes too
    allowed: dict[str, type] = {}
    stack: list[type] = [InstantiateConfig]
    while stack:
        cls = stack.pop()
        if _qualified(cls) in allowed:
            continue
        allowed[_qualified(cls)] = cls
        if not dataclasses.is_dataclass(cls):
            continue
        stack += cls.__subclasses__()  # a field of a config class may hold any subclass of it (a plug-in's format)
        try:
            hints = list(typing.get_type_hints(cls).values())
        except Exception:  # noqa: BLE001 - an annotation naming an unloaded type: use the defaults
            hints = []
        for field in dataclasses.fields(cls):
            if field.default is not dataclasses.MISSING and field.default is not None:
                hints.append(type(field.default))
        stack += [c for hint in hints for c in _classes_in(hint)
                  if (dataclasses.is_dataclass(c) or issubclass(c, Enum)) and _qualified(c) not in allowed]
    return allowed


def _config_class(qualified: str, loader: _ConfigLoader) -> type:
    qualified = _MOVED.get(qualified, qualified)
    allowed = getattr(loader, "allowed", None)
    if allowed is None:
        allowed = loader.allowed = allowed_config_classes()
    if qualified not in allowed:
        raise HicoError(f"{loader.name}: '{qualified}' is not a registered config class; refused without "
                        "importing it (expected a config.yml written by hico-train; install the plug-in "
                        "that provides it)")
    return allowed[qualified]


def _construct_dataclass(loader: _ConfigLoader, suffix: str, node: yaml.Node) -> Any:
    if suffix in _NOW_MAPPINGS:
        return loader.construct_mapping(node, deep=True) if isinstance(node, yaml.MappingNode) else {}
    cls = _config_class(suffix, loader)
    if not dataclasses.is_dataclass(cls):
        raise HicoError(f"{loader.name}: '{suffix}' is not a config dataclass")
    values = loader.construct_mapping(node, deep=True) if isinstance(node, yaml.MappingNode) else {}
    init_fields = {f.name for f in dataclasses.fields(cls) if f.init}
    renamed = _inherited(_RENAMED_FIELDS, cls)
    values = {**_inherited(_ADDED_FIELDS, cls), **{renamed.get(name, name): value for name, value in values.items()}}
    unknown = sorted(set(values) - init_fields)
    if unknown:
        raise HicoError(f"{loader.name}: unknown field(s) {', '.join(unknown)} for {cls.__qualname__}")
    return cls(**values)


def _construct_enum(loader: _ConfigLoader, suffix: str, node: yaml.Node) -> Any:
    cls = _config_class(suffix, loader)
    if not issubclass(cls, Enum):
        raise HicoError(f"{loader.name}: '{suffix}' is not an enum")
    name = loader.construct_scalar(node)
    try:
        return cls[name]
    except KeyError:
        raise HicoError(f"{loader.name}: '{name}' is not a member of {cls.__qualname__}") from None


_ConfigLoader.add_multi_constructor(_DATACLASS_TAG, _construct_dataclass)
_ConfigLoader.add_multi_constructor(_ENUM_TAG, _construct_enum)
_ConfigLoader.add_constructor("!path", lambda loader, node: Path(loader.construct_scalar(node)))
_ConfigLoader.add_constructor("!tuple", lambda loader, node: tuple(loader.construct_sequence(node, deep=True)))


class _AbsoluteDumper(_ConfigDumper):
    pass


# A run's config.yml must reload from any working directory: relative paths are written absolute.
_AbsoluteDumper.add_multi_representer(
    PurePath, lambda dumper, value: dumper.represent_scalar("!path", str(Path(value).expanduser().absolute()))
)


def save_config(config: Any, path: str | os.PathLike, absolute_paths: bool = False) -> Path:
    """Write ``config`` to ``path`` atomically (temp file + rename); returns the path. With
    ``absolute_paths`` every path is written absolute (a run's config.yml; presets stay relative)."""
    path = Path(path)
    dumper = _AbsoluteDumper if absolute_paths else _ConfigDumper
    write_text_atomic(path, yaml.dump(config, Dumper=dumper, sort_keys=False, default_flow_style=False))
    return path


def load_config(path: str | os.PathLike) -> Any:
    """The config dataclass tree saved by ``save_config``; HicoError on a missing / bad file."""
    path = Path(path)
    if not path.is_file():
        raise HicoError(f"{path}: config file not found (expected a run's config.yml)")
    with path.open("r", encoding="utf-8") as stream:
        loader = _ConfigLoader(stream)
        loader.name = str(path)
        try:
            config = loader.get_single_data()
        except yaml.YAMLError as err:
            raise HicoError(f"{path}: not valid YAML ({str(err).splitlines()[0]})") from None
        finally:
            loader.dispose()
    if not dataclasses.is_dataclass(config):
        raise HicoError(f"{path}: expected a config written by save_config (a !dataclass: mapping)")
    return config
