"""Stopping a run cleanly: SIGINT (Ctrl-C), SIGTERM and SIGHUP ask the trainer to checkpoint after the current
step and return, with exit status ``EXIT_INTERRUPTED`` (130, a Ctrl-C'd command's; 0 finished, 2 failed).

A signal ignored at start stays ignored, as Python leaves an inherited ignored SIGINT: ``nohup`` ignores SIGHUP,
and a shell without job control starts ``cmd &`` with SIGINT ignored; SIGTERM still stops such a run.
"""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from typing import Callable, Iterator

EXIT_INTERRUPTED = 130
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


@contextmanager
def stop_on_signals(request_stop: Callable[[], bool], announce: bool) -> Iterator[None]:
    """Within the block, each stop signal calls ``request_stop()`` (which returns whether a stop was
    already asked for: then a second Ctrl-C aborts at once). Only the main thread can set handlers;
    elsewhere this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_signal(signum, frame):
        if request_stop():
            raise KeyboardInterrupt
        if announce:
            name = signal.Signals(signum).name
            print(f"\n{name}: saving a checkpoint after this step (Ctrl-C again to abort)", file=sys.stderr)

    previous = {sig: signal.signal(sig, on_signal) for sig in STOP_SIGNALS if signal.getsignal(sig) is not signal.SIG_IGN}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
