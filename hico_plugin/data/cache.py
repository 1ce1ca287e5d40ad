"""A least-recently-used cache bounded by the bytes of the arrays it holds."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable

import numpy as np


class ByteLRUCache:
    """Maps keys to numpy arrays; evicts the least recently used once ``max_bytes`` is exceeded.

    An array larger than the whole budget is returned but not kept. Thread-safe (data-loading threads
    may share one dataset).
    """

    def __init__(self, max_bytes: int):
        self.max_bytes = max(0, int(max_bytes))
        self._entries: OrderedDict[Hashable, np.ndarray] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def num_bytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._entries

    def get(self, key: Hashable, load: Callable[[], np.ndarray]) -> np.ndarray:
        """The cached array for ``key``, calling ``load()`` on a miss."""
        with self._lock:
            if key in self._entries:
                self._entries.move_to_end(key)
                return self._entries[key]
        value = load()  # outside the lock: decoding is the slow part and may run in parallel
        with self._lock:
            if value.nbytes <= self.max_bytes and key not in self._entries:
                self._entries[key] = value
                self._bytes += value.nbytes
                while self._bytes > self.max_bytes:
                    _, evicted = self._entries.popitem(last=False)
                    self._bytes -= evicted.nbytes
        return value
