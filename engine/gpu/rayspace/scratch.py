"""Device buffers kept between calls and grown on demand (a generation's sizes vary; cudaMalloc
per level and per call would cost more than the kernels on small queues)."""
from __future__ import annotations

import numpy as np

from engine.gpu.device import require_cuda


class Scratch:
    """Named device arrays, each reallocated only when a call needs more rows than it has."""

    def __init__(self):
        self._arrays: dict = {}

    def rows(self, name: str) -> int:
        """Rows the array ``name`` holds now (0 before its first ``get``)."""
        held = self._arrays.get(name)
        return 0 if held is None else int(held.shape[0])

    def get(self, name: str, rows: int, dtype, cols: int = 0):
        """A device array view of at least one row: ``rows`` (x ``cols`` when cols > 0) items of
        ``dtype``. Its contents are whatever the last user left (callers initialise it)."""
        cuda = require_cuda()
        rows = max(1, int(rows))
        held = self._arrays.get(name)
        if held is None or held.shape[0] < rows or held.dtype != np.dtype(dtype):
            shape = (max(rows, 2 * (held.shape[0] if held is not None else 0)),) + ((cols,) if cols else ())
            held = cuda.device_array(shape, dtype)
            self._arrays[name] = held
        return held[:rows]
