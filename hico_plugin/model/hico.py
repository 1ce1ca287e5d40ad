"""HiCoModel: the anchor field, the renderer and the losses, and what each training step renders.

Per view: ``field.select`` (LOD, Eq. 1, + frustum culling), ``field.decode`` (CLCA, Sec. 3.3, + neural Gaussian
MLPs), the renderer, then the losses (L1 + D-SSIM, DNGC once w(t) > 0, Sec. 3.4). The renderer is asked only for
what the step's loss components read, so before DNGC's t0 it composites RGB alone and allocates no geometry
buffer.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field as dataclass_field
from typing import Any, Literal

import torch
from torch import Tensor, nn

from hico_plugin.analysis.evidence import DatasetEvidence
from hico_plugin.cameras import Camera, Cameras
from hico_plugin.config import InstantiateConfig
from hico_plugin.engine.distributed import all_reduce_sum_
from hico_plugin.engine.optimizers import ParamGroupOptimizerConfig
from hico_plugin.engine.protocol import StepOutput, TrainBatch
from hico_plugin.engine.schedule import LRSchedule
from hico_plugin.errors import HicoError
from hico_plugin.field.decoder import NeuralGaussians
from hico_plugin.field.field import FieldConfig
from hico_plugin.field.lookup_stats import flat_metrics, summarise, view_lookup_sums
from hico_plugin.losses import LossConfig, Losses, default_losses
from hico_plugin.metrics import depth_abs_rel, lpips, normal_angular_error, psnr, ssim
from hico_plugin.metrics.colour import cc_psnr, nerfw_psnr
from hico_plugin.model.effects import (EFFECTS, RENAMED_EFFECTS, EffectInputs, choose_effects, data_background,
                                      parse_effects)
from hico_plugin.model.effects.environment import EnvironmentConfig
from hico_plugin.rasterizer import RenderOutputs
from hico_plugin.rasterizer.renderer import RendererConfig
from hico_plugin.strategy import STRATEGIES
from hico_plugin.strategy.octree import BUFFERS as OCTREE_STRATEGY_BUFFERS

EVAL_OUTPUTS = ("rgb", "alpha", "depth", "normal", "distance", "plane_depth", "depth_normal")


def default_optimizers() -> dict[str, ParamGroupOptimizerConfig]:
    """Adam schedule per parameter group (CityGS-X's settings, paper Sec. 4.1), then each built-in
    effect's groups as the effect sets them; decays run over max_steps."""
    lr = ParamGroupOptimizerConfig
    field_groups = {
        "anchor": lr(1.6e-4, 1.6e-6, scale_by_extent=True),
        "offset": lr(0.01, 1e-4, scale_by_extent=True),
        "anchor_feat": lr(0.0075),
        "scaling": lr(0.007),
        "mlp_opacity": lr(0.002, 2e-5),
        "mlp_cov": lr(0.004),
        "mlp_color": lr(0.008, 5e-5),
        "clca": lr(0.008, 5e-5),  # follows the colour MLP (paper Sec. 4.1)
        "appearance": lr(0.05, 5e-4),
        "background": lr(0.03, 3e-4),  # 3 numbers; Adam moves them <= lr a step: black to white in ~35
    }
    effect_groups = {group: lr for _, effect in EFFECTS.registered() for group, lr in effect().default_lrs().items()}
    return {**field_groups, **effect_groups}


ANCHORS_PER_SEED_POINT = 32
"""Anchors a run may end with per seed point, for the checkpoint size estimate (``checkpoint_bytes``)."""


@dataclass
class HiCoModelConfig(InstantiateConfig):
    """HiCo-GS: octree anchors + CLCA + neural Gaussians, rendered by a swappable rasterizer, trained
    with the photometric loss and DNGC."""

    field: FieldConfig = dataclass_field(default_factory=FieldConfig)
    """Anchor octree, LOD selection, context aggregation (CLCA), decoder and densification."""
    renderer: RendererConfig = dataclass_field(default_factory=RendererConfig)
    """Rasterizer backend and its options."""
    losses: dict[str, LossConfig] = dataclass_field(default_factory=default_losses)
    """Loss components by registered name: photometric (rgb), DNGC (dngc) and those of installed plug-ins."""
    effects: str = "auto"
    """Image-formation effects to simulate: "auto" turns on exactly those the dataset analysis finds
    (environment = a directional background where no point explains the photos, exposure = per-image colour
    transform, lod = octree levels from the distance spread); NAME=on|off forces one, e.g.
    "auto,environment=off" or "environment=on,exposure=off,lod=on"."""
    lod_rule: Literal["octree", "measured"] = "octree"
    """When ``auto`` turns the lod effect on. "octree": whenever the points' distance span gives two levels
    or more (Octree-GS; the paper's presets). "measured": only where the views stand at different
    distances and the run has 1,000 steps or more, where levels beat one flat level on test PSNR
    (hico-gs-lite; figures in benchmarks/RESULTS.md)."""
    environment: EnvironmentConfig = dataclass_field(default_factory=EnvironmentConfig)
    """Learned directional background composited behind the Gaussians (when the environment effect is on)."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Colour composited behind the Gaussians when the environment effect is off (where learned, its start
    unless background_start takes it from the data)."""
    background_start: Literal["data", "configured"] = "data"
    """Where the learned constant starts. "data": the median colour of the photo cells no reconstructed
    point explains (sky or plain walls) where the analysis finds them, else ``background``;
    "configured": ``background``. Over a constant far from the photos' backdrop the fresh, identical
    Gaussians are pulled transparent together and the model can fade out."""
    learn_background: bool = True
    """Learn that colour (parameter group "background"): with the environment off, the best constant
    behind the Gaussians, which also fits a plain backdrop they do not reach. Splatfacto trains over a
    random colour instead so the Gaussians cannot lean on it (nerfstudio's splatfacto.py)."""
    scale_schedules: bool = True
    """Scale the step-valued schedules (the field's densification and levels, DNGC's t0 and T) by
    max_steps / field.reference_steps, so a short run keeps the paper's proportions."""
    eval_lpips: Literal["vgg", "alex", "none"] = "vgg"
    """LPIPS backbone at evaluation ("vgg" as CityGS-X, "alex", or "none" to skip it)."""
    optimizers: dict[str, ParamGroupOptimizerConfig] = dataclass_field(default_factory=default_optimizers)
    """Adam learning-rate schedule per parameter group (groups of effects that are off are unused; a
    plug-in effect's groups not listed here train at the rates the effect sets)."""

    def validate(self) -> None:
        """A HicoError for a bad --model.effects or densification strategy, before the dataset is read
        (the trainer's validate)."""
        parse_effects(self.effects)
        STRATEGIES.get(self.field.densify.strategy)

    def checkpoint_bytes(self, num_points: int) -> int:
        """A generous size of a training checkpoint of this model grown from ``num_points`` seed points,
        known before the model is built (the free-space check runs first): per anchor its parameters
        (position 3, offsets 3K, feature d, scaling 6 floats) with Adam's two moments, and its per-anchor
        buffers (level, statistics and their synced copies: about 7 + 4K floats). Densification multiplies
        the anchors: city-block's 4,000 seed points end at 69.5k to 91k anchors (the README's CLCA
        table), about 23 per point; ANCHORS_PER_SEED_POINT leaves room above that."""
        k, d = self.field.decoder.num_offsets, self.field.feature_dim
        floats_per_anchor = 3 * (3 + 3 * k + d + 6) + 7 + 4 * k
        return 4 * floats_per_anchor * ANCHORS_PER_SEED_POINT * max(num_points, 1)

    def setup(self, dataset: Any = None, total_steps: int | None = None, **kwargs: Any) -> "HiCoModel":
        if dataset is None:
            raise HicoError("model: setup needs the dataset (sparse points and training cameras)")
        return HiCoModel(self, dataset, total_steps)


class HiCoModel(nn.Module):
    """The HiCo-GS model; implements the engine's ``TrainableModel`` protocol."""

    train_gt = ("mask",)
    """Ground truth a training step reads: the photo's mask. Depth and normal maps (generated scenes)
    score evaluations only, so training batches do not decode or hold them."""

    def __init__(self, config: HiCoModelConfig, dataset: Any, total_steps: int | None = None):
        super().__init__()
        self.config = config
        train_ids = torch.as_tensor(dataset.train_indices, dtype=torch.long)
        if len(train_ids) == 0:
            raise HicoError("dataset: the training split is empty")
        train_cameras = dataset.cameras
        self.train_slot = {int(i): slot for slot, i in enumerate(train_ids.tolist())}
        evidence = DatasetEvidence(dataset)  # measured on first use, shared by the analysis and the effects
        self.effect_choices, self.effects_report = choose_effects(config.effects, dataset, total_steps, config, evidence)
        for choice in self.effect_choices.values():
            print(f"effect  {choice.line()}")
        effects = {name: EFFECTS.get(name)() for name in self.effect_choices}
        field_config = config.field
        for name, effect in effects.items():
            field_config = effect.configure_field(field_config, self.effect_choices[name].on)
        # the effects that are on, in image-formation order
        self.active_effects = dict(sorted(((name, effect) for name, effect in effects.items()
                                           if self.effect_choices[name].on), key=lambda item: item[1].stage))
        # the one schedule scale, for the field's densification and levels and the losses' DNGC
        scale = (total_steps / config.field.reference_steps) if (config.scale_schedules and total_steps) else 1.0
        octree = field_config.octree
        self.field = field_config.setup(points=dataset.points,
                                        train_cameras=_subset(train_cameras, train_ids),
                                        num_train_cameras=len(train_ids), schedule_scale=scale,
                                        distances=dataset.camera_distance_range(octree.dist_ratio, octree.max_points))
        self.strategy = field_config.densify.setup(field=self.field, schedule_scale=scale)
        memory = self.bytes_per_anchor()
        print(f"field: {self.field.num_anchors:,} anchors at {memory['total']} bytes each (parameters "
              f"{memory['parameters']}, Adam moments {memory['adam']}, statistics {memory['statistics']}, "
              f"culling {memory['culling']})")
        self.renderer = config.renderer.setup()
        self.losses = Losses.setup(config.losses, schedule_scale=scale)
        self.spatial_lr_scale = float(dataset.cameras_extent())
        learned = config.learn_background and not self.composites_behind()
        start = data_background(self.effect_choices, self.effects_report, evidence) \
            if learned and config.background_start == "data" else None
        background = torch.tensor(config.background if start is None else start, dtype=torch.float32)
        if start is not None:
            print(f"background: a learned constant from ({', '.join(f'{c:.2f}' for c in start)}), the median colour "
                  f"of the photo cells no reconstructed point explains")
        if learned:
            self.background = nn.Parameter(background)
        else:  # unused behind a composited environment, or kept as configured
            self.register_buffer("background", background)
        inputs = EffectInputs(dataset, train_ids, self.effects_report, config, evidence)
        built = {name: effect.build(inputs) for name, effect in self.active_effects.items()}
        self.effects = nn.ModuleDict({name: module for name, module in built.items() if module is not None})
        self.register_load_state_dict_pre_hook(_effect_keys_of_older_checkpoints)
        self.last_num_gaussians = 0

    # ----- rendering ------------------------------------------------------------------------------

    def appearance_camera(self, camera: Camera) -> Camera:
        """The camera with its index mapped to the training slot of the appearance embedding
        (-1 for views that are not training views)."""
        slot = self.train_slot.get(camera.index, -1)
        return Camera(camera.viewmat, camera.K, camera.width, camera.height, slot)

    def required_outputs(self, step: int) -> set[str]:
        """Render outputs a training step needs: the losses' union (rgb alone before DNGC starts)."""
        return {"rgb"} | self.losses.required_outputs(step)

    def render(self, camera: Camera, outputs: tuple[str, ...] | set[str] = ("rgb",), step: int | None = None,
               context_enabled: bool = True, level_range: tuple[int, int] | None = None,
               distance_scale: float = 1.0) -> tuple[RenderOutputs, NeuralGaussians]:
        """Render ``camera`` (step None = evaluation: every level active); ``level_range`` keeps only
        anchors of those octree levels (inclusive) and ``distance_scale`` scales the LOD distance
        (the viewer's LOD controls)."""
        device = self.background.device
        camera = self.appearance_camera(camera.to(device))
        visible_ids = self.field.select(camera, step, distance_scale)
        if level_range is not None:
            levels = self.field.levels[visible_ids]
            visible_ids = visible_ids[(levels >= level_range[0]) & (levels <= level_range[1])]
        gaussians = self.field.decode(camera, visible_ids, context_enabled=context_enabled)
        # An effect that composites what lies behind the Gaussians does it from alpha; otherwise the
        # rasterizer composites the constant background.
        behind = self.composites_behind()
        wanted = set(outputs) | ({"alpha"} if behind and "rgb" in outputs else set())
        out = self.renderer(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                            gaussians.colors, camera, outputs=tuple(sorted(wanted)),
                            background=None if behind else self.background)
        if out.rgb is not None:
            out.rgb = self.apply_effects(out, camera)
        return out, gaussians

    def composites_behind(self) -> bool:
        """Whether an effect that is on composites what lies behind the Gaussians (the environment)."""
        return any(effect.replaces_background for effect in self.active_effects.values())

    def apply_effects(self, out: RenderOutputs, camera: Camera) -> Tensor:
        """``out.rgb`` (rendered without background when an effect composites it) with every effect
        that is on applied in image-formation order: [H,W,3]."""
        for name, effect in self.active_effects.items():
            out.rgb = effect.apply(self.effects[name] if name in self.effects else None, out, camera)
        return out.rgb

    # ----- rendering for people (viewer, hico-eval, hico-render; see hico_plugin.visualization) -----

    @torch.no_grad()
    def render_for_display(self, camera: Camera, options: Any) -> dict[str, Tensor]:
        """The render outputs ``options.required_outputs`` names; "level" is the alpha-normalised
        octree level of the drawn Gaussians, composited as a colour channel."""
        wanted = set(options.required_outputs) - {"level"}
        out, gaussians = self.render(camera, wanted or {"alpha"}, None, options.clca_enabled,
                                     options.level_range, options.distance_scale)
        images = out.images()
        if "level" in options.required_outputs:
            levels = self.field.levels[gaussians.anchor_ids].to(gaussians.means)[:, None]
            level_out = self.renderer(gaussians.means, gaussians.quats, gaussians.scales,
                                      gaussians.opacities, levels, self.appearance_camera(camera.to(levels.device)),
                                      outputs=("rgb", "alpha"))
            images["level"] = level_out.rgb / level_out.alpha.clamp_min(1e-6)
            images.setdefault("alpha", level_out.alpha)
        return images

    def viewer_anchors(self) -> tuple[Tensor, Tensor]:
        return self.field.anchor_points()

    def viewer_parent_found(self) -> Tensor:
        """[A] bool aligned with viewer_anchors: the "CLCA parent found" overlay."""
        return self.field.parent_found()

    # ----- TrainableModel --------------------------------------------------------------------------

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        groups = self.field.param_groups()
        for name, module in self.effects.items():
            groups.update(self.active_effects[name].param_groups(module))
        if isinstance(self.background, nn.Parameter):
            groups["background"] = [self.background]
        return groups

    def renamed_param_groups(self) -> dict[str, str]:
        """Parameter groups of older checkpoints under their old names -> today's (the trainer's resume)."""
        return dict(RENAMED_EFFECTS)

    def lr_schedules(self, max_steps: int) -> dict[str, LRSchedule]:
        groups = self.param_groups()
        rates = {group: rate for effect in self.active_effects.values() for group, rate in effect.default_lrs().items()}
        rates.update({RENAMED_EFFECTS.get(group, group): rate for group, rate in self.config.optimizers.items()})
        missing = sorted(set(groups) - set(rates))
        if missing:
            raise HicoError(f"model.optimizers: no entry for parameter group(s) {', '.join(missing)}")
        schedules = {name: rates[name].schedule(max_steps, self.spatial_lr_scale) for name in groups}
        if not self.field.config.train_anchor_positions:
            schedules["anchor"] = LRSchedule(0.0, None, max_steps)
        return schedules

    def train_step(self, batch: TrainBatch, step: int) -> StepOutput:
        wanted = self.required_outputs(step)
        total = None
        term_sums: dict[str, float] = {}
        views = []
        psnrs = []
        masks = batch.gt.get("mask")
        for i, (camera, image) in enumerate(zip(batch.cameras, batch.images)):
            out, gaussians = self.render(camera, wanted, step)
            if out.means2d is not None and out.means2d.requires_grad:
                out.means2d.retain_grad()
            if masks is not None:  # pixels outside the photo's mask teach nothing (splatfacto's rule)
                keep = masks[i].to(image.dtype)
                image = image * keep
                out = dataclasses.replace(out, rgb=out.rgb * keep)
            terms = self.losses(out, image, step)
            view_loss = sum(terms.values())
            total = view_loss if total is None else total + view_loss
            for name, value in terms.items():
                term_sums[name] = term_sums.get(name, 0.0) + float(value.detach())
            with torch.no_grad():
                psnrs.append(float(psnr(out.rgb.clamp(0, 1), image)))
            views.append((camera, gaussians, out))
        count = len(views)
        metrics: dict[str, float | Tensor] = {f"loss/{k}": v / count for k, v in term_sums.items()}
        metrics["psnr"] = sum(psnrs) / count
        metrics.update(self.losses.metrics(step))
        self.last_num_gaussians = len(views[-1][1])
        return StepOutput(loss=total / count, metrics=metrics, extras={"views": views, "batch_size": count})

    def after_backward(self, step: int, output: StepOutput) -> None:
        batch_size = output.extras["batch_size"]
        for camera, gaussians, out in output.extras["views"]:
            grad = out.means2d.grad
            if grad is None:
                continue
            # The loss is a batch mean; the statistic is defined on one view's loss.
            self.strategy.step_post_backward(self.field, gaussians, grad * batch_size, out.radii, camera, step)

    def after_optimizer_step(self, step: int, optimizers: Any) -> None:
        self.field.after_update()
        if not self.strategy.is_adjust_step(step):
            return
        # Every worker must grow and prune identically: sum the statistics over workers first.
        self.strategy.sync(all_reduce_sum_)
        resized = self.strategy.step_post_update(self.field, step)
        groups = self.field.param_groups()
        for group, (kept_rows, num_new) in resized.items():
            optimizers.resize_group(group, groups[group], kept_rows, num_new)

    @torch.no_grad()
    def keep_anchors(self, rows: Tensor) -> None:
        """Keep only the anchors ``rows`` [R] long (ascending), with the strategy's statistics of them
        (a model of part of a scene; the optimizers, if any, are the caller's to resize)."""
        self.field.keep(rows)
        self.strategy.keep(rows)

    def bytes_per_anchor(self) -> dict[str, int]:
        """Memory each anchor holds: the field's (parameters, Adam moments, buffers, culling) and the
        strategy's statistics; the buffers count as statistics."""
        memory, strategy = self.field.bytes_per_anchor(), self.strategy.bytes_per_anchor()
        buffers = memory.pop("buffers")
        return {**memory, "statistics": buffers + strategy, "total": memory["total"] + strategy}

    @torch.no_grad()
    def eval_view(self, camera: Camera, image: Tensor, gt: dict[str, Tensor]) -> dict[str, Any]:
        start = time.perf_counter()
        self.render(camera, ("rgb",))  # timed alone: the fps a viewer would see
        render_seconds = time.perf_counter() - start
        out, gaussians = self.render(camera, EVAL_OUTPUTS)
        rgb = out.rgb.clamp(0, 1)
        image = image.to(rgb)
        # "psnr" (the headline) is raw; the colour-corrected figures discount the test photo's own
        # exposure, which no model can know (metrics/colour.py).
        results: dict[str, Any] = {"psnr": float(psnr(rgb, image)), "psnr_cc": float(cc_psnr(rgb, image)),
                                   "psnr_nerfw": float(nerfw_psnr(rgb, image)), "ssim": float(ssim(rgb, image)),
                                   "render_seconds": render_seconds, "num_gaussians": float(len(gaussians))}
        if self.config.eval_lpips != "none":
            value = lpips(rgb, image, net=self.config.eval_lpips)
            results["lpips"] = None if value is None else float(value)
        if gt.get("depth") is not None:
            results["depth_abs_rel"] = _or_none(lambda: depth_abs_rel(out.plane_depth, gt["depth"].to(rgb)))
        if gt.get("normal") is not None:
            err = _or_none(lambda: normal_angular_error(out.normal, gt["normal"].to(rgb)))
            results["normal_error_deg"] = None if err is None else err.mean_deg
            results["normal_error_median_deg"] = None if err is None else err.median_deg
        # How CLCA's lookup fares on this view, per level; averaged over views by evaluate().
        results.update(flat_metrics(summarise(view_lookup_sums(self.field, camera))))
        return results

    def run_documents(self) -> dict[str, Any]:
        """Files the trainer writes into the run dir: the dataset's effects analysis and the choices."""
        document = {"choices": {name: {"on": c.on, "reason": c.reason} for name, c in self.effect_choices.items()}}
        if self.effects_report is not None:
            document["analysis"] = self.effects_report.to_json()
        return {"effects.json": document}

    def eval_documents(self) -> dict[str, Any]:
        """Non-metric entries of eval.json: which effects were simulated, and why."""
        return {"effects": {name: {"on": c.on, "reason": c.reason} for name, c in self.effect_choices.items()},
                "headline_psnr": "psnr (raw); psnr_cc = per-view affine colour fit, psnr_nerfw = fit left half, score right"}

    def stats(self) -> dict[str, float]:
        out = self.field.stats()
        out["num_gaussians"] = float(self.last_num_gaussians)
        for name, effect in self.active_effects.items():
            for key, value in effect.cost(self.effects[name] if name in self.effects else None).items():
                out[f"effect_{key}/{name}"] = value
        return out


def _effect_keys_of_older_checkpoints(module: nn.Module, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
    """Checkpoints written before effects became components held the environment (then "sky") and the
    exposure transform as ``sky.*`` and ``colour.*``, later the environment as ``effects.sky.*``: load
    them under ``effects.environment.*`` and ``effects.exposure.*``."""
    renamed = [(f"effects.{old}.", f"effects.{new}.") for old, new in RENAMED_EFFECTS.items()]
    for old, new in (("sky.", "effects.environment."), ("colour.", "effects.exposure."), *renamed):
        for key in [k for k in state_dict if k.startswith(prefix + old)]:
            state_dict[prefix + new + key[len(prefix + old):]] = state_dict.pop(key)
    # Checkpoints written before densification became a strategy held its statistics in the field.
    for name in OCTREE_STRATEGY_BUFFERS:
        if prefix + "field." + name in state_dict:
            state_dict[prefix + "strategy." + name] = state_dict.pop(prefix + "field." + name)


def _subset(cameras: Cameras, ids: Tensor) -> Cameras:
    return Cameras(cameras.viewmats[ids], cameras.Ks[ids], cameras.widths[ids], cameras.heights[ids])


def _or_none(fn):
    """A geometry metric, or None when the view has no pixel both sides cover."""
    try:
        return fn()
    except HicoError:
        return None
