"""AnchorField: the octree anchors as an nn.Module, with selection, CLCA, decoding and densification.

Per view: ``visible_ids = field.select(camera, step)`` (step=None at eval: all levels), ``gaussians =
field.decode(camera, visible_ids)``, render, backward, ``field.accumulate_stats(gaussians, out.means2d.grad,
out.radii, camera, step)``. After the optimizer update, on ``field.is_densify_step(step)`` (``sync_stats`` first
across processes), ``field.densify(step)`` gives per changed group ``(kept_rows [R] long, num_new)``: the new
parameter is ``cat([old[kept_rows], num_new new rows])`` (``Optimizers.resize_group``'s contract), or {}.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field as dataclass_field
from typing import Any, Callable

import torch
from torch import Tensor, nn

from hico_plugin.cameras import Camera, Cameras
from hico_plugin.config import InstantiateConfig
from hico_plugin.errors import HicoError
from hico_plugin.field.chunks import AnchorChunks
from hico_plugin.field.snapshot import TensorSnapshot
from hico_plugin.field.context import ContextConfig
from hico_plugin.field.decoder import DecoderConfig, NeuralGaussians
from hico_plugin.field.context_graph import cell_keys
from hico_plugin.field.gather import take_rows
from hico_plugin.field.densify import (DensifyConfig, GrownAnchors, close_ancestors, extra_level_increment,
                                       grow_anchors, offset_gradients, prune_decision, rows_in)
from hico_plugin.field.lod import active_level_count, frustum_visible, lod_visible, progressive_interval_ends
from hico_plugin.field.octree import OctreeBuildConfig, OctreeGrid, build_octree, knn_log_scale
from hico_plugin.row_sparse import sparse_rows

def anchor_radii(log_scaling: Tensor) -> Tensor:
    """World-space extent of each anchor's Gaussians, 3 sigma of its largest offset scale: [N] from [N,6]."""
    return 3.0 * torch.exp(log_scaling[:, :3]).amax(1)


# Parameter groups whose rows are anchors (resized by densification), and the attribute holding each.
ANCHOR_GROUPS = {"anchor": "anchors", "offset": "offsets", "anchor_feat": "anchor_features",
                 "scaling": "log_scaling"}
# Densification statistics; each has a ``<name>_synced`` twin holding its value at the last sync.
STAT_BUFFERS = ("opacity_accum", "anchor_denom", "offset_grad_accum", "offset_denom", "stat_views")
# Per-anchor buffers, resized together with the anchor parameters.
ANCHOR_BUFFERS = ("levels", "drawn", "extra_level", "opacity_accum", "anchor_denom", "offset_grad_accum",
                  "offset_denom", "opacity_accum_synced", "anchor_denom_synced",
                  "offset_grad_accum_synced", "offset_denom_synced")


