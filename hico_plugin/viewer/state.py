"""What the viewer reads from the training side, and the adapter that provides it from a run.

``ViewableModel``: ``render_for_display(camera, options) -> Mapping[str, Tensor]``, at least
``options.required_outputs`` in RenderOutputs names and shapes, honouring ``level_range``, ``distance_scale`` and
``clca_enabled``, under ``torch.no_grad()`` with the render lock held; ``viewer_anchors()`` -> positions [A, 3],
levels [A]; optional ``viewer_parent_found()`` -> [A] bool. ``ViewerState``: the rest (``RunViewerState``). The
viewer holds ``render_lock`` per render and, while training runs unpaused, not again before ``step`` advances.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ContextManager, Mapping, Protocol, runtime_checkable

import cv2
import numpy as np
import torch
from torch import Tensor

from hico_plugin.cameras import Camera, Cameras
from hico_plugin.data.transform import SceneTransform
from hico_plugin.visualization.options import RenderOptions
from hico_plugin.visualization.visualize import visualize

RenderFn = Callable[[Camera, RenderOptions], np.ndarray]
"""render_fn(camera, options) -> uint8 [H, W, 3] picture of ``options.output`` seen by ``camera``."""


@runtime_checkable
class ViewableModel(Protocol):
    def render_for_display(self, camera: Camera, options: RenderOptions) -> Mapping[str, Tensor]: ...

    def viewer_anchors(self) -> tuple[Tensor, Tensor]: ...


@dataclass
class TrainingCameras:
    """The training views the viewer draws as frustums."""

    cameras: Cameras
    """C cameras (already capped in number by whoever built this)."""
    indices: list[int]
    """Dataset index of each camera (frustum names; the key of ``ViewerState.thumbnail``)."""


class ViewerState(Protocol):
    """What the viewer reads and controls. All methods may be called from the viewer's threads.

    stats() keys the viewer knows how to lay out (others are listed as they are): ``step``,
    ``it_per_s``, ``loss`` and ``loss/<term>``, ``psnr`` (train), ``eval/psnr`` (last evaluation),
    ``num_anchors``, ``num_gaussians``, ``dngc_weight``. Anchors per level are counted by the viewer
    from ``anchors()``.
    """

    render_lock: ContextManager[Any]
    """Held by the viewer for one render; the trainer holds it for each training step.

    Optional members the camera-path panel reads when present: ``scene_transform`` (SceneTransform
    from the dataset's source frame to the viewer's; paths are saved in the source frame, identity
    without it) and ``camera_path_dir`` (where paths are saved and loaded; without it saving is off)."""

    @property
    def is_training(self) -> bool:
        """True while a trainer runs (enables pause / checkpoint controls)."""
        ...

    @property
    def is_paused(self) -> bool: ...

    @property
    def step(self) -> int:
        """Completed training steps (advances after each step)."""
        ...

    def set_paused(self, paused: bool) -> None: ...

    def request_checkpoint(self) -> None:
        """Ask the trainer to save a checkpoint after the current step."""
        ...

    def training_cameras(self, max_cameras: int) -> TrainingCameras:
        """At most ``max_cameras`` training cameras, evenly chosen."""
        ...

    def thumbnail(self, index: int, size: int) -> np.ndarray | None:
        """uint8 [h, w, 3] image of dataset view ``index`` with longer side ``size`` (None: no image).
        Called from the viewer's thread after start-up, one view at a time."""
        ...

    def anchors(self) -> tuple[Tensor, Tensor]:
        """Anchor positions [A, 3] and octree levels [A]."""
        ...

    def stats(self) -> dict[str, Any]: ...

    def history(self) -> dict[str, np.ndarray]:
        """``"step"`` [T] plus equally long series (``"loss"``, ``"psnr"``) for the plot."""
        ...


def model_render_fn(model: ViewableModel) -> RenderFn:
    """The render_fn of a ViewableModel: its outputs for the camera, drawn by ``visualize``."""

    def render(camera: Camera, options: RenderOptions) -> np.ndarray:
        with torch.no_grad():
            outputs = model.render_for_display(camera, options)
        return visualize(outputs, options)

    return render


def evenly_spaced(count: int, cap: int) -> list[int]:
    """At most ``cap`` positions in range(count), evenly spread, first and last included."""
    if count <= cap:
        return list(range(count))
    return sorted(set(np.linspace(0, count - 1, cap).round().astype(int).tolist()))


