"""Base class for configs that build the object they describe (nerfstudio's pattern)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass
class InstantiateConfig:
    """A dataclass config whose ``setup(**kwargs)`` returns the component it describes.

    Field docstrings (the string literal under each field) become ``--help`` text through tyro.
    Subclasses override ``setup``; configs nest (method -> model -> field / renderer / losses).
    """

    def setup(self, **kwargs: Any) -> Any:
        raise NotImplementedError(f"{type(self).__name__} does not build anything")
