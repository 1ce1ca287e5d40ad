"""The whole model as explicit Gaussians: each anchor (all levels, or a level range) decoded once, from its own
view.

A splat file has no camera, so each anchor is decoded from the mean direction of the training cameras that decode
it (LOD and frustum, as ``AnchorField.select`` at evaluation), at their median distance; one scene-wide direction
would feed the MLPs directions they never saw. CLCA contexts are read among all anchors. The appearance is neutral
(mean appearance embedding, no exposure) or a reference photo's; what lies behind the Gaussians is left out.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from hico_plugin.cameras import Camera
from hico_plugin.errors import HicoError

CHUNK_ELEMENTS = 1 << 22
"""Anchors x training views per chunk: bounds the per-chunk distance table (16 MB) and the MLPs'
activations (those of CHUNK_ELEMENTS / views anchors)."""


@dataclass
class BakedGaussians:
    """Explicit Gaussians in the training (normalised) frame, each with opacity > 0.

    means [N, 3]; quats [N, 4] (w, x, y, z, unit); scales [N, 3] (linear); opacities [N] in (0, 1];
    colors [N, 3] RGB (the decoder's, in (0, 1); a reference photo's colour transform may take them
    outside); levels [N] long, the octree level of each one's anchor; anchor_ids [N] long; eyes
    [N, 3], the canonical viewpoint its anchor was decoded for.
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    levels: Tensor
    anchor_ids: Tensor
    eyes: Tensor

    def __len__(self) -> int:
        return self.means.shape[0]


@torch.no_grad()
def canonical_views(field, cameras: list[Camera], ids: Tensor) -> tuple[Tensor, Tensor]:
    """The view each anchor ``ids`` [V] long of ``field`` (an AnchorField) is baked for, from the
    training ``cameras``: (directions [V, 3] unit, camera -> anchor; distances [V]).

    The direction is the normalised mean of the unit directions from the cameras that decode the
    anchor, the distance the median of theirs. An anchor no camera decodes, or whose cameras' directions
    cancel out, takes the nearest camera's direction and distance.
    """
    positions = field.anchors.detach()[ids]
    direction_sum = torch.zeros_like(positions)
    distances = positions.new_full((len(ids), len(cameras)), float("nan"))  # NaN: camera does not decode it
    nearest_distance = positions.new_full((len(ids),), float("inf"))
    nearest_direction = torch.zeros_like(positions)
    for column, camera in enumerate(cameras):
        to_anchor = positions - camera.center.to(positions)
        distance = to_anchor.norm(dim=-1)
        unit = to_anchor / distance.clamp_min(1e-12)[:, None]
        seen = field.sees(camera, ids)
        direction_sum += unit * seen[:, None]
        distances[:, column] = torch.where(seen, distance, distances[:, column])
        closer = distance < nearest_distance
        nearest_distance = torch.where(closer, distance, nearest_distance)
        nearest_direction = torch.where(closer[:, None], unit, nearest_direction)
    length = direction_sum.norm(dim=-1)
    seen_any = length > 1e-6
    directions = torch.where(seen_any[:, None], direction_sum / length.clamp_min(1e-12)[:, None], nearest_direction)
    median = distances.nanmedian(dim=1).values  # NaN only where no camera decodes the anchor
    return directions, torch.where(seen_any, median, nearest_distance)


@torch.no_grad()
def bake(model, dataset, level_range: tuple[int, int] | None = None, reference_view: int | None = None,
         chunk_elements: int = CHUNK_ELEMENTS) -> BakedGaussians:
    """Every anchor of ``model`` (a HiCoModel) decoded once for its canonical view (module docstring),
    in chunks of ``chunk_elements`` / training views anchors.

    level_range (lo, hi), inclusive, keeps the anchors of those levels; their Gaussians are those of
    the whole bake (contexts are still read among all anchors). reference_view: a training photo
    (dataset index) whose appearance is baked in: its appearance embedding and what the effects fold
    into colours (exposure's colour transform); None: the neutral appearance.
    """
    field = model.field
    device = field.anchors.device
    slot, photo = -1, None
    if reference_view is not None:
        if reference_view not in model.train_slot:
            raise HicoError(f"--appearance-view: {reference_view} is not a training photo of this run "
                            f"(only those have a learned appearance)")
        photo = model.appearance_camera(dataset.cameras[reference_view].to(device))
        slot = photo.index
    every = torch.arange(field.num_anchors, device=device)
    features = field.enhanced_features(every)
    kept = every[field.drawn]  # ancestors kept for CLCA's context only are not drawn
    if level_range is not None:
        kept = kept[(field.levels[kept] >= level_range[0]) & (field.levels[kept] <= level_range[1])]
        if len(kept) == 0:
            raise HicoError(f"--levels: no anchor has a level in {level_range[0]}..{level_range[1]} "
                            f"(the model's levels: 0..{field.grid.num_levels - 1})")
    cameras = [dataset.cameras[int(i)].to(device) for i in dataset.train_indices]
    chunk = max(1, chunk_elements // max(1, len(cameras)))
    parts = []
    for start in range(0, len(kept), chunk):
        ids = kept[start:start + chunk]
        directions, distances = canonical_views(field, cameras, ids)
        eyes = field.anchors.detach()[ids] - directions * distances[:, None]
        decoded = field.decode_features(features[ids], ids, eyes, slot)
        colors = decoded.colors
        if photo is not None:
            for name, effect in model.active_effects.items():
                colors = effect.bake_colors(model.effects[name] if name in model.effects else None, colors, photo)
        rows = torch.searchsorted(ids, decoded.anchor_ids)  # ids ascending: each Gaussian's anchor row
        parts.append(BakedGaussians(decoded.means, decoded.quats, decoded.scales, decoded.opacities, colors,
                                    field.levels[decoded.anchor_ids], decoded.anchor_ids, eyes[rows]))
    return BakedGaussians(**{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(BakedGaussians)})

