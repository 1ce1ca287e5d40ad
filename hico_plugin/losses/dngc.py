"""Depth-Normal Geometric Consistency (HiCo-GS Sec. 3.4): L_nc, edge-aware L_ns / L_ds, warmup w(t).

L = ... + w(t) (lambda_nc L_nc + lambda_ns L_ns + lambda_ds L_ds), w(t) = clamp((t - t0) / T, 0, 1). Where the
paper is silent: alpha (L_nc's weight) and RGB (edge weights) are detached, so transparency or sharper edges
cannot lower it; |grad I| is the RGB mean of absolute forward differences; L_nc skips pixels of undefined n_r or
n_d, and L_ns counts a difference only between two defined n_r (no silhouette penalty); L_ns reads unit n_r (its
length is alpha); L_ns and L_ds are spatial means; d stays in scene units, so lambda_ds is scale-dependent.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hico_plugin.errors import HicoError
from hico_plugin.losses import dngc_fused
from hico_plugin.losses.base import LOSSES, LossConfig, require_images
from hico_plugin.rasterizer.base import RenderOutputs
from hico_plugin.rasterizer.geometry import NORMAL_EPS

KERNELS = ("auto", "fused", "torch")
"""Values of ``DNGCLossConfig.kernel``."""


def warmup_weight(step: int, start_step: int, warmup_steps: int) -> float:
    """w(t) = clamp((t - t0) / T, 0, 1); T = 0 is a hard switch at t0 (w = 1 for t > t0)."""
    if warmup_steps <= 0:
        return 1.0 if step > start_step else 0.0
    return min(max((step - start_step) / warmup_steps, 0.0), 1.0)


def _unit(vectors: Tensor) -> tuple[Tensor, Tensor]:
    """Unit vectors and the mask where they are defined: [..., 3] -> ([..., 3], [...] bool).

    Undefined vectors are replaced by a constant before dividing, so no NaN/inf enters the graph
    (a masked 0 * NaN would still poison the gradient).
    """
    defined = vectors.detach().norm(dim=-1, keepdim=True) > NORMAL_EPS
    safe = torch.where(defined, vectors, torch.ones_like(vectors))
    return safe / safe.norm(dim=-1, keepdim=True), defined[..., 0]


def normal_consistency_loss(normal: Tensor, depth_normal: Tensor, alpha: Tensor) -> Tensor:
    """L_nc = sum_p alpha ||n_r_hat - n_d_hat||_1 / sum_p alpha over pixels where both normals exist.

    normal (n_r), depth_normal (n_d): [..., H, W, 3]; alpha: [..., H, W, 1] (detached here).
    Returns 0 (with zero, finite gradients) when no pixel has weight.
    """
    unit_rendered, rendered_ok = _unit(normal)
    unit_depth, depth_ok = _unit(depth_normal)
    weight = alpha.detach()[..., 0] * (rendered_ok & depth_ok)
    per_pixel = (unit_rendered - unit_depth).abs().sum(dim=-1)
    return (weight * per_pixel).sum() / weight.sum().clamp_min(1e-8)


def edge_weights(rgb: Tensor, beta: float = 10.0) -> tuple[Tensor, Tensor]:
    """w = exp(-beta |grad I|) from forward differences of the (detached) image, averaged over channels.

    rgb: [..., H, W, C] -> (w_x [..., H, W-1], w_y [..., H-1, W]).
    """
    image = rgb.detach()
    grad_x = (image[..., :, 1:, :] - image[..., :, :-1, :]).abs().mean(dim=-1)
    grad_y = (image[..., 1:, :, :] - image[..., :-1, :, :]).abs().mean(dim=-1)
    return torch.exp(-beta * grad_x), torch.exp(-beta * grad_y)


def edge_aware_smoothness(values: Tensor, weight_x: Tensor, weight_y: Tensor, valid: Tensor | None = None) -> Tensor:
    """mean(w_x |grad_x v|) + mean(w_y |grad_y v|), the means over all difference positions and channels.

    values: [..., H, W, K]; weight_x: [..., H, W-1]; weight_y: [..., H-1, W]; valid: optional
    [..., H, W] bool -- a difference counts only when both its pixels are valid.
    """
    diff_x = (values[..., :, 1:, :] - values[..., :, :-1, :]).abs().mean(dim=-1) * weight_x
    diff_y = (values[..., 1:, :, :] - values[..., :-1, :, :]).abs().mean(dim=-1) * weight_y
    if valid is not None:
        diff_x = diff_x * (valid[..., :, 1:] & valid[..., :, :-1])
        diff_y = diff_y * (valid[..., 1:, :] & valid[..., :-1, :])
    # An image 1 pixel wide or high has no differences along that axis: contributes 0, not NaN.
    mean_x = diff_x.sum() / max(diff_x.numel(), 1)
    mean_y = diff_y.sum() / max(diff_y.numel(), 1)
    return mean_x + mean_y


def dngc_losses(
    rgb: Tensor, alpha: Tensor, normal: Tensor, depth_normal: Tensor, distance: Tensor, beta: float = 10.0
) -> dict[str, Tensor]:
    """The unweighted DNGC terms {"nc": L_nc, "ns": L_ns, "ds": L_ds}.

    rgb: [..., H, W, 3] rendered image; alpha: [..., H, W, 1]; normal: [..., H, W, 3] n_r (camera
    coordinates, facing the camera); depth_normal: [..., H, W, 3] n_d; distance: [..., H, W, 1] d.
    """
    weight_x, weight_y = edge_weights(rgb, beta)
    unit_rendered, rendered_ok = _unit(normal)
    return {
        "nc": normal_consistency_loss(normal, depth_normal, alpha),
        "ns": edge_aware_smoothness(unit_rendered, weight_x, weight_y, rendered_ok),
        "ds": edge_aware_smoothness(distance, weight_x, weight_y),
    }


class DNGCLoss:
    """``dngc_nc``, ``dngc_ns``, ``dngc_ds``: each lambda * w(t) * term; nothing before t0."""

    OUTPUTS = frozenset({"rgb", "alpha", "normal", "depth_normal", "distance"})

    def __init__(self, config: "DNGCLossConfig", start_step: int, warmup_steps: int):
        self.config = config
        self.start_step = start_step  # t0 and T of this run (the config's, scaled to its length)
        self.warmup_steps = warmup_steps

    def warmup(self, step: int) -> float:
        return warmup_weight(step, self.start_step, self.warmup_steps)

    def metrics(self, step: int) -> dict[str, float]:
        return {"dngc_weight": self.warmup(step)}

    def required_outputs(self, step: int) -> set[str]:
        return set(self.OUTPUTS) if self.warmup(step) > 0 else set()

    def terms(self, *images: Tensor) -> dict[str, Tensor]:
        """``dngc_losses(rgb, alpha, normal, depth_normal, distance, edge_beta)``, by the fused kernel when
        ``kernel`` allows it, it takes these images (CPU, float32/float64) and it is built."""
        use_fused = (self.config.kernel != "torch" and dngc_fused.dngc_fused_accepts(*images)
                     and dngc_fused.dngc_fused_available())
        return (dngc_fused.dngc_terms_fused if use_fused else dngc_losses)(*images, self.config.edge_beta)

    def __call__(self, outputs: RenderOutputs, target: Tensor, step: int) -> dict[str, Tensor]:
        ramp = self.warmup(step)
        if ramp <= 0:
            return {}
        images = require_images(outputs, set(self.OUTPUTS), "dngc")
        terms = self.terms(images["rgb"], images["alpha"], images["normal"], images["depth_normal"], images["distance"])
        lambdas = {"nc": self.config.lambda_nc, "ns": self.config.lambda_ns, "ds": self.config.lambda_ds}
        return {f"dngc_{name}": ramp * lambdas[name] * value for name, value in terms.items() if lambdas[name] != 0}


@LOSSES.register("dngc")
@dataclass
class DNGCLossConfig(LossConfig):
    """Depth-normal geometric consistency: normal consistency + edge-aware normal / distance smoothness."""

    enabled: bool = True
    """Add the DNGC terms (off = the octree-anchor baseline)."""
    lambda_nc: float = 0.05
    """Weight of L_nc, the alpha-weighted L1 between unit n_r and unit n_d."""
    lambda_ns: float = 0.01
    """Weight of L_ns, the edge-aware smoothness of the rendered normal n_r."""
    lambda_ds: float = 0.01
    """Weight of L_ds, the edge-aware smoothness of the plane distance d (scene units)."""
    edge_beta: float = 10.0
    """beta in the edge weight exp(-beta |grad I|) on the rendered RGB."""
    start_step: int = 10_000
    """t0: the step after which geometry is rendered and DNGC ramps in (CityGS-X's switch, same counter
    as the trainer), in reference steps (scaled with the run's length, like every schedule)."""
    warmup_steps: int = 10_000
    """T: steps of the linear ramp from 0 to full weight after t0 (0 = switch on at once), in reference
    steps."""
    kernel: str = "auto"
    """How the terms are computed: "auto" (the fused C++ kernel, built on first use, for CPU float32/float64
    renders when it builds, else torch), "fused" (the same, and an error at setup when it cannot be built)
    or "torch" (the reference torch ops, any device)."""

    def setup(self, schedule_scale: float = 1.0, **kwargs) -> DNGCLoss:
        for name in ("lambda_nc", "lambda_ns", "lambda_ds", "edge_beta"):
            if getattr(self, name) < 0:
                raise HicoError(f"losses.dngc.{name} must be >= 0, got {getattr(self, name)}")
        if self.start_step < 0 or self.warmup_steps < 0:
            raise HicoError("losses.dngc.start_step and losses.dngc.warmup_steps must be >= 0")
        if self.kernel not in KERNELS:
            raise HicoError(f"losses.dngc.kernel must be one of {list(KERNELS)}, got {self.kernel!r}")
        if self.kernel == "fused" and not dngc_fused.dngc_fused_available():
            raise HicoError(f"losses.dngc.kernel='fused' but the fused CPU DNGC kernel could not be built "
                            f"({dngc_fused.KERNEL.error}); install a C++ compiler or use 'auto' or 'torch'")
        return DNGCLoss(self, int(round(self.start_step * schedule_scale)),
                        int(round(self.warmup_steps * schedule_scale)))
