"""AnchorField: the octree anchors as an nn.Module, with selection, CLCA and decoding.

Per view: ``visible_ids = field.select(camera, step)`` (step=None at eval: all levels), ``gaussians =
field.decode(camera, visible_ids)``, render, backward; after the optimizer update ``field.after_update()``.
Densification is a strategy beside the field (``hico_plugin.strategy``) that edits it through ``resize``:
per anchor-row group the new parameter is ``cat([old[kept_rows], new rows])`` (``Optimizers.resize_group``'s
contract).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field as dataclass_field
from typing import Any

import torch
from torch import Tensor, nn

from hico_plugin.cameras import Camera, Cameras
from hico_plugin.config import InstantiateConfig
from hico_plugin.errors import HicoError
from hico_plugin.field.chunks import AnchorChunks
from hico_plugin.field.snapshot import TensorSnapshot
from hico_plugin.field.context import ContextConfig
from hico_plugin.field.decoder import DecoderConfig, NeuralGaussians
from hico_plugin.field.gather import take_rows
from hico_plugin.field.lod import active_level_count, frustum_visible, lod_visible, progressive_interval_ends
from hico_plugin.field.octree import OctreeBuildConfig, OctreeGrid, build_octree, knn_log_scale
from hico_plugin.row_sparse import sparse_rows
from hico_plugin.strategy.base import DensifyConfig

def anchor_radii(log_scaling: Tensor) -> Tensor:
    """World-space extent of each anchor's Gaussians, 3 sigma of its largest offset scale: [N] from [N,6]."""
    return 3.0 * torch.exp(log_scaling[:, :3]).amax(1)


# Parameter groups whose rows are anchors (resized by densification), and the attribute holding each.
ANCHOR_GROUPS = {"anchor": "anchors", "offset": "offsets", "anchor_feat": "anchor_features",
                 "scaling": "log_scaling"}
# Per-anchor buffers, resized together with the anchor parameters.
ANCHOR_BUFFERS = ("levels", "drawn", "extra_level")


@dataclass
class FieldConfig(InstantiateConfig):
    """The octree-anchor field: octree construction, LOD selection, CLCA, decoder, densification."""

    feature_dim: int = 32
    """d, the anchor feature size."""
    octree: OctreeBuildConfig = dataclass_field(default_factory=OctreeBuildConfig)
    context: ContextConfig = dataclass_field(default_factory=ContextConfig)
    decoder: DecoderConfig = dataclass_field(default_factory=DecoderConfig)
    densify: DensifyConfig = dataclass_field(default_factory=DensifyConfig)
    """The densification strategy and its schedule (built beside the field by the model)."""
    reference_steps: int = 30_000
    """Step values of the schedules (coarse_steps, densify.*) are written for a run of this many
    optimizer steps (the paper's 30k iterations); a run of T steps scales them by T / reference_steps.
    CityGS-X counts its schedules in images (batch size per step); here they count optimizer steps,
    and the statistics thresholds follow the views actually accumulated per step."""
    progressive: bool = True
    """Coarse-to-fine: levels above octree.init_level switch on one by one during training."""
    coarse_steps: int = 10_000
    """Step at which the last level switches on (CityGS-X's coarse_iter)."""
    coarse_factor: float = 1.5
    """Each level's activation interval is this factor shorter than the previous one."""
    frustum_margin: float = 0.15
    """Anchors projecting up to this fraction of the image size outside it are kept (their Gaussians
    spread around them)."""
    near: float = 0.01
    """Anchors closer than this to the camera plane (z) are culled."""
    train_anchor_positions: bool = True
    """Anchor positions get a learning rate (CityGS-X); False freezes them (Octree-GS, Scaffold-GS)."""
    sparse_grad: bool = False
    """Per-anchor parameters get row-sparse gradients and Adam updates only the anchors a step decoded
    (Taming 3DGS's sparse Adam, gsplat's sparse_grad), so a step costs what its views see. False: the
    dense update of the base code, in which every anchor's moments and values move every step."""
    chunk_size: int = 512
    """Anchors per chunk of the view culling: a view tests the chunks' bounds, then the anchors of the
    chunks it may see; 0 tests every anchor of the model for every view."""

    def setup(self, points: Tensor | None = None, train_cameras: Cameras | None = None,
              num_train_cameras: int | None = None, schedule_scale: float = 1.0,
              distances: tuple[float, float] | None = None, **kwargs) -> "AnchorField":
        """Build the octree from sparse points [P,3] and the training cameras, then the field.

        The field is built on the CPU; move it with ``.to(device)`` like any module. ``schedule_scale``
        (the run's length / ``reference_steps``, decided by the model) scales the step schedules;
        ``distances``: the camera-to-point distance range when the caller measured it already.
        """
        if points is None or train_cameras is None:
            raise HicoError("field: setup needs the sparse points and the training cameras")
        points = torch.as_tensor(points, dtype=torch.float32).cpu()
        centers = train_cameras.centers.float().cpu()
        positions, levels, grid = build_octree(points, centers, self.octree, distances)
        return AnchorField(self, positions, levels, grid, centers,
                           num_train_cameras if num_train_cameras is not None else len(train_cameras),
                           schedule_scale)


