"""What a whole-model export weighs and keeps: file size, Gaussian count, and the test views' PSNR of
its Gaussians next to the model's own, written as JSON next to the PLY."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np
import torch

from hico_plugin.engine.data import load_view
from hico_plugin.export.bake import BakedGaussians
from hico_plugin.export.gaussians import gaussians_from_colmap, rows_to_gaussians
from hico_plugin.metrics import psnr
from hico_plugin.rasterizer import rasterize
from hico_plugin.storage import write_text_atomic


@torch.no_grad()
def file_figures(path: Path, read: Callable[[Path], np.ndarray], model, dataset) -> dict[str, Any]:
    """Size and test-view PSNR of an exported file, from the file itself: ``read`` (``read_ply``,
    ``read_spz``) gives its rows back, which are mapped to the training frame and rasterized as
    ``psnr_on_test_views`` rasterizes the baked set (so a format's quantisation shows)."""
    gaussians = rows_to_gaussians(read(path))
    means, quats, scales = gaussians_from_colmap(gaussians["means"], gaussians["quats"], gaussians["scales"],
                                                 dataset.transform)
    device = model.background.device
    decoded = SimpleNamespace(means=means.to(device), quats=quats.to(device), scales=scales.to(device),
                              opacities=gaussians["opacities"].to(device), colors=gaussians["colors"].to(device))
    return {"file": path.name, "file_bytes": path.stat().st_size, "num_gaussians": len(means),
            "psnr": psnr_on_test_views(model, dataset, decoded)["psnr_baked"]}


@torch.no_grad()
def psnr_on_test_views(model, dataset, baked: BakedGaussians) -> dict[str, float | None]:
    """Mean PSNR (dB) over the test views of ``model`` (a HiCoModel), None without test views: ``psnr_model``, its
    own render; ``psnr_baked``, ``baked`` rasterized with the model's backend and cut-offs and composited over the
    model's constant background or learned environment (which the file does not hold); ``psnr_baked_vs_model``,
    the baked render against the model's, what baking loses. The rasterizer culls opacity <= 1/255, as the PLY
    writer drops, so the baked set renders as the file does.
    """
    sums = {"psnr_model": 0.0, "psnr_baked": 0.0, "psnr_baked_vs_model": 0.0}
    # What lies behind the Gaussians (a learned environment) is no part of the file; it is composited from
    # the model as its own renders do, so the figures measure the Gaussians (without it a sky scene's
    # baked render scores low whatever the Gaussians).
    behind = model.composites_behind()
    views = [int(i) for i in dataset.test_indices]
    config = model.renderer.config
    for index in views:
        camera = dataset.cameras[index].to(baked.means.device)
        image = load_view(dataset, index)[0].to(baked.means)
        own = model.render(camera, ("rgb",))[0].rgb.clamp(0, 1)
        out = rasterize(baked.means, baked.quats, baked.scales, baked.opacities, baked.colors, camera.viewmat,
                        camera.K, camera.width, camera.height, outputs=("rgb", "alpha"),
                        background=None if behind else model.background, backend=model.renderer.backend,
                        near=config.near, far=config.far, tile_size=config.tile_size)
        mine = model.apply_effects(out, camera).clamp(0, 1)
        sums["psnr_model"] += float(psnr(own, image))
        sums["psnr_baked"] += float(psnr(mine, image))
        sums["psnr_baked_vs_model"] += float(psnr(mine, own))
    return {key: total / len(views) if views else None for key, total in sums.items()}


def write_bake_report(ply: Path, num_written: int, baked: BakedGaussians, model, dataset,
                      settings: dict[str, Any]) -> tuple[dict[str, Any], Path]:
    """The report of the PLY ``ply`` holding ``num_written`` of the ``baked`` Gaussians, with the
    export's ``settings`` (anchors, levels, appearance), written to ``<ply stem>_report.json``."""
    report = {
        "file": ply.name,
        "file_bytes": ply.stat().st_size,
        "num_gaussians": num_written,
        "num_baked": len(baked),
        **settings,
        "test_views": len(dataset.test_indices),
        **psnr_on_test_views(model, dataset, baked),
    }
    path = ply.with_name(f"{ply.stem}_report.json")
    write_text_atomic(path, json.dumps(report, indent=2) + "\n")  # 0644, as the PLY next to it
    return report, path
