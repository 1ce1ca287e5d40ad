"""``hico-render --load-config RUN/config.yml {test|orbit|interpolate|camera-path} [--outputs ...]``: frames and
videos.

    hico-render --load-config outputs/city-block/hico-gs-lite/config.yml orbit --outputs rgb depth level

Renders at evaluation LOD (every level active) through the model's ``render_for_display``: one PNG per frame and
output in OUTPUT_DIR/<output>/, and OUTPUT_DIR/<output>.mp4 when a video writer is available.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Sequence

import torch
import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from hico_plugin.cameras import Camera, Cameras
import hico_plugin.presets  # noqa: F401  (loads the config classes a config.yml may name)
from hico_plugin.cli import run_cli
from hico_plugin.errors import HicoError
from hico_plugin.engine import load_run
from hico_plugin.data.transform import SceneTransform
from hico_plugin.export import interpolate_path, orbit_path
from hico_plugin.export.camera_path_file import nerfstudio_transform, read_camera_path
from hico_plugin.export.frames import Mp4Writer, write_png
from hico_plugin.visualization.options import COLORMAP_NAMES, RenderOptions
from hico_plugin.visualization.visualize import visualize

OutputName = Literal["rgb", "depth", "plane-depth", "normal", "depth-normal", "normal-disagreement",
                     "distance", "alpha", "level"]


@dataclass(frozen=True)
class FrameRequest(RenderOptions):
    """What ``HiCoModel.render_for_display`` should draw for every frame: several outputs at once, with
    the viewer's defaults for everything else (the model's own LOD, CLCA as trained)."""

    outputs: tuple[str, ...] = ("rgb",)
    """Render outputs (RenderOutputs field names) to produce."""

    @property
    def required_outputs(self) -> tuple[str, ...]:
        return self.outputs


@dataclass
class RenderArgs:
    """Render a trained HiCo-GS run along a camera path: PNG frames per output and MP4 videos."""

    path: tyro.conf.Positional[Literal["test", "orbit", "interpolate", "camera-path"]]
    """Camera path: the test views, an orbit around the scene centre, a smooth path through the
    training cameras, or the frames of a nerfstudio camera_path.json (--camera-path)."""
    load_config: Path
    """The run's config.yml (written by hico-train next to its checkpoints)."""
    outputs: tuple[OutputName, ...] = ("rgb",)
    """Outputs to render (depth-like maps use a colormap, normals (n + 1) / 2, level the octree level)."""
    output_dir: Path | None = None
    """Folder for <output>/NNNNN.png and <output>.mp4 (default RUN/renders/<path>)."""
    num_frames: int = 120
    """Frames of an orbit or interpolate path (test renders every test view)."""
    fps: float = 30.0
    """Frame rate of the videos."""
    scale: float = 1.0
    """Resolution factor relative to the training cameras."""
    colormap: str = "turbo"
    """Colormap of scalar outputs (turbo, viridis, inferno, magma, jet, gray)."""
    camera_path: Path | None = None
    """camera-path: a nerfstudio camera_path.json (poses in the dataset's source frame; its size, fov
    and fps are used, --num-frames and --fps are not)."""
    nerfstudio_transforms: Path | None = None
    """camera-path: the dataparser_transforms.json of the nerfstudio run that wrote --camera-path
    (nerfstudio writes its own normalised frame; this maps it to the dataset's source frame)."""
    checkpoint: Path | None = None
    """Checkpoint to render instead of the run's newest."""
    device: str | None = None
    """Device to render on (default: the run's)."""


