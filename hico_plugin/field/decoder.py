"""Neural Gaussian decoder (Scaffold-GS / Octree-GS, paper Sec. 3.1): K Gaussians per visible anchor from
shared MLPs conditioned on the anchor feature and the view."""

from __future__ import annotations

import math

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from hico_plugin.config import InstantiateConfig
from hico_plugin.field.gather import repeat_rows, take_rows


@dataclass
class NeuralGaussians:
    """The Gaussians decoded for one view (only those with opacity > 0), plus densification inputs.

    means [M,3]; quats [M,4] (w,x,y,z, unit); scales [M,3] (linear); opacities [M] in (0,1];
    colors [M,3] in (0,1); anchor_ids [M] long (index into the field's anchors);
    child_ids [M] long (which of the anchor's K offsets).
    visible_ids [V] long: the anchors decoded; raw_opacities [V,K]: tanh opacities of all K children
    of each visible anchor (detached; the opacity statistic); keep_mask [V,K] bool: opacity > 0.
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    anchor_ids: Tensor
    child_ids: Tensor
    visible_ids: Tensor
    raw_opacities: Tensor
    keep_mask: Tensor

    def __len__(self) -> int:
        return self.means.shape[0]


@dataclass
class DecoderConfig(InstantiateConfig):
    """Shared MLPs turning an anchor's (enhanced) feature and the view into K neural Gaussians."""

    num_offsets: int = 5
    """K, neural Gaussians per anchor (the paper's default 5; CityGS-X's command-line default is 10)."""
    hidden_dim: int = 32
    """Hidden width of the opacity / covariance / colour MLPs."""
    add_distance: bool = False
    """Append the camera distance to the MLP inputs (base default off; Octree-GS suggests on for
    scenes spanning many scales)."""
    add_level: bool = False
    """Append the anchor's octree level to the MLP inputs."""
    appearance_dim: int = 0
    """Per-training-camera appearance embedding size fed to the colour MLP; 0 = off (CityGS-X's
    default). Cameras without a training index (test / viewer, index -1 or out of range) use the mean
    of the training embeddings, the neutral appearance."""
    chunk_size: int = 65_536
    """Anchors decoded per chunk, bounding the MLPs' intermediate memory on large scenes."""

    def setup(self, feature_dim: int = 32, num_train_cameras: int = 0, **kwargs) -> "GaussianDecoder":
        return GaussianDecoder(self, feature_dim, num_train_cameras)


INITIAL_OPACITY = 0.1
"""Mean opacity of a fresh decoder's children (3DGS's initial opacity)."""


def _mlp(in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, out_dim))


