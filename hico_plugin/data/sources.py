"""Where training data comes from: a COLMAP directory, or a built-in scene when none is given."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from hico_plugin.data.dataset import Dataset
from hico_plugin.data.parser import ColmapDataParserConfig


@dataclass
class DataSourceConfig(ColmapDataParserConfig):
    """A COLMAP dataset (``--data DIR``), or with no ``--data`` the built-in ``--scene`` (generated and
    cached on first use)."""

    data: Optional[Path] = None
    """COLMAP dataset directory (images/ + sparse/0); omit it to train on the built-in --scene."""
    scene: str = "city-block"
    """Built-in scene used when --data is not given (city-block, pagoda, tiny)."""

    def setup(self, **kwargs: Any) -> Dataset:
        if self.data is not None:
            return super().setup(**kwargs)
        from hico_plugin.scenes.generate import generate_scene

        parser = dataclasses.replace(self, data=generate_scene(self.scene))
        return ColmapDataParserConfig.parse(parser)
