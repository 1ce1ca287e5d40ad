"""From photographs or a video to a dataset ``hico-train --data`` reads (pycolmap SfM)."""

from __future__ import annotations

import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tyro

from hico_plugin.config import InstantiateConfig
from hico_plugin.errors import HicoError
from hico_plugin.process.ingest import ingest_photos
from hico_plugin.process.sfm import SfmOptions, check_options, list_images, print_summary, run_sfm
from hico_plugin.process.stages import StageRunner, stage_key, write_json_atomic
from hico_plugin.process.video import extract_frames


def _check_output(out: Path, source: Path) -> Path:
    out = out.expanduser().resolve()
    if out == source or out in source.parents or source in out.parents:
        raise HicoError(f"--output {out}: must not contain or lie inside the input {source}")
    if out.exists() and not out.is_dir():
        raise HicoError(f"--output {out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    return out


@dataclass
class ProcessImagesConfig(InstantiateConfig):
    """A folder of photos (sub-folders allowed) -> a COLMAP dataset with undistorted pinhole images."""

    input: tyro.conf.Positional[Path]
    """Folder of photos (.jpg/.png/.tif...; sub-folders give per-folder cameras with --camera-mode per-folder)."""
    output: Path
    """Dataset folder to write (images/, images_2|4|8/, sparse/0/, colmap/, process.json)."""
    sfm: SfmOptions = field(default_factory=SfmOptions)

    def setup(self, **kwargs: Any) -> dict[str, Any]:
        check_options(self.sfm)
        source = self.input.expanduser().resolve()
        if not source.is_dir():
            raise HicoError(f"{self.input}: folder of photos not found")
        out = _check_output(self.output, source)
        names = list_images(source)
        if len(names) < 3:
            raise HicoError(f"{source}: found {len(names)} photos (expected at least 3 .jpg/.png/.tif files)")
        runner = StageRunner(out)
        input_dir = out / "colmap" / "input"
        files = [(name, (source / name).stat().st_size, (source / name).stat().st_mtime_ns) for name in names]
        ingested = runner.run("ingest", stage_key(files), lambda report: ingest_photos(
            source, names, input_dir, input_dir.parent / "masks", report), unit="photos", describe=_describe_ingest)
        skipped = ingested["skipped"]
        for name, reason in sorted(skipped.items()):
            print(f"skipped  {name}: {reason}", file=sys.stderr)
        if len(ingested["kept"]) < 3:
            raise HicoError(f"{source}: {len(ingested['kept'])} of {len(names)} files are usable photos "
                            f"(expected at least 3; {len(skipped)} skipped, listed above)")
        summary = run_sfm(input_dir, ingested["kept"], out, self.sfm, runner, files)
        summary.update(skipped=skipped, rewritten=ingested["rewritten"], masked=ingested["masked"])
        return _finish(summary, out, runner)


@dataclass
class ProcessVideoConfig(InstantiateConfig):
    """A video -> sharp frames sampled over its length -> a COLMAP dataset (frames in time order: sequential
    matching when there are more than --exhaustive-max)."""

    input: tyro.conf.Positional[Path]
    """Video file (anything OpenCV's FFmpeg reads: .mp4, .mov, .avi...)."""
    output: Path
    """Dataset folder to write."""
    num_frames: int = 300
    """Frames to keep: the video is cut into this many windows and the sharpest frame of each is kept."""
    sfm: SfmOptions = field(default_factory=SfmOptions)

    def setup(self, **kwargs: Any) -> dict[str, Any]:
        check_options(self.sfm)
        video = self.input.expanduser().resolve()
        out = _check_output(self.output, video)
        runner = StageRunner(out)
        input_dir = out / "colmap" / "input"
        stat = video.stat() if video.is_file() else None
        key = stage_key(str(video), stat and stat.st_size, stat and stat.st_mtime_ns, self.num_frames)

        def frames(report):
            if input_dir.exists():
                shutil.rmtree(input_dir)
            return extract_frames(video, input_dir, self.num_frames, report)

        frame_summary = runner.run("frames", key, frames, unit="windows",
                                   describe=lambda done: f"{done['kept_frames']} of {done['video_frames']} frames kept")
        names = list_images(input_dir)
        summary = run_sfm(input_dir, names, out, self.sfm, runner, key, ordered=True)
        summary.update(frame_summary)
        return _finish(summary, out, runner)


def _describe_ingest(summary: dict[str, Any]) -> str:
    return (f"{len(summary['kept'])} photos kept, {len(summary['skipped'])} skipped, "
            f"{len(summary['rewritten'])} normalised")


def _finish(summary: dict[str, Any], out: Path, runner: StageRunner) -> dict[str, Any]:
    summary["timings_s"] = runner.timings
    summary["reused_stages"] = runner.reused
    write_json_atomic(out / "process.json", summary)
    print_summary(summary, out, runner.timings, runner.reused)
    return summary


__all__ = ["ProcessImagesConfig", "ProcessVideoConfig", "SfmOptions"]
