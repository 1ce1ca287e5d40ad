"""Evaluation on the test split, when a run evaluates, and ``eval.json`` in nerfstudio's ns-eval layout."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from hico_plugin.engine.data import load_view
from hico_plugin.engine.memory import release_free_memory
from hico_plugin.engine.protocol import TrainableModel, TrainDataset
from hico_plugin.storage import write_text_atomic


def _scalar(value: Any) -> float | None | bool:
    """The float of a scalar metric, None for 'unavailable', False for a non-scalar (an image)."""
    if value is None:
        return None
    if isinstance(value, bool):
        return False
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, Tensor) and value.numel() == 1:
        return float(value.detach().reshape(()).item())
    return False


def _scalars(view: dict[str, Any]) -> dict[str, Any]:
    """The scalar metrics of one view (images and other values dropped)."""
    return {key: value for key, value in view.items() if _scalar(value) is not False}


def summarize(per_view: list[dict[str, Any]]) -> dict[str, float | None]:
    """Mean and population std over views of every scalar metric: ``k`` and ``k_std``.

    Views where a metric is None or missing are left out of it; a metric no view has is None.
    """
    keys: list[str] = []
    for view in per_view:
        keys += [k for k, v in view.items() if k not in keys and _scalar(v) is not False]
    results: dict[str, float | None] = {}
    for key in keys:
        values = [s for v in per_view if (s := _scalar(v.get(key))) is not None and s is not False]
        if not values:
            results[key], results[f"{key}_std"] = None, None
            continue
        mean = sum(values) / len(values)
        results[key] = mean
        results[f"{key}_std"] = math.sqrt(sum((x - mean) ** 2 for x in values) / len(values))
    return results


@torch.no_grad()
def evaluate(model: TrainableModel, dataset: TrainDataset, indices: list[int], device: torch.device) -> dict[str, Any]:
    """Run ``model.eval_view`` on the views ``indices``; returns the summary plus ``fps``,
    ``num_views`` and the model's ``stats()`` (``num_anchors``, ``num_gaussians``, ...) for keys
    eval_view did not report itself.

    fps = views / the summed ``render_seconds`` the model reports, else / the wall time of eval_view.
    Freed heap memory goes back to the system before the first view and after each (``memory``), so
    the evaluation's peak is not stacked on what training or the previous view left free.
    """
    module = model if isinstance(model, nn.Module) else None
    was_training = module.training if module is not None else False
    if module is not None:
        module.eval()
    per_view, wall_seconds = [], 0.0
    release_free_memory()
    try:
        for index in indices:
            image, gt = load_view(dataset, index)
            gt = {k: v.to(device) for k, v in gt.items()}
            camera = dataset.cameras[index].to(device)
            start = time.perf_counter()
            # only the scalars outlive the view: memory does not grow with the test views
            per_view.append(_scalars(model.eval_view(camera, image.to(device), gt)))
            wall_seconds += time.perf_counter() - start
            release_free_memory()
    finally:
        if module is not None:
            module.train(was_training)
    results = summarize(per_view)
    render_seconds = results.pop("render_seconds", None)
    results.pop("render_seconds_std", None)
    total_seconds = render_seconds * len(per_view) if render_seconds is not None else wall_seconds
    results["fps"] = len(per_view) / total_seconds if total_seconds > 0 else None
    results["num_views"] = len(per_view)
    for key, value in model.stats().items():  # per-view figures from eval_view take precedence
        results.setdefault(key, float(value))
    # choices the model made from the data (e.g. which effects it simulates), as they are
    results.update(getattr(model, "eval_documents", dict)())
    return results


def periodic_eval_due(completed_steps: int, eval_every: int, max_steps: int) -> bool:
    """Whether a run evaluates after ``completed_steps``: every ``eval_every`` steps (0: never), except
    after the last one, which the final evaluation covers."""
    return bool(eval_every) and completed_steps % eval_every == 0 and completed_steps < max_steps


def write_eval_json(
    path: Path, experiment_name: str, method_name: str, checkpoint: str | None, results: dict[str, Any]
) -> Path:
    """Write ``{"experiment_name", "method_name", "checkpoint", "results"}`` atomically."""
    document = {
        "experiment_name": experiment_name,
        "method_name": method_name,
        "checkpoint": checkpoint,
        "results": results,
    }
    write_text_atomic(Path(path), json.dumps(document, indent=2, allow_nan=True) + "\n")
    return Path(path)
