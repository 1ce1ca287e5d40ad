"""Rendered frames to disk: PNGs and MP4s, each written atomically (``storage.atomic_path``)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from hico_plugin.storage import atomic_path, write_bytes_atomic


def write_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write ``image`` uint8 [H, W, 3] RGB as a PNG, atomically."""
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    return write_bytes_atomic(path, encoded.tobytes())


class Mp4Writer:
    """Stream uint8 [H, W, 3] RGB frames into an MP4 (OpenCV, 'mp4v'); the file appears under its
    name only on a successful ``close()``. ``available`` is False when no video writer works here
    (then ``write`` / ``close`` do nothing and ``close`` returns False)."""

    def __init__(self, path: str | os.PathLike, fps: float, width: int, height: int):
        self.path = Path(path)
        self._target = atomic_path(self.path)  # entered here, left by close() (kept) or discard() (removed)
        self._tmp = self._target.__enter__()
        # MPEG-4 codes even sizes only; an odd last row / column is repeated rather than cut off.
        self._padded = (width + width % 2, height + height % 2)
        self._writer = cv2.VideoWriter(str(self._tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), self._padded)
        self.available = self._writer.isOpened()
        self.size = (width, height)
        self.count = 0

    def write(self, frame: np.ndarray) -> None:
        if not self.available:
            return
        if (frame.shape[1], frame.shape[0]) != self.size:
            raise ValueError(f"{self.path}: frame of {frame.shape[1]}x{frame.shape[0]}, "
                             f"the video is {self.size[0]}x{self.size[1]}")
        pad = ((0, self._padded[1] - self.size[1]), (0, self._padded[0] - self.size[0]), (0, 0))
        self._writer.write(np.ascontiguousarray(np.pad(frame[..., ::-1], pad, mode="edge")))
        self.count += 1

    def close(self) -> bool:
        """Finish the file; True when the MP4 was written."""
        self._writer.release()
        written = self.available and self.count > 0 and self._tmp.stat().st_size > 0
        if written:
            self._target.__exit__(None, None, None)
        else:
            self.discard()
        return written

    def discard(self) -> None:
        """Drop the unfinished video (after an error)."""
        self._writer.release()
        dropped = OSError(f"{self.path}: video discarded")
        self._target.__exit__(type(dropped), dropped, None)
