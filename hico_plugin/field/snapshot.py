"""Whether a value derived from some tensors is still current: the tensors it read, by identity and
by their in-place version counters (every in-place write, an optimizer's included, bumps them)."""

from __future__ import annotations

import weakref

from torch import Tensor


class TensorSnapshot:
    """The identity and version of each of ``tensors`` at the time of the snapshot."""

    def __init__(self, *tensors: Tensor):
        self._seen = tuple((weakref.ref(t), t._version) for t in tensors)

    def same_tensors(self, *tensors: Tensor) -> bool:
        """Whether ``tensors`` are the very tensors of the snapshot (none replaced)."""
        return len(tensors) == len(self._seen) and all(ref() is t for (ref, _), t in zip(self._seen, tensors))

    def unchanged(self, *tensors: Tensor) -> bool:
        """Whether ``tensors`` are the snapshot's tensors, none written since."""
        return self.same_tensors(*tensors) and all(version == t._version for (_, version), t in zip(self._seen, tensors))
