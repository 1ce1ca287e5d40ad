"""hico-scene: generate a built-in scene as a COLMAP dataset with exact ground truth.

    hico-scene city-block --out data/city --num-views 120 --effects.no-exposure
    hico-scene tiny            # into the cache; prints where
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import tyro

from hico_plugin.cli import run_cli
from hico_plugin.scenes import SCENES, SceneConfig
from hico_plugin.scenes.generate import generate_scene

SceneChoice = tyro.extras.subcommand_type_from_defaults({name: SCENES.get(name)() for name in SCENES.names()})


@dataclass
class SceneCommand:
    """Render a built-in scene (exact depth, normals and surface points) into a COLMAP dataset."""

    scene: Annotated[SceneChoice, tyro.conf.arg(name="")]
    """Which scene to generate."""
    out: Optional[Path] = None
    """Output directory; default: the scene cache, $HICO_CACHE_DIR/scenes (~/.cache/hico_plugin/scenes by default)."""


def _dir_size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main(argv: list[str] | None = None) -> Path:
    command = tyro.cli(SceneCommand, args=argv, config=(tyro.conf.CascadeSubcommandArgs,))
    config: SceneConfig = command.scene
    name = next(n for n in SCENES.names() if type(config) is SCENES.get(n))
    overrides = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    start = time.perf_counter()
    path = generate_scene(name, command.out, **overrides)
    meta = json.loads((path / "scene.json").read_text())
    print(f"scene      {name} -> {path}")
    print(f"views      {meta['num_views']} x {meta['width']}x{meta['height']} PINHOLE")
    print(f"points3D   {meta['num_points3D']} (mean track {meta['mean_track_length']:.1f}, "
          f"reprojection {meta['mean_reprojection_error_px']:.2f} px); surface samples {meta['num_surface_points']}")
    print(f"effects    declared: {', '.join(meta['declared_effects']) or '(none)'}; "
          f"enabled: {', '.join(meta['enabled_effects']) or '(none)'}")
    if meta.get("sfm"):
        sfm = meta["sfm"]
        print(f"sfm        {sfm['registered_images']}/{meta['num_views']} images registered, camera centre error "
              f"mean {sfm['camera_center_error_mean']:.3g} max {sfm['camera_center_error_max']:.3g} (scene units)")
    print(f"size       {_dir_size(path) / 1e6:.1f} MB")
    timings = meta["timings_s"]
    print(f"time       generation {timings['total']:.2f} s (render {timings['render']:.2f} s, sparse "
          f"{timings['sparse']:.2f} s); this call {time.perf_counter() - start:.2f} s")
    return path


def entrypoint() -> None:
    run_cli(main)


if __name__ == "__main__":
    entrypoint()
