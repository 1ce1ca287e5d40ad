"""Thread-safe controls of a running trainer (the viewer and signal handlers use them): pause,
checkpoint now, stop. Under torchrun every rank agrees on the flags at each step."""

from __future__ import annotations

import threading
import time
from typing import Callable

import torch

from hico_plugin.engine import distributed as dist_utils


class TrainerControls:
    def __init__(self, device: torch.device):
        self.device = device
        self.paused = threading.Event()
        self.checkpoint_requested = threading.Event()
        self.stop_requested = threading.Event()

    def request_stop(self) -> bool:
        """Ask for a stop; returns whether one was already asked for."""
        already = self.stop_requested.is_set()
        self.stop_requested.set()
        return already

    def flags(self) -> tuple[bool, bool, bool]:
        """(stop, checkpoint, pause) requested on any rank, identical on every rank.

        Reading a checkpoint request consumes it. Pausing is agreed too, so under torchrun the other
        workers idle with rank 0 instead of timing out at the next collective.
        """
        checkpoint = self.checkpoint_requested.is_set()
        if checkpoint:
            self.checkpoint_requested.clear()
        flags = torch.tensor(
            [float(self.stop_requested.is_set()), float(checkpoint), float(self.paused.is_set())],
            device=self.device,
        )
        stop, checkpoint, paused = (dist_utils.all_reduce_sum_(flags) > 0).tolist()
        return stop, checkpoint, paused

    def wait_while_paused(self, save_checkpoint: Callable[[], object]) -> bool:
        """Idle until resumed (all ranks together); checkpoints asked for meanwhile are written at
        once. Returns True when a stop was requested."""
        while True:
            time.sleep(0.05)
            stop, checkpoint, paused = self.flags()
            if checkpoint:
                save_checkpoint()
            if stop or not paused:
                return stop
