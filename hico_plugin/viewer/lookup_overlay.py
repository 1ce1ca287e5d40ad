"""The "CLCA parent found" anchor overlay: which anchors CLCA finds a parent context for.

A model may offer ``viewer_parent_found() -> Tensor [A] bool`` (every anchor counted as visible);
the viewer then colours the anchor cloud by it instead of by level when the overlay is switched on.
"""

from __future__ import annotations

from typing import Any

import numpy as np

FOUND = (40, 200, 80)  # green: the parent context was found
MISSING = (230, 50, 40)  # red: no parent anchor among the candidates (the learned "missing" vector)
COARSEST = (150, 150, 150)  # grey: level 0 has no coarser level


def parent_found_colors(found: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """uint8 [A, 3] colours of anchors from found [A] bool and levels [A] int."""
    colors = np.where(np.asarray(found, bool)[:, None], np.array(FOUND, np.uint8), np.array(MISSING, np.uint8))
    return np.where((np.asarray(levels) == 0)[:, None], np.array(COARSEST, np.uint8), colors).astype(np.uint8)


def read_parent_found(state: Any) -> np.ndarray | None:
    """found [A] bool from a viewer state whose model offers ``viewer_parent_found``, else None."""
    read = getattr(state, "anchor_parent_found", None)
    found = read() if callable(read) else None
    return None if found is None else found.detach().cpu().numpy().astype(bool).reshape(-1)
