"""Built-in scene generation speed: per-view render time (wall and CPU) and full generation time.

    python benchmarks/bench_scenes.py [--scenes city-block pagoda tiny] [--views 8]

Prints, per scene: primitives, per-view render time at the default resolution, rays per second,
and (with --generate) a full uncached generation into a temporary directory.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from hico_plugin.scenes.generate import generate_scene, scene_config
from hico_plugin.scenes.render import render_view


def bench_render(name: str, views: int) -> None:
    config = scene_config(name)
    scene = config.setup(name)
    picks = np.linspace(0, len(scene.viewmats) - 1, views).astype(int)
    render_view(scene.caster, scene.viewmats[0], scene.K, scene.width, scene.height, scene.sun, config.ambient,
                config.shadows)  # warm-up (pixel ray cache)
    wall, cpu = time.perf_counter(), time.process_time()
    with threadpool_limits(limits=1, user_api="blas"):  # as generate_scene renders
        for i in picks:
            render_view(scene.caster, scene.viewmats[i], scene.K, scene.width, scene.height, scene.sun,
                        config.ambient, config.shadows)
    wall, cpu = (time.perf_counter() - wall) / views, (time.process_time() - cpu) / views
    rays = scene.width * scene.height
    print(f"{name:11s} {len(scene.primitives):3d} primitives  {scene.width}x{scene.height}  "
          f"render/view wall {wall * 1e3:7.1f} ms  cpu {cpu * 1e3:7.1f} ms  "
          f"({rays / cpu / 1e6:.2f} M primary rays/s cpu)")


def bench_generate(name: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        path = generate_scene(name, Path(tmp) / name)
        total = time.perf_counter() - start
        meta = json.loads((path / "scene.json").read_text())
        size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
        print(f"{name:11s} generate: {meta['num_views']} views {meta['width']}x{meta['height']}, "
              f"{meta['num_points3D']} points3D, {meta['num_surface_points']} surface samples, "
              f"{size / 1e6:.1f} MB, {total:.1f} s (render {meta['timings_s']['render']:.1f} s, "
              f"sparse+COLMAP {meta['timings_s']['sparse']:.1f} s); effects {meta['enabled_effects']}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["tiny", "city-block", "pagoda"])
    parser.add_argument("--views", type=int, default=8, help="views rendered per scene for the timing")
    parser.add_argument("--generate", action="store_true", help="also time a full uncached generation")
    args = parser.parse_args()
    print(f"load average at start: {open('/proc/loadavg').read().split()[:3]}")
    for scene_name in args.scenes:
        bench_render(scene_name, args.views)
        if args.generate:
            bench_generate(scene_name)
