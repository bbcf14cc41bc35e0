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

import mmap

import numpy as np
from numba import njit, prange

#: The bytes of one memory page: a new buffer gets one store per page (``touch_pages``).
PAGE = mmap.PAGESIZE
#: Buffers up to this many bytes are touched by a numpy pass on the calling thread; larger ones
#: by ``touch_pages`` on every numba thread (a parallel launch costs more than a few pages).
SERIAL_TOUCH_BYTES = 1 << 20


def new_array(name, rows, tail=(), dtype=np.float32):
    """The default ``allocate(name, rows, tail, dtype)``, the signature of ``Scratch.allocator``'s
    functions: a new uninitialised array of shape (rows, *tail)."""
    return np.empty((rows,) + tuple(tail), dtype)


@njit(cache=True, parallel=True)
def touch_pages(flat, step):
    """Store a zero at flat[0], flat[step], flat[2 step], ... and flat[-1] (flat: u8[n], n >
    0), so that every page of ``step`` bytes the buffer spans has been written once."""
    n = flat.shape[0]
    for i in prange((n + step - 1) // step):
        flat[i * step] = 0
    flat[n - 1] = 0


def make_pages_present(buffer: np.ndarray) -> None:
    """One store into every page ``buffer`` (C-contiguous) spans, on all numba threads when it
    is large: what a new buffer needs before the kernels see it (see ``Scratch._view``)."""
    flat = buffer.reshape(-1).view(np.uint8)
    if flat.shape[0] == 0:
        return
    if flat.shape[0] <= SERIAL_TOUCH_BYTES:
        flat[::PAGE] = 0
        flat[-1] = 0
    else:
        touch_pages(flat, PAGE)


class Scratch:
    """Named, growing buffers. ``take(key, rows, tail, dtype)`` -> a C-contiguous view of
    shape (rows, *tail), uninitialised (callers may not rely on what it holds); the same key
    returns the same memory next time."""

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
            # instead of 2.0-2.5 ms (dist and ndotl are stored on hit lanes only). One store a
            # page does that, on both cores: a kitchen frame at 1024x1024 takes about 500 MB of
            # new buffers, which ``fill(0)`` on one thread wrote in 0.79-0.85 s of the first
            # frame and the stores make present in 0.26-0.71 s (session 28; what a first touch
            # costs on this VM varies from run to run). The first frame: 1.19-1.31 -> 1.00-1.15 s.
            make_pages_present(buffer)
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