class GaussianDecoder(nn.Module):
    """Opacity (tanh), covariance (7 per child) and colour (sigmoid) MLPs on [f_hat; view dir; ...]."""

    def __init__(self, config: DecoderConfig, feature_dim: int, num_train_cameras: int):
        super().__init__()
        self.config = config
        k, hidden = config.num_offsets, config.hidden_dim
        in_dim = feature_dim + 3 + int(config.add_distance) + int(config.add_level)
        self.mlp_opacity = _mlp(in_dim, hidden, k)
        # Children start at opacity tanh(bias) ~ 0.1 on average, the opacity 3DGS gives every new
        # Gaussian (Kerbl et al. 2023). Started around 0, a few early Adam steps can push every
        # child below 0: then none is drawn, none gets a gradient, and the scene never comes back.
        with torch.no_grad():
            self.mlp_opacity[-1].bias.fill_(math.atanh(INITIAL_OPACITY))
        self.mlp_cov = _mlp(in_dim, hidden, 7 * k)
        self.mlp_color = _mlp(in_dim + config.appearance_dim, hidden, 3 * k)
        self.appearance = (nn.Embedding(max(1, num_train_cameras), config.appearance_dim)
                           if config.appearance_dim > 0 else None)

    def appearance_code(self, camera_index: int, like: Tensor) -> Tensor:
        """[appearance_dim] embedding of a training camera, or the mean embedding for any other."""
        table = self.appearance.weight
        if 0 <= camera_index < table.shape[0]:
            return table[camera_index]
        return table.mean(0)

    def forward(self, features: Tensor, positions: Tensor, offsets: Tensor, scalings: Tensor,
                levels: Tensor, camera_center: Tensor, camera_index: int, anchor_ids: Tensor
                ) -> NeuralGaussians:
        """Decode visible anchors.

        features [V,d] (f_hat); positions [V,3]; offsets [V,K,3]; scalings [V,6] (linear,
        = exp of the log-scaling parameter); levels [V]; camera_center [3], or [V,3] one viewpoint
        per anchor; anchor_ids [V] long (the anchors' ids in the field, carried into the output).
        """
        size = max(1, self.config.chunk_size)
        if features.shape[0] <= size:  # the usual view: a slice would add a copy to every input's gradient
            return self._decode(features, positions, offsets, scalings, levels, camera_center, camera_index,
                                anchor_ids)
        per_anchor = camera_center.dim() == 2
        parts = []
        for start in range(0, features.shape[0], size):  # chunks of anchors, not a per-anchor loop
            sl = slice(start, start + size)
            parts.append(self._decode(features[sl], positions[sl], offsets[sl], scalings[sl], levels[sl],
                                      camera_center[sl] if per_anchor else camera_center, camera_index,
                                      anchor_ids[sl]))
        names = NeuralGaussians.__dataclass_fields__
        return NeuralGaussians(**{name: torch.cat([getattr(p, name) for p in parts]) for name in names})

    def _decode(self, features, positions, offsets, scalings, levels, camera_center, camera_index,
                anchor_ids) -> NeuralGaussians:
        k = self.config.num_offsets
        to_anchor = positions - camera_center
        dist = to_anchor.norm(dim=-1, keepdim=True)
        inputs = [features, to_anchor / dist.clamp_min(1e-12)]
        if self.config.add_distance:
            inputs.append(dist)
        if self.config.add_level:
            inputs.append(levels[:, None].to(features.dtype))
        inputs = torch.cat(inputs, dim=1)

        opacity = torch.tanh(self.mlp_opacity(inputs))  # [V,K]
        keep = opacity > 0
        anchor_rows, child_ids = keep.nonzero(as_tuple=True)
        child_rows = anchor_rows * k + child_ids  # rows of the [V*K, ...] per-child outputs

        color_in = inputs
        if self.appearance is not None:
            code = self.appearance_code(camera_index, inputs)
            color_in = torch.cat([inputs, code.expand(inputs.shape[0], -1)], dim=1)
        # Only the kept children are needed downstream: evaluate the MLPs per anchor, then gather the
        # kept rows (each once: take_rows) and each kept child's anchor (repeat_rows: anchor_rows
        # ascends, so the backward sums each anchor's children in parallel).
        colors = take_rows(torch.sigmoid(self.mlp_color(color_in)).view(-1, 3), child_rows)
        cov = take_rows(self.mlp_cov(inputs).view(-1, 7), child_rows)
        # split, not two slices: its backward writes each part's gradient once (one cat) where each
        # slice's would zero-fill a whole [M, 6] / [M, 7] table and the two be added
        offset_scale, gaussian_scale = repeat_rows(scalings, anchor_rows).split(3, dim=1)
        cov_scale, cov_rotation = cov.split([3, 4], dim=1)
        scales = gaussian_scale * torch.sigmoid(cov_scale)
        quats = F.normalize(cov_rotation, dim=-1)
        means = (repeat_rows(positions, anchor_rows)
                 + take_rows(offsets.reshape(-1, 3), child_rows) * offset_scale)
        return NeuralGaussians(
            means=means, quats=quats, scales=scales, opacities=take_rows(opacity.view(-1), child_rows),
            colors=colors, anchor_ids=anchor_ids[anchor_rows], child_ids=child_ids,
            visible_ids=anchor_ids, raw_opacities=opacity.detach(), keep_mask=keep)
