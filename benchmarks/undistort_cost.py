"""What images-only training loses to SfM poses and what it loses to undistortion's resampling.

    python benchmarks/undistort_cost.py WORKDIR [--seeds 0 1] [--scene city-block] [--jobs 2]

Per seed, hico-gs-lite trained three times on the same photos of a built-in scene:
  A  the photos with their true cameras (the generated scene as a COLMAP dataset);
  B  the photos through ``hico-process images`` (SfM); a camera whose fitted distortion moves no pixel
     by more than half a pixel keeps its photos as taken, so B's test photos are the originals;
  C  the same reconstruction with every photo resampled by COLMAP's undistorter (``--keep-below-px 0``
     on a copy, which reuses the SfM stages, so the poses are B's), scored with B's test cameras and
     photos (``hico-eval --data``: rendered on the original pixel grid) and, for reference, on its own.
SfM-pose cost = A - B and resampling cost = B - C, paired per seed. Everything is written under WORKDIR
and what finished there is reused, so an interrupted call continues where it stopped. Each training
runs on one thread (OMP_NUM_THREADS=1), --jobs of them side by side.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pycolmap

from hico_plugin.process.undistort import describe
from hico_plugin.scenes.generate import generate_scene

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
BIN = Path(sys.executable).parent


def run(args: list, log: Path) -> None:
    with open(log, "a") as out:
        done = subprocess.run([str(a) for a in args], check=False, stdout=out, stderr=subprocess.STDOUT, env=ENV)
    if done.returncode != 0:
        raise SystemExit(f"{args[0]} failed (exit {done.returncode}); see {log}")


def process(photos: Path, out: Path, extra: list) -> dict:
    run([BIN / "hico-process", "images", photos, "--output", out, "--num-threads", "2", *extra], out.with_suffix(".log"))
    return json.loads((out / "process.json").read_text())


def same_reconstruction(a: Path, b: Path) -> str:
    """A line saying that the models in a/sparse/0 and b/sparse/0 hold the same poses and points."""
    first, second = (pycolmap.Reconstruction(str(d / "sparse" / "0")) for d in (a, b))
    poses = [np.array_equal(image.cam_from_world().matrix(), second.images[image_id].cam_from_world().matrix())
             for image_id, image in first.images.items()]
    points = [np.array_equal(point.xyz, second.points3D[point_id].xyz) for point_id, point in first.points3D.items()]
    if not (all(poses) and all(points) and len(second.images) == len(poses) and len(second.points3D) == len(points)):
        raise SystemExit(f"{a} and {b} hold different reconstructions; delete {b} and run again")
    cameras = "; ".join(f"{d.name}: " + ", ".join(f"{c.model.name} {c.width}x{c.height} "
                                                  f"[{', '.join(f'{v:.2f}' for v in c.params)}]" for c in m.cameras.values())
                        for d, m in ((a, first), (b, second)))
    return f"same poses ({len(poses)} images) and points ({len(points)}); cameras {cameras}"


def train(work: Path, arm: str, data: Path, seed: int, steps: int) -> None:
    out = work / "runs" / f"{arm}_s{seed}"
    if (out / "eval.json").is_file():
        return
    resume = ["--resume"] if (out / "config.yml").is_file() else []
    run([BIN / "hico-train", "hico-gs-lite", "--data", data, "--seed", seed, "--max-steps", steps, "--vis", "none",
         "--progress", "lines", "--output-dir", out, *resume], work / f"{arm}_s{seed}.log")


def scores(work: Path, arm: str, seed: int, name: str = "eval.json") -> dict:
    return json.loads((work / "runs" / f"{arm}_s{seed}" / name).read_text())["results"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path, help="folder for the scene, datasets, runs and logs")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--scene", default="city-block")
    parser.add_argument("--max-steps", type=int, default=3000)
    parser.add_argument("--jobs", type=int, default=2, help="trainings side by side")
    args = parser.parse_args()
    work = args.work.resolve()
    scene, photos, kept, resampled = work / "scene", work / "photos", work / "sfm", work / "sfm_resampled"
    if not (scene / "scene.json").is_file():
        generate_scene(args.scene, scene)
    if not photos.is_dir():
        shutil.copytree(scene / "images", photos)
    summaries = {"B": process(photos, kept, [])}
    if not resampled.is_dir():
        shutil.copytree(kept, resampled)  # the SfM stages' work files and markers: they are reused
    summaries["C"] = process(photos, resampled, ["--keep-below-px", "0"])
    for arm, summary in summaries.items():
        for choice in summary["undistortion"]:
            print(f"{arm}: registered {summary['registered']} of {summary['images']}; {describe(choice)}")
        print(f"{arm}: reused stages {', '.join(summary['reused_stages']) or 'none'}")
    print(same_reconstruction(kept, resampled))

    jobs = [(arm, data, seed) for seed in args.seeds for arm, data in (("A", scene), ("B", kept), ("C", resampled))]
    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(lambda job: train(work, *job, args.max_steps), jobs))
    for seed in args.seeds:
        config = work / "runs" / f"C_s{seed}" / "config.yml"
        if not (config.parent / "eval_on_B.json").is_file():
            run([BIN / "hico-eval", "--load-config", config, "--data", kept, "--output-path",
                 config.parent / "eval_on_B.json"], work / f"C_s{seed}_eval_on_B.log")

    print("\nPSNR / SSIM of hico-gs-lite on the test photos (A, B, C-on-B: the original photos on their grid)")
    print("| seed | A true poses | B SfM, photos as taken | C SfM, resampled, on B's grid | C on its own photos "
          "| A - B (poses) | B - C (resampling) |\n|---|---|---|---|---|---|---|")
    rows = []
    for seed in args.seeds:
        a, b, c, own = (scores(work, arm, seed, name) for arm, name in
                        (("A", "eval.json"), ("B", "eval.json"), ("C", "eval_on_B.json"), ("C", "eval.json")))
        rows.append([a["psnr"], b["psnr"], c["psnr"], own["psnr"], a["psnr"] - b["psnr"], b["psnr"] - c["psnr"]])
        cells = [f"{r['psnr']:.2f} / {r['ssim']:.4f}" for r in (a, b, c, own)]
        print(f"| {seed} | " + " | ".join(cells) + f" | {rows[-1][4]:+.2f} | {rows[-1][5]:+.2f} |")
    values = np.array(rows)
    std = values.std(0, ddof=1) if len(rows) > 1 else np.zeros(values.shape[1])
    print("| mean ± std | " + " | ".join(f"{m:+.2f} ± {s:.2f}" if i >= 4 else f"{m:.2f} ± {s:.2f}"
                                         for i, (m, s) in enumerate(zip(values.mean(0), std))) + " |")


if __name__ == "__main__":
    main()
