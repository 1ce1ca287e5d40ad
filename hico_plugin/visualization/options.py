"""What a person asks a render for (in the viewer, hico-eval or hico-render): the output to show and
how to show it."""

from __future__ import annotations

from dataclasses import dataclass

# Every output the viewer offers, in dropdown order, with the render outputs each one needs.
# "normal_disagreement" is the angle between the rendered normal n_r and the depth normal n_d (what
# DNGC minimises); "level" is the per-pixel (alpha-weighted) octree level of the drawn Gaussians.
REQUIRED_OUTPUTS: dict[str, tuple[str, ...]] = {
    "rgb": ("rgb",),
    "depth": ("depth", "alpha"),
    "plane_depth": ("plane_depth", "alpha"),
    "normal": ("normal", "alpha"),
    "depth_normal": ("depth_normal", "alpha"),
    "normal_disagreement": ("normal", "depth_normal", "alpha"),
    "distance": ("distance", "alpha"),
    "alpha": ("alpha",),
    "level": ("level", "alpha"),
}
OUTPUT_NAMES: tuple[str, ...] = tuple(REQUIRED_OUTPUTS)
COLORMAP_NAMES: tuple[str, ...] = ("turbo", "viridis", "inferno", "magma", "jet", "gray")


@dataclass(frozen=True)
class RenderOptions:
    """One render request of the viewer (the GUI state at the time of the request)."""

    output: str = "rgb"
    """Which output to show: one of OUTPUT_NAMES."""
    colormap: str = "turbo"
    """Colormap for scalar outputs (depth, distance, alpha, disagreement, level): one of COLORMAP_NAMES."""
    max_resolution: int = 512
    """Longest image side the user allows; the camera handed to render_fn is already sized to fit."""
    level_range: tuple[int, int] | None = None
    """Inclusive range of octree levels to draw (LOD override); None keeps the model's own choice."""
    distance_scale: float = 1.0
    """Multiplies the camera distance in the LOD level rule (>1 picks coarser levels, <1 finer)."""
    clca_enabled: bool = True
    """Cross-level context aggregation on (True) or off for this view, to see what it changes."""
    normalize_percentiles: tuple[float, float] = (1.0, 99.0)
    """Percentiles of the valid pixels mapped to the ends of the colormap (depth, distance)."""
    max_disagreement_degrees: float = 90.0
    """Angle shown at the top of the colormap for the n_r vs n_d disagreement."""
    num_levels: int | None = None
    """Number of octree levels, so the level map uses the same colours as the anchor cloud."""

    def __post_init__(self) -> None:
        if self.output not in REQUIRED_OUTPUTS:
            raise ValueError(f"RenderOptions.output: '{self.output}' is not one of {', '.join(OUTPUT_NAMES)}")
        if self.colormap not in COLORMAP_NAMES:
            raise ValueError(f"RenderOptions.colormap: '{self.colormap}' is not one of {', '.join(COLORMAP_NAMES)}")

    @property
    def required_outputs(self) -> tuple[str, ...]:
        """The render outputs (RenderOutputs field names) needed to draw ``output``."""
        return REQUIRED_OUTPUTS[self.output]
