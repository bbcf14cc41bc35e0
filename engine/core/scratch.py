"""Per-lane arrays kept from one frame (or query) to the next.

A fresh array costs a page fault for every 4 KiB the kernels first touch; on this machine that
made a numba pass over new arrays four times slower than over reused ones (the kitchen's primary
surface pass: 130 ms fresh against 33 ms reused, 1024x1024). So a renderer keeps its per-lane
arrays in a ``Scratch`` and takes views of them: each key is one use that can be alive at a
time (the Whitted loop keys by generation parity, so a generation's batches never overwrite
their parents while they are being built). A ``RayMeshIntersector`` keeps one for the internal
arrays of its queries (lanes, frusta, packet answers), never for the arrays it returns. Nothing
is shared between renderers or intersectors.
"""
from __future__ import annotations

import numpy as np


class Scratch:
    """Named, growing buffers. ``take(key, rows, tail, dtype)`` -> a C-contiguous view of
    shape (rows, *tail), uninitialised (callers may not rely on what it holds: zeros when new,
    the last use's values after); the same key returns the same memory next time."""

    def __init__(self):
        self._buffers: dict = {}
        self._constants: dict = {}  # key -> the value its buffer holds everywhere (``constant``)

    def take(self, key, rows: int, tail: tuple = (), dtype=np.float32) -> np.ndarray:
        self._constants.pop(key, None)  # whoever takes it may write it
        return self._view(key, rows, tail, dtype)

    def _view(self, key, rows: int, tail: tuple, dtype) -> np.ndarray:
        buffer = self._buffers.get(key)
        if buffer is None or buffer.shape[0] < rows or buffer.shape[1:] != tail or buffer.dtype != dtype:
            buffer = np.empty((rows + rows // 8,) + tail, dtype)  # room for the next frame's few more rays
            # Every page written once now. The eight-lane steps store some rows through a lane
            # mask (``Lanes.store_row(..., mask=)``), and on this machine (AMD EPYC) a masked
            # store whose lanes are all off, into a page never written, costs a microcode assist
            # each time: the page never becomes present, as nothing else writes it. The bunny's
            # camera batch (22% of lanes hit) spent 13-16 ms a frame in light_directions
            # instead of 2.0-2.5 ms (dist and ndotl are stored on hit lanes only).
            buffer.fill(0)
            self._buffers[key] = buffer
        return buffer[:rows]

    def constant(self, key, rows: int, value, tail: tuple = (), dtype=np.float32) -> np.ndarray:
        """A view of shape (rows, *tail) holding ``value`` everywhere, for inputs the kernels only
        read (the unit weights of shadow rays, the endless tmax of secondary rays): its buffer is
        filled when it is new or last held another value, not at every take, which on the kitchen
        was megabytes of writes per batch. Nothing may write into it."""
        buffer = self._buffers.get(key)
        view = self._view(key, rows, tail, dtype)
        if self._buffers[key] is not buffer or self._constants.get(key) != value:
            self._buffers[key].fill(value)
            self._constants[key] = value
        return view

    def allocator(self, prefix):
        """``allocate(name, rows, tail, dtype)`` taking from this scratch under (prefix, name)."""
        return lambda name, rows, tail=(), dtype=np.float32: self.take((prefix, name), rows, tail, dtype)

    def nbytes(self) -> int:
        """Bytes held."""
        return sum(b.nbytes for b in self._buffers.values())
