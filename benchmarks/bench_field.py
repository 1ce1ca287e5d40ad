"""Time the field's per-view stages (LOD selection, CLCA, decoding) and their share of a training step.

    python benchmarks/bench_field.py [--points 20000] [--width 256] [--height 192] [--threads 1]

A synthetic city-like octree (points on building facades and the ground, cameras on an orbit) is
built with the default FieldConfig; random features / offsets stand in for a trained model. For one
view the script prints the median wall time of select, CLCA (forward + backward), decode (forward +
backward, CLCA off) and the rasterizer (forward + backward, pure-torch backend) on the decoded
Gaussians, and each one's share of their sum (a training step without the loss). One thread by
default: on a shared, oversubscribed machine OpenMP threads spin and make timings meaningless.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np
import torch

from hico_plugin.cameras import Cameras
from hico_plugin.field import FieldConfig
from hico_plugin.rasterizer import rasterize
from hico_plugin.scenes.orbits import look_at


def city_points(num: int, gen: torch.Generator) -> torch.Tensor:
    """Points on 30 box 'buildings' (facades) and the ground plane of a 100 m square."""
    ground = torch.rand(num // 3, 3, generator=gen) * torch.tensor([100.0, 100.0, 0.0])
    ground[:, :2] -= 50.0
    centres = torch.rand(30, 2, generator=gen) * 80 - 40
    sizes = torch.rand(30, 3, generator=gen) * torch.tensor([10.0, 10.0, 30.0]) + 3
    which = torch.randint(0, 30, (num - num // 3,), generator=gen)
    local = torch.rand(which.shape[0], 3, generator=gen)
    face = torch.randint(0, 4, (which.shape[0],), generator=gen)
    local[face == 0, 0] = 0.0
    local[face == 1, 0] = 1.0
    local[face == 2, 1] = 0.0
    local[face == 3, 1] = 1.0
    lo = torch.cat([centres[which] - sizes[which, :2] / 2, torch.zeros(which.shape[0], 1)], 1)
    walls = lo + local * sizes[which]
    return torch.cat([ground, walls])


def orbit_cameras(count: int, width: int, height: int) -> Cameras:
    viewmats = []
    for angle in torch.linspace(0, 2 * math.pi, count + 1)[:-1].tolist():
        radius = 60.0 + 20.0 * math.sin(3 * angle)
        eye = np.array([[radius * math.cos(angle), radius * math.sin(angle), 25.0]])
        viewmats.append(torch.from_numpy(look_at(eye, np.zeros_like(eye))[0]).float())
    focal = 0.8 * width
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return Cameras(torch.stack(viewmats), K.expand(count, 3, 3).clone(),
                   torch.full((count,), width), torch.full((count,), height))


def timed(fn, repeats: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20_000)
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--height", type=int, default=192)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)  # the MLPs' initialisation
    gen = torch.Generator().manual_seed(0)
    cameras = orbit_cameras(24, args.width, args.height)
    start = time.perf_counter()
    field = FieldConfig().setup(points=city_points(args.points, gen), train_cameras=cameras)
    build = time.perf_counter() - start
    with torch.no_grad():
        field.anchor_features.normal_(generator=gen)
        field.offsets.normal_(generator=gen)
        for p in field.context.parameters():
            p.normal_(std=0.1, generator=gen)
    camera = cameras[0]
    print(f"octree: {field.num_anchors} anchors, per level {field.level_counts().tolist()}, "
          f"built in {build:.2f} s")

    t_select, ids = timed(lambda: field.select(camera, None), args.repeats)
    def clca():  # gathering the visible rows is part of CLCA's graph, as in decode
        graph = field.context.graph(field.levels, field.anchors, ids, field.grid)
        out = field.context(field.anchor_features[ids], graph)
        out.sum().backward()
        return out

    t_clca, _ = timed(clca, args.repeats)
    def decode():
        gaussians = field.decode(camera, ids, context_enabled=False)
        (gaussians.means.sum() + gaussians.colors.sum() + gaussians.opacities.sum()
         + gaussians.scales.sum() + gaussians.quats.sum()).backward()
        return gaussians

    t_decode, gaussians = timed(decode, args.repeats)
    gaussians = field.decode(camera, ids, context_enabled=False)

    def render():
        out = rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                        gaussians.colors, camera.viewmat, camera.K, camera.width, camera.height)
        out.rgb.mean().backward(retain_graph=True)
        return out

    render()  # the first call compiles the compositor
    t_render, _ = timed(render, args.repeats)
    step = t_select + t_clca + t_decode + t_render
    print(f"view {args.width}x{args.height}, {args.threads} thread(s): {len(ids)} visible anchors, "
          f"{len(gaussians)} Gaussians")
    for name, seconds in (("select (LOD + frustum)", t_select), ("CLCA forward+backward", t_clca),
                          ("decode forward+backward", t_decode), ("rasterize forward+backward", t_render)):
        print(f"  {name:28s} {1000 * seconds:9.1f} ms  {100 * seconds / step:5.1f} %")


if __name__ == "__main__":
    main()
