"""How freed heap memory is kept for reuse during training and handed back between a run's phases.

torch's CPU tensors are malloc'd. A training step allocates and frees the same few dozen large
temporaries (1 to 30 MB on a 320x240 view) every step. By default glibc serves blocks above its mmap
threshold with a fresh mmap and returns the top of the heap to the system once more than the trim
threshold is free there, so each step pays the kernel's page faults (zero-filled pages) for memory it
had a moment before. ``keep_freed_memory`` sets both thresholds for training (mallopt(3)): blocks up to
32 MiB come from the heap, and freed heap pages stay mapped for the next step. That changes where
blocks live, not what is computed, and saves the page faults (benchmarks/RESULTS.md).

Between phases the opposite is wanted: ``malloc_trim(0)`` returns every whole free page of every arena
to the system (glibc >= 2.8; malloc_trim(3)); the blocks stay free for reuse, so nothing computed
changes, and the final evaluation's peak RSS is lower.
"""

from __future__ import annotations

import ctypes
import ctypes.util

_LIBC_NAME = ctypes.util.find_library("c")


def _glibc(name: str):
    """glibc's function ``name``, or None on a C library without it (musl, macOS, Windows)."""
    try:
        return getattr(ctypes.CDLL(_LIBC_NAME), name) if _LIBC_NAME else None
    except (OSError, AttributeError):
        return None


_TRIM = _glibc("malloc_trim")
_MALLOPT = _glibc("mallopt")
# mallopt(3): parameter numbers from malloc.h, and the largest mmap threshold glibc accepts on a
# 64-bit system (DEFAULT_MMAP_THRESHOLD_MAX, 4 MiB * sizeof(long)).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD_MAX = 32 * 1024 * 1024


def keep_freed_memory() -> bool:
    """From now on in this process, serve blocks up to 32 MiB from the heap and never trim its free top
    (``release_free_memory`` still returns free pages when asked). Both settings together: either alone
    turns off glibc's dynamic mmap threshold and leaves the other at its 128 KiB default, which is
    slower than no setting at all. False where mallopt is unavailable or refused a setting."""
    if _MALLOPT is None:
        return False
    return bool(_MALLOPT(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX)) and bool(_MALLOPT(_M_TRIM_THRESHOLD, -1))


def release_free_memory() -> bool:
    """Return the free pages of the heap to the operating system; False where that is unavailable."""
    if _TRIM is None:
        return False
    _TRIM(0)
    return True
