"""Where training data comes from: a dataset directory (any registered format), or a built-in scene."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from hico_plugin.data.dataset import Dataset
from hico_plugin.data.parser import DataParserConfig


@dataclass
class DataSourceConfig(DataParserConfig):
    """A dataset (``--data DIR``: COLMAP, transforms.json, hico-process output...), or with no ``--data``
    the built-in ``--scene`` (generated and cached on first use)."""

    data: Optional[Path] = None
    """Dataset directory (format detected, or named after it: --data DIR transforms); omit it to train on the built-in --scene."""
    scene: str = "city-block"
    """Built-in scene used when --data is not given (city-block, district, pagoda, room, tiny)."""

    def __post_init__(self) -> None:
        self.data = Path(self.data) if self.data is not None else None
        self.cache_dir = Path(self.cache_dir) if self.cache_dir is not None else None
        self.test_names = tuple(self.test_names)
        self.test_list = Path(self.test_list) if self.test_list is not None else None

    def setup(self, announce: bool = True, frame: dict | None = None, **kwargs: Any) -> Dataset:
        if self.data is not None:
            return super().setup(announce, frame, **kwargs)
        from hico_plugin.scenes.generate import generate_scene

        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(DataParserConfig)}
        fields["data"] = generate_scene(self.scene)
        return DataParserConfig(**fields).parse(announce, frame)
