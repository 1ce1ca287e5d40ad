"""How freed heap memory is kept for reuse during training and handed back between a run's phases.

By default glibc serves large blocks with a fresh mmap and trims the heap top, so each step page-faults in the
temporaries it freed a moment before. ``keep_freed_memory`` raises both thresholds for training (mallopt(3)):
blocks up to 32 MiB come from the heap and freed pages stay mapped. Between phases ``malloc_trim(0)`` (glibc >=
2.8) returns every whole free page of every arena, lowering the final evaluation's peak RSS. Neither changes what
is computed (figures: benchmarks/RESULTS.md, "Figures behind the defaults").
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
