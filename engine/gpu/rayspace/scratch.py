"""Device buffers kept between calls and grown on demand (a generation's sizes vary; cudaMalloc
per level and per call would cost more than the kernels on small queues)."""
from __future__ import annotations

import numpy as np

from engine.gpu.device import DeviceUnavailable, require_cuda


class Scratch:
    """Named device arrays, each reallocated only when a call needs more rows than it has.

    hint: what the one-line error says to do when an array does not fit the GPU's free memory.
    """

    def __init__(self, hint: str = "render smaller"):
        self._arrays: dict = {}
        self.hint = hint

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
            row_bytes = np.dtype(dtype).itemsize * max(cols, 1)
            free = cuda.current_context().get_memory_info().free
            if held is not None:
                free += held.shape[0] * held.dtype.itemsize * max(cols, 1)  # given back first
            if rows * row_bytes > free:
                raise DeviceUnavailable(
                    f"the ray-space traversal's {name} buffer needs {rows * row_bytes / 2**30:.2f} GiB of GPU memory "
                    f"({rows:,} rows), more than the {free / 2**30:.2f} GiB free on the device; {self.hint}")
            # Doubled when that fits, so a growing size reallocates a few times, not every call.
            grown = max(rows, 2 * (held.shape[0] if held is not None else 0))
            if grown * row_bytes > free:
                grown = rows
            self._arrays[name] = held = None
            held = cuda.device_array((grown,) + ((cols,) if cols else ()), dtype)
            self._arrays[name] = held
        return held[:rows]
