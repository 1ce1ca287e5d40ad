"""Rasterizer benchmark: time and peak memory of the torch backend.

Each case runs in its own subprocess so that its peak RSS (ru_maxrss) is its own. Prints a table of
forward and forward+backward medians over --reps runs after one warm-up, for rgb alone and for rgb
with every geometry output. Random Gaussians: log-scales around -4, in a 2x2x2 m box 2-4 m in front
of a camera with f = image width.

    python benchmarks/rasterizer.py                       # the full table (N 10k/50k/200k x 256^2/512^2)
    python benchmarks/rasterizer.py --compositor torch    # the vectorised torch compositor instead
    python benchmarks/rasterizer.py --ns 50000 --sizes 512 --compositor torch --no-compile --tile-size 16
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

GEOMETRY = ("rgb", "alpha", "depth", "normal", "distance", "plane_depth", "depth_normal")


def scene(n: int, size: int):
    import torch

    g = torch.Generator().manual_seed(0)
    means = torch.rand(n, 3, generator=g) * 2 - 1
    means[:, 2] += 3.0
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.5 - 4.0)
    opacities = torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    K = torch.tensor([[float(size), 0, size / 2], [0, float(size), size / 2], [0, 0, 1]])
    return [means, quats, scales, opacities, colors], torch.eye(4), K


def run_case(n: int, size: int, outputs: tuple[str, ...], reps: int, use_compile: bool, tile_size: int,
             compositor: str) -> dict:
    """Time one case in this process; returns medians (s), pair count and peak RSS (GB)."""
    import torch

    from hico_plugin.rasterizer import rasterize
    from hico_plugin.rasterizer.torch_backend import TorchBackend

    params, viewmat, K = scene(n, size)
    tile_size = tile_size or TorchBackend(compositor=compositor).default_tile_size(params[0].device)

    def forward(grad: bool):
        leaves = [p.detach().requires_grad_(grad) for p in params]
        out = rasterize(*leaves, viewmat, K, size, size, outputs=outputs, use_compile=use_compile,
                        tile_size=tile_size, compositor=compositor)
        if grad:
            loss = sum(img.square().mean() for img in out.images().values())
            loss.backward()
        return out

    times = {}
    for mode, grad in (("fwd", False), ("fwd_bwd", True)):
        forward(grad)  # warm-up (and compilation)
        samples = []
        for _ in range(reps):
            start = time.perf_counter()
            if grad:
                forward(True)
            else:
                with torch.no_grad():
                    forward(False)
            samples.append(time.perf_counter() - start)
        times[mode] = statistics.median(samples)
    out = forward(False)
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2  # KiB on Linux
    return dict(fwd=times["fwd"], fwd_bwd=times["fwd_bwd"], peak_gb=peak_gb,
                drawn=int((out.radii > 0).sum()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--ns", type=int, nargs="+", default=[10_000, 50_000, 200_000])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--compositor", default="auto", choices=["auto", "fused", "torch"],
                        help="blending kernel (auto: the fused C++ one when it builds)")
    parser.add_argument("--no-compile", action="store_true", help="torch compositor: eager, no torch.compile")
    parser.add_argument("--tile-size", type=int, default=0,
                        help="tile edge in pixels (0: the compositor's default, 16 fused / 4 torch)")
    parser.add_argument("--case", help=argparse.SUPPRESS)  # internal: run one case, print JSON
    args = parser.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    if args.case:
        n, size, which = args.case.split(",")
        outputs = ("rgb",) if which == "rgb" else GEOMETRY
        print(json.dumps(run_case(int(n), int(size), outputs, args.reps, not args.no_compile,
                                  args.tile_size, args.compositor)))
        return

    print(f"torch {torch.__version__}, {args.threads} threads, compositor {args.compositor}, "
          f"compile={'off' if args.no_compile else 'on'}, tile {args.tile_size or 'default'}, median of {args.reps} after 1 warm-up; shared machine: timings are noisy")
    header = f"{'N':>8} {'res':>5} {'outputs':>9} {'fwd s':>8} {'fwd+bwd s':>10} {'peak GB':>8} {'drawn':>8}"
    print(header)
    print("-" * len(header))
    for size in args.sizes:
        for n in args.ns:
            rows = {}
            for which in ("rgb", "geometry"):
                cmd = [sys.executable, __file__, "--case", f"{n},{size},{which}",
                       "--reps", str(args.reps), "--threads", str(args.threads), "--tile-size", str(args.tile_size),
                       "--compositor", args.compositor]
                if args.no_compile:
                    cmd.append("--no-compile")
                proc = subprocess.run(cmd, capture_output=True, text=True)
                if proc.returncode != 0:
                    print(f"{n:>8} {size:>5} {which:>9} failed: {proc.stderr.strip().splitlines()[-1]}")
                    continue
                r = rows[which] = json.loads(proc.stdout.strip().splitlines()[-1])
                print(f"{n:>8} {size:>5} {which:>9} {r['fwd']:>8.3f} {r['fwd_bwd']:>10.3f} "
                      f"{r['peak_gb']:>8.2f} {r['drawn']:>8}", flush=True)
            if len(rows) == 2:
                extra = rows["geometry"]["fwd_bwd"] / rows["rgb"]["fwd_bwd"] - 1
                print(f"{'':>8} {'':>5} {'geometry adds':>24} {100 * extra:>+.0f}% to fwd+bwd")


if __name__ == "__main__":
    main()
