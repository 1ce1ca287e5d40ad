"""When to render and at what size: pure functions the render thread follows."""

from __future__ import annotations

import math
from typing import Literal

RenderKind = Literal["preview", "full", "refresh"]


def next_resolution(last_render_seconds: float, target_seconds: float, current: int, minimum: int, maximum: int) -> int:
    """The longest image side for the next preview render, so a render takes about ``target_seconds``.

    Render time grows with the pixel count, i.e. with the square of the side, so the side is scaled by
    sqrt(target / last). The step is limited to x0.5 .. x2 so one slow frame (a GC pause, training
    holding the CPU) does not collapse the picture. The result is clamped to [minimum, maximum].
    """
    if minimum > maximum:
        raise ValueError(f"next_resolution: minimum {minimum} > maximum {maximum}")
    if not math.isfinite(last_render_seconds) or last_render_seconds <= 0.0:
        scaled = 2.0 * current  # no usable measurement (e.g. a zero-time render): grow
    else:
        factor = math.sqrt(target_seconds / last_render_seconds)
        scaled = current * min(max(factor, 0.5), 2.0)
    return int(min(max(round(scaled), minimum), maximum))


def plan_render(
    now: float,
    last_change_time: float,
    version: int,
    rendered_version: int,
    rendered_full: bool,
    settle_seconds: float,
    model_changed: bool = False,
) -> RenderKind | None:
    """What a client's view needs now.

    ``version`` counts the user's changes (camera moved, option changed); ``rendered_version`` and
    ``rendered_full`` describe the picture on screen. Within ``settle_seconds`` of the last change the view gets
    fast low-resolution previews, then one full-resolution render; ``model_changed`` (training moved on) asks for
    a "refresh" at the fast preview size, which keeps training's share of the CPU.
    """
    settled = now - last_change_time >= settle_seconds
    if version != rendered_version:
        return "full" if settled else "preview"
    if not rendered_full and settled:
        return "full"
    if model_changed:
        return "refresh"
    return None


def refresh_interval(last_render_seconds: float, minimum_seconds: float, render_share: float) -> float:
    """Seconds between training-progress refreshes, so that renders take at most ``render_share`` of
    the wall time (a 2 s render at share 0.2 refreshes every 8 s), and never more often than
    ``minimum_seconds``."""
    if not 0.0 < render_share <= 1.0:
        raise ValueError(f"refresh_interval: render_share must be in (0, 1], got {render_share}")
    return max(minimum_seconds, last_render_seconds * (1.0 - render_share) / render_share)