def make_thumbnail(image: Any, size: int) -> np.ndarray:
    """image: uint8 [H, W, 3] (tensor or array) -> uint8 [h, w, 3] with the longer side ``size``."""
    pixels = image.detach().cpu().numpy() if hasattr(image, "detach") else np.asarray(image)
    if pixels.dtype != np.uint8:  # float images in [0, 1]
        pixels = (np.clip(pixels, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    height, width = pixels.shape[:2]
    scale = size / max(height, width)
    if scale >= 1.0:
        return np.ascontiguousarray(pixels[..., :3])
    new_size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return cv2.resize(np.ascontiguousarray(pixels[..., :3]), new_size, interpolation=cv2.INTER_AREA)


class RunViewerState:
    """ViewerState of a model + dataset, optionally driven by a Trainer.

    Join a training run as a trainer callback (``trainer.add_callback(state)``): it takes the trainer's
    lock, pause and checkpoint controls on ``on_train_start`` and records stats / history on every
    step. Without a trainer (``hico-view`` of a finished run) it shows the model as it is.
    The dataset needs ``cameras``, ``train_indices`` and ``image(i) -> uint8 [H, W, 3]``.
    """

    def __init__(self, model: ViewableModel, dataset: Any, stats: Mapping[str, Any] | None = None, max_history: int = 2000,
                 run_dir: Path | None = None):
        self.model = model
        self.dataset = dataset
        self.scene_transform = getattr(dataset, "transform", None) or SceneTransform.identity()
        self.camera_path_dir = None if run_dir is None else Path(run_dir) / "camera_paths"
        self.render_lock: Any = threading.RLock()
        self._trainer: Any = None
        self._training = False
        self._stats: dict[str, Any] = dict(stats or {})
        self._stats_lock = threading.Lock()
        self._history: dict[str, list[float]] = {"step": [], "loss": [], "psnr": []}
        self._history_stride = 1
        self._max_history = max_history
        self._step = int(self._stats.get("step", 0))

    def attach(self, trainer: Any) -> None:
        """Share ``trainer``'s lock and controls (before a render can run concurrently with a step)."""
        self._trainer = trainer
        self.render_lock = trainer.lock
        self._step = int(getattr(trainer, "step", self._step))

    # ------------------------------------------------------------------ trainer callback hooks
    def on_train_start(self, trainer: Any, step: int) -> None:
        self.attach(trainer)
        self._training = True
        self._step = step

    def on_step_end(self, step: int, metrics: Mapping[str, float]) -> None:
        with self._stats_lock:
            self._stats.update(metrics)
            self._stats["step"] = step + 1
            if step % self._history_stride == 0:
                self._history["step"].append(float(step))
                self._history["loss"].append(float(metrics.get("loss", np.nan)))
                self._history["psnr"].append(float(metrics.get("psnr", np.nan)))
                if len(self._history["step"]) > self._max_history:  # halve the density, keep the span
                    self._history = {k: v[::2] for k, v in self._history.items()}
                    self._history_stride *= 2
        self._step = step + 1

    def on_eval(self, step: int, results: Mapping[str, Any]) -> None:
        with self._stats_lock:
            self._stats.update({f"eval/{k}": v for k, v in results.items() if isinstance(v, (int, float))})

    def on_train_end(self, step: int) -> None:
        self._training = False

    # ------------------------------------------------------------------ ViewerState
    @property
    def is_training(self) -> bool:
        return self._training

    @property
    def is_paused(self) -> bool:
        return bool(self._trainer is not None and self._trainer.is_paused)

    @property
    def step(self) -> int:
        return self._step

    def set_paused(self, paused: bool) -> None:
        if self._trainer is not None:
            self._trainer.pause() if paused else self._trainer.resume_training()

    def request_checkpoint(self) -> None:
        if self._trainer is not None:
            self._trainer.request_checkpoint()

    def training_cameras(self, max_cameras: int) -> TrainingCameras:
        train_indices = [int(i) for i in self.dataset.train_indices]
        chosen = [train_indices[p] for p in evenly_spaced(len(train_indices), max_cameras)]
        all_cameras: Cameras = self.dataset.cameras
        selection = torch.as_tensor(chosen, dtype=torch.long)
        cameras = Cameras(
            all_cameras.viewmats[selection], all_cameras.Ks[selection],
            all_cameras.widths[selection], all_cameras.heights[selection],
        )
        return TrainingCameras(cameras, chosen)

    def thumbnail(self, index: int, size: int) -> np.ndarray | None:
        if not hasattr(self.dataset, "image"):
            return None
        return make_thumbnail(self.dataset.image(index), size)

    def anchors(self) -> tuple[Tensor, Tensor]:
        positions, levels = self.model.viewer_anchors()
        return positions.detach().float().cpu().clone(), levels.detach().cpu().long().clone()

    def anchor_parent_found(self) -> Tensor | None:
        """[A] bool, aligned with ``anchors()``: CLCA found a parent context (None: the model has no CLCA)."""
        read = getattr(self.model, "viewer_parent_found", None)
        return read().detach().cpu().clone() if callable(read) else None

    def stats(self) -> dict[str, Any]:
        model_stats = getattr(self.model, "stats", None)
        # During training the trainer's metrics already carry the model's stats.
        fresh = model_stats() if callable(model_stats) and not self._training else {}
        with self._stats_lock:
            self._stats.update(fresh)
            return dict(self._stats)

    def history(self) -> dict[str, np.ndarray]:
        with self._stats_lock:
            return {k: np.asarray(v, dtype=np.float64) for k, v in self._history.items()}