def path_cameras(dataset, path: str, num_frames: int) -> list[Camera]:
    """The cameras of ``path`` in the dataset's (normalised) frame. Path cameras have index -1 (no
    training appearance); test views keep their dataset index."""
    if path == "test":
        indices = [int(i) for i in dataset.test_indices]
        if not indices:
            raise HicoError("test: the run's dataset has no test views (use orbit or interpolate)")
        return [dataset.cameras[i] for i in indices]
    if num_frames < 1:
        raise HicoError(f"--num-frames: expected >= 1, got {num_frames}")
    ids = torch.as_tensor(dataset.train_indices, dtype=torch.long)
    cams = dataset.cameras
    train = Cameras(cams.viewmats[ids], cams.Ks[ids], cams.widths[ids], cams.heights[ids])
    frames = orbit_path(train, num_frames) if path == "orbit" else interpolate_path(train, num_frames)
    return [Camera(frames.viewmats[i], frames.Ks[i], int(frames.widths[i]), int(frames.heights[i]), -1)
            for i in range(len(frames))]


def main(args: RenderArgs) -> Path:
    if args.colormap not in COLORMAP_NAMES:
        raise HicoError(f"--colormap: '{args.colormap}' is not one of {', '.join(COLORMAP_NAMES)}")
    if args.scale <= 0 or args.fps <= 0:
        raise HicoError(f"--scale / --fps: expected > 0, got {args.scale} / {args.fps}")
    fps = args.fps
    if args.path == "camera-path":  # the file is checked before the run loads (its frame comes with it)
        if args.camera_path is None:
            raise HicoError("camera-path: --camera-path FILE is required (a nerfstudio camera_path.json)")
        nerfstudio = None if args.nerfstudio_transforms is None else nerfstudio_transform(args.nerfstudio_transforms)
        read_camera_path(args.camera_path, SceneTransform.identity(), nerfstudio)
    run = load_run(args.load_config, args.checkpoint, args.device)
    if args.path == "camera-path":
        frames, fps = read_camera_path(args.camera_path, run.dataset.transform, nerfstudio)
        cameras = [Camera(frames.viewmats[i], frames.Ks[i], int(frames.widths[i]), int(frames.heights[i]), -1)
                   .scaled(args.scale) for i in range(len(frames))]  # index -1: no training photo's appearance
    else:
        cameras = [c.scaled(args.scale) for c in path_cameras(run.dataset, args.path, args.num_frames)]
    names = list(dict.fromkeys(args.outputs))
    options = {name: RenderOptions(output=name.replace("-", "_"), colormap=args.colormap,
                                   num_levels=run.model.field.grid.num_levels) for name in names}
    request = FrameRequest(outputs=tuple(sorted({r for o in options.values() for r in o.required_outputs})))
    output_dir = args.output_dir or run.run_dir / "renders" / args.path
    videos = {name: Mp4Writer(output_dir / f"{name}.mp4", fps, cameras[0].width, cameras[0].height)
              for name in names} if len({(c.width, c.height) for c in cameras}) == 1 else {}
    start = time.perf_counter()
    bar = Progress(TextColumn("[bold]render"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                   console=Console(stderr=True), transient=True)
    try:
        with bar:
            task = bar.add_task("render", total=len(cameras))
            for i, camera in enumerate(cameras):
                images = run.model.render_for_display(camera, request)
                for name in names:
                    picture = visualize(images, options[name])
                    write_png(output_dir / name / f"{i:05d}.png", picture)
                    if name in videos:
                        videos[name].write(picture)
                bar.advance(task)
    except BaseException:
        for video in videos.values():
            video.discard()
        raise
    seconds = time.perf_counter() - start
    written = [name for name, video in videos.items() if video.close()]
    print(f"render: {len(cameras)} {args.path} frames x {len(names)} outputs ({', '.join(names)}) in {seconds:.1f} s "
          f"({seconds / len(cameras):.2f} s/frame) -> {output_dir}")
    if written:
        print(f"videos: {', '.join(str(output_dir / f'{n}.mp4') for n in written)}")
    else:
        reason = "frames differ in size" if not videos else "no video writer"
        print(f"videos: none ({reason}); PNG frames kept")
    return output_dir


def parse(args: Sequence[str]) -> RenderArgs:
    return tyro.cli(RenderArgs, args=list(args), prog="hico-render")


def entrypoint(argv: Sequence[str] | None = None) -> None:
    run_cli(lambda: main(parse(sys.argv[1:] if argv is None else argv)))
