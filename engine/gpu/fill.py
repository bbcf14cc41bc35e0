"""``fill_array``: one value written over the first n elements of a device array, as a kernel.

Shared by the device rayspace build (its i32 counters) and the device queries (their f32
segment bounds), which used to have a copy each.
"""
from __future__ import annotations

from engine.gpu.device import require_cuda

cuda = require_cuda()


@cuda.jit
def fill_array(values, n, value):
    """values[0 .. n-1] = value (one thread an element; launch ``blocks(n)`` blocks of BLOCK)."""
    i = cuda.grid(1)
    if i < n:
        values[i] = value