@dataclass
class FieldConfig(InstantiateConfig):
    """The octree-anchor field: octree construction, LOD selection, CLCA, decoder, densification."""

    feature_dim: int = 32
    """d, the anchor feature size."""
    octree: OctreeBuildConfig = dataclass_field(default_factory=OctreeBuildConfig)
    context: ContextConfig = dataclass_field(default_factory=ContextConfig)
    decoder: DecoderConfig = dataclass_field(default_factory=DecoderConfig)
    densify: DensifyConfig = dataclass_field(default_factory=DensifyConfig)
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
    the densification rule as in the base code); opacity_accum [N], anchor_denom [N], offset_grad_accum [N,K],
    offset_denom [N,K]; training camera centres [C,3]; schedule counters; the ``OctreeGrid`` as extra state.
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
        self.register_buffer("opacity_accum", torch.zeros(num))
        self.register_buffer("anchor_denom", torch.zeros(num))
        self.register_buffer("offset_grad_accum", torch.zeros(num, k))
        self.register_buffer("offset_denom", torch.zeros(num, k))
        self.register_buffer("train_camera_centers", camera_centers.float().clone())
        self.register_buffer("stat_views", torch.zeros((), dtype=torch.long))
        self.register_buffer("last_adjust_step", torch.zeros((), dtype=torch.long))
        for name in STAT_BUFFERS:
            self.register_buffer(f"{name}_synced", getattr(self, name).clone())
        self.context = config.context.setup(feature_dim=d)
        self.keeps_ancestors = config.densify.keeps_tree(config.context)
        self.decoder = config.decoder.setup(feature_dim=d, num_train_cameras=num_train_cameras)
        self.set_schedule_scale(schedule_scale)
        self.last_densify: dict[str, int] = {}
        self._chunks: AnchorChunks | None = None
        self._chunks_of: TensorSnapshot | None = None  # the tensors the chunks' bounds were read from
        self._counts: tuple[TensorSnapshot | None, dict[str, float]] = (None, {})  # stats() of those tensors
        # The octree's own anchors, the base of a relative anchor budget. A resumed run rebuilds the
        # same octree from the same data before loading its checkpoint, so this stays the run's.
        self.initial_anchors = num

    # ----- schedule -------------------------------------------------------------------------------

    def set_schedule_scale(self, scale: float) -> None:
        """Scale the step-valued schedules by ``scale`` (a run's length / ``reference_steps``)."""
        self.schedule_scale = scale
        dens = self.config.densify
        self.densify_start = int(round(dens.start_step * scale))
        self.densify_interval = max(1, int(round(dens.interval * scale)))
        self.densify_stop = int(round(dens.stop_step * scale))
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
    def accumulate_stats(self, gaussians: NeuralGaussians, means2d_grad: Tensor, radii: Tensor,
                         camera: Camera, step: int) -> None:
        """Add one view to the densification statistics (until densify.stop_step).

        means2d_grad [M,2]: dL/dmeans2d in pixels of this view's loss (the rasterizer's means2d.grad;
        if the loss is a batch mean, multiply by the batch size first); it is converted to NDC units,
        the scale of grad_threshold. radii [M] (or [M,2]): Gaussians with radius 0 were not drawn.
        """
        if not self.config.densify.enabled or step > self.densify_stop:
            return
        ids = gaussians.visible_ids
        opacity_sums = gaussians.raw_opacities.clamp_min(0).sum(1).to(self.opacity_accum)
        self.opacity_accum.index_add_(0, ids, opacity_sums)
        self.anchor_denom.index_add_(0, ids, torch.ones_like(ids, dtype=self.anchor_denom.dtype))
        drawn = radii > 0 if radii.dim() == 1 else (radii > 0).any(-1)  # a view may decode nothing
        ndc = means2d_grad.detach() * means2d_grad.new_tensor([camera.width / 2, camera.height / 2])
        grad_norm = ndc.norm(dim=-1)[drawn].to(self.offset_grad_accum)
        offset_rows = (gaussians.anchor_ids * self.offsets.shape[1] + gaussians.child_ids)[drawn]
        self.offset_grad_accum.view(-1).index_add_(0, offset_rows, grad_norm)
        self.offset_denom.view(-1).index_add_(0, offset_rows, torch.ones_like(grad_norm))
        self.stat_views += 1

    @torch.no_grad()
    def sync_stats(self, all_reduce_sum: Callable[[Tensor], Any]) -> None:
        """Sum the statistics gathered since the last sync over all workers (multi-process training).

        Call on every worker, before ``densify``, with an in-place sum over workers (e.g.
        ``engine.distributed.all_reduce_sum_``). Only the increments since the last sync are reduced:
        reducing the whole accumulators would count the part carried over from earlier intervals
        (identical on every worker) once per worker.
        """
        for name in STAT_BUFFERS:
            total, synced = getattr(self, name), getattr(self, f"{name}_synced")
            increment = total - synced
            all_reduce_sum(increment)
            total.copy_(synced + increment)
            synced.copy_(total)

    def is_densify_step(self, step: int) -> bool:
        return (self.config.densify.enabled and self.densify_start < step <= self.densify_stop
                and step % self.densify_interval == 0)

    @torch.no_grad()
    def densify(self, step: int) -> dict[str, tuple[Tensor, int]]:
        """Grow and prune anchors when the schedule says so; see the module docstring for the result.

        Returns {group: (kept_rows [R] long, num_new)} for every anchor-row group, or {} when no shape
        changed (not a densification step, or nothing grown or pruned).
        """
        if not self.is_densify_step(step):
            return {}
        cfg = self.config.densify
        steps_elapsed = max(1, step - int(self.last_adjust_step))
        check_views = self.densify_interval * float(self.stat_views) / steps_elapsed * cfg.success_threshold
        grads, eligible = offset_gradients(self.offset_grad_accum, self.offset_denom, 0.5 * check_views)
        allow_finer = self.progressive_done(step)
        if allow_finer:
            self.extra_level += extra_level_increment(grads, eligible, self.levels, self.grid, cfg)
        threshold = self.config.octree.visible_threshold
        hides = self.keeps_ancestors and not cfg.draw_ancestors
        prune, judged = prune_decision(self.opacity_accum, self.anchor_denom, cfg.min_opacity, check_views)
        budget = cfg.budget(self.initial_anchors)
        room = None if budget is None else budget - int((self.drawn & ~prune).sum())
        grown = grow_anchors(self.anchors.detach(), self.levels, self.anchor_features.detach(),
                             self.offsets.detach(), self.log_scaling.detach(), grads, self.grid, cfg,
                             self.train_camera_centers, max(threshold, 0.0), allow_finer,
                             blocks=self.drawn if hides else None, limit=room)
        if hides:
            grown = self._draw_hidden_ancestors(grown)
        self.offset_grad_accum[eligible] = 0
        self.offset_denom[eligible] = 0
        new_drawn = torch.ones(grown.positions.shape[0], dtype=torch.bool, device=self.drawn.device)
        if self.keeps_ancestors:
            # an ancestor no kept anchor needs goes; close_ancestors revives the needed ones
            before = ~prune & self.drawn if hides else ~prune
            keep, grown = close_ancestors(self.anchors.detach(), self.levels, self.anchor_features.detach(),
                                          before, grown, self.grid)
            prune = ~keep
            added = grown.positions.shape[0] - len(new_drawn)  # the new parents, appended to grown
            new_drawn = torch.cat([new_drawn, new_drawn.new_full((added,), not hides)])
            if hides:
                self.drawn &= before  # the revived anchors: context only
        self.opacity_accum[judged] = 0
        self.anchor_denom[judged] = 0
        self.stat_views.zero_()
        self.last_adjust_step.fill_(step)

        num_new = grown.positions.shape[0]
        self.last_densify = {"grown": num_new, "pruned": int(prune.sum())}
        for level in range(self.grid.num_levels):
            self.last_densify[f"grown_level_{level}"] = int((grown.levels == level).sum())
        if num_new == 0 and not prune.any():
            self._mark_synced()
            return {}
        kept_rows = (~prune).nonzero().squeeze(1)
        self._resize(kept_rows, grown, new_drawn)
        self._mark_synced()
        if prune.any():
            self.log_scaling[:, 3:].clamp_(max=cfg.max_log_scale)
        return {name: (kept_rows, num_new) for name in ANCHOR_GROUPS}

    @torch.no_grad()
    def keep(self, rows: Tensor) -> dict[str, tuple[Tensor, int]]:
        """Keep only the anchors ``rows`` [R] long (ascending), with every per-anchor parameter and
        buffer; returns ``densify``'s {group: (kept_rows, 0)} for ``Optimizers.resize_group``."""
        empty = GrownAnchors(self.anchors.new_zeros(0, 3), self.levels.new_zeros(0),
                             self.anchor_features.new_zeros(0, self.anchor_features.shape[1]))
        self._resize(rows, empty, self.drawn.new_zeros(0))
        self._mark_synced()
        return {name: (rows, 0) for name in ANCHOR_GROUPS}

    def _mark_synced(self) -> None:
        """After an adjustment every worker holds the same statistics: the next sync starts here."""
        for name in STAT_BUFFERS:
            getattr(self, f"{name}_synced").copy_(getattr(self, name))

    def _draw_hidden_ancestors(self, grown: GrownAnchors) -> GrownAnchors:
        """Growth asks for an anchor where an ancestor kept for context sits: draw that ancestor (it
        keeps its training) instead of adding a second anchor to its cell; returns the rest of ``grown``."""
        hidden = (~self.drawn).nonzero().squeeze(1)
        if len(hidden) == 0 or grown.positions.shape[0] == 0:
            return grown
        hidden_keys = cell_keys(self.anchors.detach()[hidden], self.levels[hidden], self.grid)
        grown_keys = cell_keys(grown.positions, grown.levels, self.grid)
        self.drawn[hidden[rows_in(hidden_keys, grown_keys)]] = True
        fresh = ~rows_in(grown_keys, hidden_keys)
        return GrownAnchors(grown.positions[fresh], grown.levels[fresh], grown.features[fresh])

    def _resize(self, kept_rows: Tensor, grown, new_drawn: Tensor) -> None:
        """Swap every per-anchor parameter / buffer for ``cat([old[kept_rows], new rows])``;
        new_drawn [G] bool: which new rows are drawn."""
        num_new, k = grown.positions.shape[0], self.offsets.shape[1]
        voxel = self.grid.voxel_size / float(self.grid.fork) ** grown.levels.to(torch.float32)
        new_rows = {
            "anchors": grown.positions.to(self.anchors),
            "offsets": self.offsets.new_zeros(num_new, k, 3),
            "anchor_features": grown.features.to(self.anchor_features),
            "log_scaling": torch.log(voxel).to(self.log_scaling)[:, None].repeat(1, 6),
        }
        for attr, rows in new_rows.items():
            old = getattr(self, attr)
            setattr(self, attr, nn.Parameter(torch.cat([old.detach()[kept_rows], rows]),
                                             requires_grad=old.requires_grad))
        given = {"levels": grown.levels, "drawn": new_drawn}  # every other buffer starts at zero
        for name in ANCHOR_BUFFERS:
            old = getattr(self, name)
            rows = given[name].to(old) if name in given else old.new_zeros(num_new, *old.shape[1:])
            setattr(self, name, torch.cat([old[kept_rows], rows]))

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
        """Memory each anchor holds: its parameters, their two Adam moments, its buffers (level, eps,
        statistics) and its place in the culling chunks."""
        def row_bytes(tensor: Tensor) -> int:
            return math.prod(tensor.shape[1:]) * tensor.element_size()

        parameters = sum(row_bytes(getattr(self, attr)) for attr in ANCHOR_GROUPS.values())
        buffers = sum(row_bytes(getattr(self, name)) for name in ANCHOR_BUFFERS)
        chunks = 2 * torch.empty((), dtype=torch.long).element_size()  # order and chunk_of
        return {"parameters": parameters, "adam": 2 * parameters, "statistics": buffers, "culling": chunks,
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