class AnchorField(nn.Module):
    """Octree anchors (N of them) and the networks decoding them into Gaussians.

    Parameters: anchors [N,3] (p), offsets [N,K,3], anchor_features [N,d], log_scaling [N,6] (s[:3] scales the
    offsets, s[3:] bounds the children's scales). Buffers: levels [N] long; drawn [N] bool (False: an ancestor
    kept only for CLCA, ``DensifyConfig.draw_ancestors``); extra_level [N] (the paper's "learnable" eps, set by
    the densification rule as in the base code); training camera centres [C,3]; the ``OctreeGrid`` as extra
    state.
    """

    def __init__(self, config: FieldConfig, positions: Tensor, levels: Tensor, grid: OctreeGrid,
                 camera_centers: Tensor, num_train_cameras: int = 0, schedule_scale: float = 1.0):
        super().__init__()
        self.config = config
        self.grid = grid
        num, k, d = positions.shape[0], config.decoder.num_offsets, config.feature_dim
        self.anchors = nn.Parameter(positions.float().clone())
        self.offsets = nn.Parameter(torch.zeros(num, k, 3))
        self.anchor_features = nn.Parameter(torch.zeros(num, d))
        self.log_scaling = nn.Parameter(knn_log_scale(self.anchors.detach())[:, None].repeat(1, 6))
        self.register_buffer("levels", levels.long().clone())
        self.register_buffer("drawn", torch.ones(num, dtype=torch.bool))
        self.register_buffer("extra_level", torch.zeros(num))
        self.register_buffer("train_camera_centers", camera_centers.float().clone())
        self.context = config.context.setup(feature_dim=d)
        self.decoder = config.decoder.setup(feature_dim=d, num_train_cameras=num_train_cameras)
        self.set_schedule_scale(schedule_scale)
        self._chunks: AnchorChunks | None = None
        self._chunks_of: TensorSnapshot | None = None  # the tensors the chunks' bounds were read from
        self._counts: tuple[TensorSnapshot | None, dict[str, float]] = (None, {})  # stats() of those tensors

    # ----- schedule -------------------------------------------------------------------------------

    def set_schedule_scale(self, scale: float) -> None:
        """Scale the level schedule by ``scale`` (a run's length / ``reference_steps``)."""
        self.schedule_scale = scale
        coarse = self.config.coarse_steps * scale if self.config.progressive else 0
        self.level_interval_ends = progressive_interval_ends(self.grid, coarse, self.config.coarse_factor)

    def progressive_done(self, step: int | None) -> bool:
        """Whether every level is active (growth into finer levels and eps updates allowed)."""
        return step is None or not self.level_interval_ends or step > self.level_interval_ends[-1]

    # ----- per view -------------------------------------------------------------------------------

    @property
    def num_anchors(self) -> int:
        return self.anchors.shape[0]

    def active_levels(self, step: int | None) -> int:
        """Number of levels usable at ``step`` (coarse-to-fine schedule; None = all)."""
        return active_level_count(self.grid, step, self.level_interval_ends)

    @torch.no_grad()
    def select(self, camera: Camera, step: int | None = None, distance_scale: float = 1.0) -> Tensor:
        """Anchors to decode for ``camera``: LOD (paper Eq. 1 with eps) then frustum culling.

        step: training step (progressive levels) or None at eval (all levels). distance_scale
        multiplies the camera distance in Eq. 1 (>1 picks coarser levels; the viewer's LOD control).
        Returns visible_ids [V] long, ascending. Only the anchors of the chunks the view may see are
        tested (``chunks.py``); the result is the rule's over every anchor.
        """
        if self.config.chunk_size <= 0:
            return self.sees(camera, None, step, distance_scale).nonzero().squeeze(1)
        rows = self.chunks().candidates(camera, self.grid, self.active_levels(step), distance_scale,
                                        self.config.near, self.config.frustum_margin)
        if 2 * rows.numel() > self.num_anchors:  # a view of most of the model: test all, no gather or sort
            return self.sees(camera, None, step, distance_scale).nonzero().squeeze(1)
        return rows[self.sees(camera, rows, step, distance_scale)].sort().values

    @torch.no_grad()
    def sees(self, camera: Camera, ids: Tensor | None, step: int | None = None, distance_scale: float = 1.0) -> Tensor:
        """Which of the anchors ``ids`` [V] long (None: all N) ``camera`` decodes, by ``select``'s rule:
        [V] bool."""
        positions, levels = self.anchors.detach(), self.levels
        extra_level, log_scaling = self.extra_level, self.log_scaling.detach()
        if ids is not None:
            positions, levels, extra_level, log_scaling = (
                positions[ids], levels[ids], extra_level[ids], log_scaling[ids])
        center = camera.center.to(positions)
        seen = lod_visible(positions, levels, extra_level, center, self.grid, self.active_levels(step),
                           distance_scale)
        # frustum test only on the LOD survivors: the cheaper test first
        candidates = seen.nonzero().squeeze(1)
        seen[candidates] = frustum_visible(positions[candidates], anchor_radii(log_scaling[candidates]), camera,
                                           self.config.near, self.config.frustum_margin)
        return seen

    # ----- view culling by chunks -----------------------------------------------------------------

    def _bounded_tensors(self) -> tuple[Tensor, ...]:
        return self.anchors, self.log_scaling, self.levels, self.extra_level

    def _record_chunk_state(self) -> None:
        self._chunks_of = TensorSnapshot(*self._bounded_tensors())

    def _chunk_state(self) -> str:
        """"current": the bounds hold; "moved": the same tensors, written since (the grouping holds,
        the bounds do not); "regroup": other tensors (densification, loading another size, a device)."""
        if self._chunks_of is None or self._chunks is None or self._chunks.order.device != self.anchors.device \
                or not self._chunks_of.same_tensors(*self._bounded_tensors()):
            return "regroup"
        return "current" if self._chunks_of.unchanged(*self._bounded_tensors()) else "moved"

    @torch.no_grad()
    def chunks(self) -> AnchorChunks:
        """The anchors' chunks with bounds that hold for today's values: regrouped when the anchors
        changed (densification, loading), bounds recomputed when a value changed unseen by
        ``after_update``."""
        state = self._chunk_state()
        if state != "current":
            radii = anchor_radii(self.log_scaling.detach())
            if state == "moved":
                self._chunks.refresh(self.anchors.detach(), self.levels, self.extra_level, radii)
            else:
                self._chunks = AnchorChunks.build(self.anchors.detach(), self.levels, self.extra_level, radii,
                                                  self.grid, self.config.chunk_size)
            self._record_chunk_state()
        return self._chunks

    @torch.no_grad()
    def after_update(self) -> None:
        """After the optimizer step: widen the chunks' bounds to the rows it moved (the rows of the
        position and scaling gradients when row-sparse; all rows otherwise)."""
        if self._chunk_state() == "regroup":
            return
        grads = [self.anchors.grad, self.log_scaling.grad]
        if any(grad is not None and not grad.is_sparse for grad in grads):
            self._chunks.refresh(self.anchors.detach(), self.levels, self.extra_level,
                                 anchor_radii(self.log_scaling.detach()))
        else:
            moved = [sparse_rows(grad)[0] for grad in grads if grad is not None]
            if moved:
                # the positions' and scalings' rows are the same rows when every drawn anchor was decoded
                same = len(moved) == 1 or torch.equal(moved[0], moved[1])
                rows = moved[0] if same else torch.cat(moved).unique()
                self._chunks.expand(rows, self.anchors.detach()[rows],
                                    anchor_radii(self.log_scaling.detach()[rows]))
        self._record_chunk_state()

    def decode(self, camera: Camera, visible_ids: Tensor, context_enabled: bool = True) -> NeuralGaussians:
        """Neural Gaussians of the visible anchors that are drawn; CLCA enhances their features
        unless disabled, with contexts read among all of ``visible_ids`` (ancestors kept for context
        included)."""
        features = self.enhanced_features(visible_ids, context_enabled)
        drawn = self.drawn.index_select(0, visible_ids)
        if not bool(drawn.all()):
            rows = drawn.nonzero().squeeze(1)
            features, visible_ids = take_rows(features, rows), visible_ids.index_select(0, rows)
        return self.decode_features(features, visible_ids, camera.center.to(features), camera.index)

    def enhanced_features(self, visible_ids: Tensor, context_enabled: bool = True) -> Tensor:
        """Features [V,d] of the anchors ``visible_ids`` [V] long (ascending), CLCA-enhanced with
        contexts read among those anchors only, unless disabled."""
        features = take_rows(self.anchor_features, visible_ids, self.config.sparse_grad)
        if context_enabled and self.context.reads_context:
            features = self.context(features, self.context.graph(self.levels, self.anchors, visible_ids, self.grid))
        return features

    def decode_features(self, features: Tensor, ids: Tensor, eyes: Tensor, appearance_index: int) -> NeuralGaussians:
        """Neural Gaussians of the anchors ``ids`` [V] long (no id twice) from their (enhanced) features [V,d],
        viewed from ``eyes``: [3] one camera centre, or [V,3] one viewpoint per anchor (an export's
        canonical views). appearance_index: the training slot of the appearance embedding (-1: the
        mean, neutral appearance)."""
        sparse = self.config.sparse_grad
        positions = take_rows(self.anchors, ids, sparse)
        return self.decoder(features, positions, take_rows(self.offsets, ids, sparse),
                            torch.exp(take_rows(self.log_scaling, ids, sparse)), self.levels.index_select(0, ids),
                            eyes, appearance_index, ids)

    # ----- optimisation -----------------------------------------------------------------------------

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        """Trainable parameters by group name (``clca`` / ``appearance`` only when they exist)."""
        groups = {name: [getattr(self, attr)] for name, attr in ANCHOR_GROUPS.items()}
        groups["mlp_opacity"] = list(self.decoder.mlp_opacity.parameters())
        groups["mlp_cov"] = list(self.decoder.mlp_cov.parameters())
        groups["mlp_color"] = list(self.decoder.mlp_color.parameters())
        if any(True for _ in self.context.parameters()):
            groups["clca"] = list(self.context.parameters())
        if self.decoder.appearance is not None:
            groups["appearance"] = list(self.decoder.appearance.parameters())
        return groups

    @torch.no_grad()
    def keep(self, rows: Tensor) -> dict[str, tuple[Tensor, int]]:
        """Keep only the anchors ``rows`` [R] long (ascending), with every per-anchor parameter and
        buffer; returns ``resize``'s {group: (rows, 0)}."""
        return self.resize(rows, self.anchors.new_zeros(0, 3), self.levels.new_zeros(0),
                           self.anchor_features.new_zeros(0, self.anchor_features.shape[1]), self.drawn.new_zeros(0))

    @torch.no_grad()
    def resize(self, kept_rows: Tensor, positions: Tensor, levels: Tensor, features: Tensor,
               drawn: Tensor) -> dict[str, tuple[Tensor, int]]:
        """Swap every per-anchor parameter / buffer for ``cat([old[kept_rows], new rows])``: G new anchors at
        positions [G,3] on their levels [G] long with features [G,d], drawn [G] bool; offsets zero, scales
        their cell's. Returns {group: (kept_rows, G)} for ``Optimizers.resize_group``."""
        num_new, k = positions.shape[0], self.offsets.shape[1]
        voxel = self.grid.voxel_size / float(self.grid.fork) ** levels.to(torch.float32)
        new_rows = {
            "anchors": positions.to(self.anchors),
            "offsets": self.offsets.new_zeros(num_new, k, 3),
            "anchor_features": features.to(self.anchor_features),
            "log_scaling": torch.log(voxel).to(self.log_scaling)[:, None].repeat(1, 6),
        }
        for attr, rows in new_rows.items():
            old = getattr(self, attr)
            setattr(self, attr, nn.Parameter(torch.cat([old.detach()[kept_rows], rows]),
                                             requires_grad=old.requires_grad))
        given = {"levels": levels, "drawn": drawn}  # every other buffer starts at zero
        for name in ANCHOR_BUFFERS:
            old = getattr(self, name)
            rows = given[name].to(old) if name in given else old.new_zeros(num_new, *old.shape[1:])
            setattr(self, name, torch.cat([old[kept_rows], rows]))
        return {name: (kept_rows, num_new) for name in ANCHOR_GROUPS}

    # ----- introspection ----------------------------------------------------------------------------

    def level_counts(self) -> Tensor:
        """Anchors per level: [L] long."""
        return torch.bincount(self.levels, minlength=self.grid.num_levels)

    @torch.no_grad()
    def parent_found(self) -> Tensor:
        """[N] bool: CLCA's lookup finds a parent context, every anchor counted as visible (overlay)."""
        every = torch.arange(self.num_anchors, device=self.levels.device)
        return self.context.graph(self.levels, self.anchors, every, self.grid).parent_weight > 0

    def anchor_points(self) -> tuple[Tensor, Tensor]:
        """(positions [N,3], levels [N]) of all anchors, detached (viewer, export)."""
        return self.anchors.detach(), self.levels

    def bytes_per_anchor(self) -> dict[str, int]:
        """Memory each anchor of the field holds: its parameters, their two Adam moments, its buffers (level,
        drawn, eps) and its place in the culling chunks (the strategy's statistics are the strategy's)."""
        def row_bytes(tensor: Tensor) -> int:
            return math.prod(tensor.shape[1:]) * tensor.element_size()

        parameters = sum(row_bytes(getattr(self, attr)) for attr in ANCHOR_GROUPS.values())
        buffers = sum(row_bytes(getattr(self, name)) for name in ANCHOR_BUFFERS)
        chunks = 2 * torch.empty((), dtype=torch.long).element_size()  # order and chunk_of
        return {"parameters": parameters, "adam": 2 * parameters, "buffers": buffers, "culling": chunks,
                "total": 3 * parameters + buffers + chunks}

    def stats(self) -> dict[str, float]:
        """Counters for logs: total anchors and anchors per level (counted again only when the anchors
        changed: the trainer logs them every step)."""
        snapshot, counts = self._counts
        if snapshot is None or not snapshot.unchanged(self.levels, self.drawn):
            counts = {"num_anchors": float(self.num_anchors), "anchors/context_only": float((~self.drawn).sum())}
            for level, count in enumerate(self.level_counts().tolist()):
                counts[f"anchors/level_{level}"] = float(count)
            self._counts = (TensorSnapshot(self.levels, self.drawn), counts)
        return dict(counts)

    # ----- state ------------------------------------------------------------------------------------

    def get_extra_state(self) -> dict[str, Any]:
        return {"grid": self.grid.as_dict()}

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self.grid = OctreeGrid.from_dict(state["grid"])
        self.set_schedule_scale(self.schedule_scale)  # the level schedule depends on the grid's levels

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys,
                              unexpected_keys, error_msgs):
        # Checkpoints from before ancestors could be kept for context only draw every anchor.
        if prefix + "levels" in state_dict and prefix + "drawn" not in state_dict:
            state_dict[prefix + "drawn"] = torch.ones(len(state_dict[prefix + "levels"]), dtype=torch.bool)
        # The checkpoint may hold a different number of anchors (densification) or training cameras:
        # take its shapes before copying, so a freshly built field loads any checkpoint of the scene.
        for name, tensor in list(self._parameters.items()) + list(self._buffers.items()):
            saved = state_dict.get(prefix + name)
            if tensor is None or saved is None or saved.shape == tensor.shape:
                continue
            fresh = tensor.new_empty(saved.shape)
            if name in self._parameters:
                setattr(self, name, nn.Parameter(fresh, requires_grad=tensor.requires_grad))
            else:
                setattr(self, name, fresh)
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys,
                                      unexpected_keys, error_msgs)
