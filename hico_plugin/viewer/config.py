"""The viewer's settings, importable without viser (a training run without a viewer never loads it)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, TYPE_CHECKING

from hico_plugin.config import InstantiateConfig
from hico_plugin.errors import HicoError

if TYPE_CHECKING:
    from hico_plugin.viewer.viewer import Viewer


@dataclass
class ViewerConfig(InstantiateConfig):
    """Live viser viewer."""

    host: str = "127.0.0.1"
    """Interface to bind; 127.0.0.1 keeps it local (reach it remotely through `ssh -L`), 0.0.0.0 opens it."""
    port: int = 7007
    """First port to try; when busy, viser takes the next free one (the real URL is printed)."""
    max_resolution: int = 512
    """Initial longest side of a settled (full) render, in pixels; adjustable in the GUI."""
    min_resolution: int = 64
    """Smallest longest side of a preview render while the camera moves."""
    target_preview_fps: float = 8.0
    """Preview renders are sized so one takes about 1 / this many seconds."""
    settle_seconds: float = 0.25
    """Time without camera / option changes after which the view is rendered at full resolution."""
    refresh_seconds: float = 1.0
    """While training: how often the stats and plot are refreshed (and at most how often the view is)."""
    training_render_share: float = 0.2
    """While training: the largest share of wall time spent re-rendering the view as the model changes."""
    refresh_render_seconds: float = 1.0
    """While training: model-update re-renders are sized to take about this long (1 s at share 0.2: one every 5 s)."""
    anchor_refresh_seconds: float = 5.0
    """While training: how often the anchor cloud is re-read from the model."""
    max_cameras: int = 100
    """Training cameras drawn as frustums (evenly chosen when there are more)."""
    thumbnail_size: int = 96
    """Longest side of the images drawn in the frustums (0: no images)."""
    frustum_scale: float = 0.08
    """Frustum size as a fraction of the camera spread."""
    max_anchor_points: int = 200_000
    """Anchors drawn at most (evenly subsampled beyond)."""
    anchor_point_size: float = 0.004
    """Anchor point size as a fraction of the camera spread."""
    max_wait_for_step_seconds: float = 2.0
    """Longest the render thread waits for a training step before rendering again anyway."""
    jpeg_quality: int = 85
    """Quality of the JPEG stream of rendered images."""

    def setup(self, **kwargs: Any) -> "Viewer":
        """``setup(render_fn=..., state=...)`` starts the viewer."""
        from hico_plugin.viewer.viewer import Viewer  # viser is imported only when a viewer starts

        return Viewer(self, **kwargs)


def validate_viewer_config(config: ViewerConfig) -> None:
    if not 0 <= config.port <= 65535:
        raise HicoError(f"viewer.port: expected 0..65535, got {config.port}")
    if not 16 <= config.min_resolution <= config.max_resolution:
        raise HicoError(
            f"viewer.min_resolution / max_resolution: expected 16 <= min <= max, got {config.min_resolution} / {config.max_resolution}"
        )
    if config.target_preview_fps <= 0:
        raise HicoError(f"viewer.target_preview_fps: expected > 0, got {config.target_preview_fps}")
    if not 0.0 < config.training_render_share <= 1.0:
        raise HicoError(f"viewer.training_render_share: expected in (0, 1], got {config.training_render_share}")
