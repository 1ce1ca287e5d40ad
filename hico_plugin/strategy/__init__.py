"""Densification strategies (how anchors grow and shrink while training), each registered in ``STRATEGIES``.

    strategy = field_config.densify.setup(field=field, schedule_scale=scale)
    strategy.step_post_backward(field, gaussians, means2d_grad, radii, camera, step)   # after backward
    resized = strategy.step_post_update(field, step)   # after the optimizer: {group: (kept_rows, num_new)}
"""

from hico_plugin.strategy import octree  # noqa: F401 -- registers "octree"
from hico_plugin.strategy.base import STRATEGIES, DensifyConfig, Strategy

__all__ = ["STRATEGIES", "DensifyConfig", "Strategy"]
