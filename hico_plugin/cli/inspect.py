"""``hico-inspect DIR``: load a dataset exactly as training does and print a summary (or the error)."""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Optional

import tyro

from hico_plugin.cli import run_cli
from hico_plugin.data import DataParserConfig, Dataset
from hico_plugin.field.octree import level_count
from hico_plugin.storage import write_text_atomic


@dataclass
class InspectConfig(DataParserConfig):
    """Load a COLMAP dataset as hico-train would and summarise it."""

    data: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DIR")] = field()
    """Dataset directory holding images/ and sparse/0/."""
    verify_images: bool = True
    """Decode every image and mask (fills the undistortion cache); --no-verify-images skips it on big
    scenes (headers are still checked against the cameras)."""
    effects: bool = True
    """Analyse which image-formation effects the capture has (exposure, environment, noise, distortion,
    multi-distance, LOD levels): what --model.effects auto would turn on."""
    effects_json: Optional[Path] = None
    """Also write the effects analysis (per-image gains included) to this JSON file."""


def scene_label(metadata: dict) -> str:
    """The scene name from scene.json (built-in scenes write ``scene``; ``name`` is accepted too)."""
    name = metadata.get("scene", metadata.get("name"))
    return f"  (scene '{name}')" if name else ""


def summarize(dataset: Dataset) -> list[str]:
    """The summary lines ``hico-inspect`` prints."""
    models = Counter(dataset.sources[camera_id].model for camera_id in set(dataset.camera_ids))
    undistorted = sum(1 for source in dataset.sources.values() if source.needs_undistortion)
    sizes = Counter(zip(dataset.cameras.widths.tolist(), dataset.cameras.heights.tolist()))
    size_text = ", ".join(f"{w}x{h} ({n} views)" for (w, h), n in sizes.most_common(3))
    if len(sizes) > 3:
        size_text += f", ... {len(sizes)} sizes in all"
    dist_min, dist_max = dataset.camera_distance_range()
    levels = level_count(dist_min, dist_max)
    has_masks = sum(path is not None for path in dataset.mask_paths)
    ground_truth = [
        kind
        for kind, present in (
            ("depth", dataset.gt_depth(0) is not None),
            ("normal", dataset.gt_normal(0) is not None),
            ("surface points", dataset.gt_surface_points is not None),
        )
        if present
    ]
    centre = ", ".join(f"{v:.4g}" for v in dataset.transform.centre.tolist())
    lines = [
        f"dataset      {dataset.data_dir}" + scene_label(dataset.metadata),
        (
            f"images       {len(dataset)} registered: {len(dataset.train_indices)} train, "
            f"{len(dataset.test_indices)} test  (from {dataset.image_paths[0].parent})"
        ),
        f"cameras      {len(dataset.sources)}: "
        + ", ".join(f"{model} x{n}" for model, n in sorted(models.items()))
        + (f"  ({undistorted} undistorted to PINHOLE)" if undistorted else ""),
        f"resolution   {size_text}",
        f"points       {len(dataset.points)} sparse points",
        (
            f"scene scale  centre ({centre}), scale {dataset.transform.scale:.6g} (normalised units per "
            f"COLMAP unit), camera extent {dataset.cameras_extent():.4g}"
        ),
        (
            f"LOD range    camera-point distance {dist_min:.4g} .. {dist_max:.4g} (normalised), "
            f"ratio {dist_max / max(dist_min, 1e-12):.3g} -> {levels} octree levels at fork 2"
        ),
        f"masks        {has_masks} of {len(dataset)} views",
        f"ground truth {', '.join(ground_truth) if ground_truth else 'none'}",
    ]
    return lines


def main(config: InspectConfig) -> None:
    dataset = config.setup()
    for line in summarize(dataset):
        print(line)
    if config.effects:
        from hico_plugin.model.effects import analyze_effects

        report = analyze_effects(dataset)
        for line in report.lines():
            print(f"effect  {line}")
        if config.effects_json is not None:
            write_text_atomic(config.effects_json, json.dumps(report.to_json(), indent=2) + "\n")
            print(f"effects      written to {config.effects_json}")
    if config.verify_images:
        dataset.verify_images()
        print(f"verified     all {len(dataset)} images decode and match their cameras")


def entrypoint() -> None:
    run_cli(lambda: main(tyro.cli(InspectConfig)))


if __name__ == "__main__":
    entrypoint()
