"""``config.yml``: the whole config dataclass tree as YAML that reloads the run exactly.

Every dataclass is written with its import path as a YAML tag, so ``load_config`` rebuilds the same
classes (presets, subclasses, plugin components) without knowing them in advance::

    !dataclass:hico_plugin.engine.trainer.TrainerConfig
    max_steps: 3000
    output_dir: !path outputs/city-block
    model: !dataclass:hico_plugin.model.HiCoModelConfig
      ...

Paths and tuples keep their types (``!path``, ``!tuple``); fields missing from the file take their
defaults, unknown fields are an error naming the file and the field.
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import tempfile
from enum import Enum
from pathlib import Path, PurePath
from typing import Any

import yaml

from hico_plugin.errors import HicoError

_DATACLASS_TAG = "!dataclass:"
_ENUM_TAG = "!enum:"


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


def _import(qualified: str, loader: _ConfigLoader) -> Any:
    # Nested classes: peel attributes off the right until the rest imports as a module.
    parts = qualified.split(".")
    for split in range(len(parts) - 1, 0, -1):
        try:
            obj: Any = importlib.import_module(".".join(parts[:split]))
        except ImportError:
            continue
        try:
            for name in parts[split:]:
                obj = getattr(obj, name)
            return obj
        except AttributeError:
            break
    raise HicoError(f"{loader.name}: cannot import '{qualified}' named in the config") from None


def _construct_dataclass(loader: _ConfigLoader, suffix: str, node: yaml.Node) -> Any:
    cls = _import(suffix, loader)
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise HicoError(f"{loader.name}: '{suffix}' is not a config dataclass")
    values = loader.construct_mapping(node, deep=True) if isinstance(node, yaml.MappingNode) else {}
    init_fields = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(values) - init_fields)
    if unknown:
        raise HicoError(f"{loader.name}: unknown field(s) {', '.join(unknown)} for {cls.__qualname__}")
    return cls(**values)


def _construct_enum(loader: _ConfigLoader, suffix: str, node: yaml.Node) -> Any:
    cls = _import(suffix, loader)
    name = loader.construct_scalar(node)
    try:
        return cls[name]
    except KeyError:
        raise HicoError(f"{loader.name}: '{name}' is not a member of {cls.__qualname__}") from None


_ConfigLoader.add_multi_constructor(_DATACLASS_TAG, _construct_dataclass)
_ConfigLoader.add_multi_constructor(_ENUM_TAG, _construct_enum)
_ConfigLoader.add_constructor("!path", lambda loader, node: Path(loader.construct_scalar(node)))
_ConfigLoader.add_constructor("!tuple", lambda loader, node: tuple(loader.construct_sequence(node, deep=True)))


def config_to_yaml(config: Any) -> str:
    """The YAML text of a config dataclass tree."""
    return yaml.dump(config, Dumper=_ConfigDumper, sort_keys=False, default_flow_style=False)


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


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temp file in the same directory and ``os.replace``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as stream:
            stream.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
