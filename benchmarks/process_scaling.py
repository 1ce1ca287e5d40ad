"""How hico-process's time grows with the photos, under its automatic choice of matcher and mapper.

    python benchmarks/process_scaling.py WORKDIR --num-photos 100 300 1000 [--scene district] [--no-gps]
    python benchmarks/process_scaling.py WORKDIR --photos FOLDER [-- --num-threads 2 ...]

For each count N a built-in scene is rendered with N views (default ``district``, a drone's grid over
many blocks, or ``city-block`` where district is not registered) over an area that grows with N, so
that every count is captured as densely as the scene's default (``--fixed-area``: the default area
for every N, N views spread ever thinner), and handed over as unposed JPEGs,
each with its camera centre plus a consumer GPS fix's error (--gps-noise-m) as GPS in its EXIF
(--no-gps: none, so above --exhaustive-max the vocabulary tree pairs them); --photos takes a folder as
it is. ``hico-process images`` runs on each with the options after ``--``, and its summary gives one
row of the table: photos, matcher, mapper, registered photos, pairs, seconds per stage and matching
seconds per photo. Scenes, photos and outputs stay under WORKDIR (an output folder per set of options)
and hico-process resumes what it had finished, so an interrupted call continues where it stopped; the
stages' seconds are those of the run that finished each.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from PIL import Image

from hico_plugin.process.stages import stage_key
from hico_plugin.scenes import SCENES
from hico_plugin.scenes.generate import generate_scene, scene_config
from hico_plugin.scenes.geotagged import write_geotagged_photos

STAGES = ("ingest", "features", "matching", "mapping", "undistort", "downscale")


def blocks_for(scene: str, count: int) -> int | None:
    """Blocks per side that hold ``count`` views as densely as the scene's default holds its views
    (area in proportion to the views; odd, at least 3, as the grid needs); None for a scene without blocks."""
    default = scene_config(scene)
    if not hasattr(default, "blocks"):
        return None
    side = default.blocks * (count / default.num_views) ** 0.5
    return max(3, 2 * int(round((side - 1) / 2)) + 1)


def photos_of_scene(work: Path, scene: str, count: int, size: tuple[int, int] | None, gps: bool,
                    noise_m: float, fixed_area: bool) -> Path:
    """WORKDIR/<scene>-<count>[-bB][-WxH]/photos[-no-gps]: the scene's views rendered and written as JPEGs."""
    blocks = None if fixed_area else blocks_for(scene, count)
    root = work / (f"{scene}-{count}" + (f"-b{blocks}" if blocks else "") + (f"-{size[0]}x{size[1]}" if size else ""))
    overrides = {"num_views": count, **({"blocks": blocks} if blocks else {}),
                 **({"width": size[0], "height": size[1]} if size else {})}
    rendered = generate_scene(scene, root / "scene", **overrides)
    photos = root / ("photos" if gps else "photos-no-gps")
    if not photos.is_dir():
        partial = photos.with_name(photos.name + ".partial")
        if gps:
            write_geotagged_photos(rendered, partial, noise_m=noise_m)
        else:
            partial.mkdir(parents=True, exist_ok=True)
            for path in sorted((rendered / "images").iterdir()):
                with Image.open(path) as photo:
                    photo.convert("RGB").save(partial / f"{path.stem}.jpg", quality=95)
        partial.rename(photos)
    return photos


def process(photos: Path, out: Path, extra: list[str]) -> list[str]:
    """``hico-process images PHOTOS --output OUT EXTRA...`` (its log next to OUT) -> a table row."""
    log = out.with_name(out.name + ".log")
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as stream:
        done = subprocess.run([sys.executable, "-m", "hico_plugin.cli.process", "images", str(photos),
                               "--output", str(out), *extra], stdout=stream, stderr=subprocess.STDOUT, check=False)
    if done.returncode != 0:
        errors = [line for line in log.read_text().splitlines() if line.startswith("error:")]
        return [errors[-1] if errors else f"exit status {done.returncode}, see {log}"]
    summary = json.loads((out / "process.json").read_text())
    seconds = {stage: json.loads((out / ".hico_process" / f"{stage}.json").read_text()).get("seconds", 0.0)
               for stage in STAGES}
    return [str(summary["images"]), summary["matcher"], summary["mapper"], str(summary["registered"]),
            f"{summary['pairs']:,}", *(f"{seconds[stage]:.1f}" for stage in STAGES),
            f"{seconds['matching'] / max(1, summary['images']):.2f}"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path, help="folder for the scenes, photos and hico-process outputs")
    parser.add_argument("--photos", type=Path, help="a folder of photos, processed as it is")
    parser.add_argument("--scene", default="district" if "district" in SCENES.names() else "city-block")
    parser.add_argument("--num-photos", type=int, nargs="+", default=[100])
    parser.add_argument("--size", type=lambda text: tuple(int(v) for v in text.split("x")), default=None,
                        help="rendered WxH (default: the scene's)")
    parser.add_argument("--fixed-area", action="store_true",
                        help="the scene's default area for every count (default: the area grows with the count)")
    parser.add_argument("--no-gps", action="store_true", help="photos without GPS in their EXIF")
    parser.add_argument("--gps-noise-m", type=float, default=3.0, help="GPS error per axis in metres")
    args, extra = parser.parse_known_args()
    extra = [arg for arg in extra if arg != "--"]
    work = args.work.expanduser().resolve()
    if args.photos is not None:
        folders = [args.photos.expanduser().resolve()]
    else:
        folders = [photos_of_scene(work, args.scene, count, args.size, not args.no_gps, args.gps_noise_m,
                                   args.fixed_area)
                   for count in args.num_photos]
    header = ["photos", "matcher", "mapper", "registered", "pairs", *(f"{s} s" for s in STAGES), "matching s/photo"]
    rows = []
    for photos in folders:
        out = (work if args.photos is not None else photos.parent) / f"out-{photos.name}-{stage_key(extra)}"
        rows.append(process(photos, out, extra))
        print(" | ".join(rows[-1]), file=sys.stderr, flush=True)
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for cells in rows:
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
