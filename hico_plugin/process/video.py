"""Frames from a video: sampled evenly to a target count, the blurriest of each window dropped.

Sharpness is the variance of the Laplacian of the grey frame (high = sharp edges). The video is cut
into ``num_frames`` equal windows of consecutive frames and the sharpest frame of each window is
kept, so motion-blurred frames are skipped while the frames stay spread over the whole video.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from hico_plugin.errors import HicoError
from hico_plugin.process.stages import Report


def sharpness(bgr: np.ndarray) -> float:
    """Variance of the Laplacian of ``bgr`` [H, W, 3] uint8."""
    return float(cv2.Laplacian(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), cv2.CV_64F).var())


def extract_frames(video: Path, target: Path, num_frames: int, report: Report) -> dict:
    """Write the sharpest frame of each of ``num_frames`` windows as ``target/frame_00000.png``..."""
    if not video.is_file():
        raise HicoError(f"{video}: video file not found")
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        raise HicoError(f"{video}: cannot be opened as a video (expected a file OpenCV/FFmpeg can decode)")
    total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    if total <= 0:
        raise HicoError(f"{video}: the video reports no frames")
    if num_frames < 3:
        raise HicoError(f"--num-frames: expected at least 3, got {num_frames}")
    windows = min(num_frames, total)
    edges = np.linspace(0, total, windows + 1).round().astype(int)
    target.mkdir(parents=True, exist_ok=True)
    kept, scores, index = 0, [], 0
    for window in range(windows):
        best, best_score = None, -1.0
        while index < edges[window + 1]:
            ok, frame = capture.read()
            index += 1
            if not ok:
                break
            score = sharpness(frame)
            if score > best_score:
                best, best_score = frame, score
        if best is None:
            break  # the container announced more frames than it holds
        if not cv2.imwrite(str(target / f"frame_{kept:05d}.png"), best):
            raise HicoError(f"{target}: cannot write frames there")
        scores.append(best_score)
        kept += 1
        report(window + 1, windows)
    capture.release()
    if kept < 3:
        raise HicoError(f"{video}: only {kept} frames could be decoded (expected at least 3)")
    return {"video_frames": total, "kept_frames": kept, "min_sharpness": min(scores)}
