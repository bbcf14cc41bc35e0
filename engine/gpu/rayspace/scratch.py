"""Device buffers kept between calls and grown on demand (a generation's sizes vary; cudaMalloc
per level and per call would cost more than the kernels on small queues), and the launches
prepared over them.

The same request (name, rows) returns the same view object, so a kernel launched again over the
same views, as the next frame of a static view does generation by generation, finds its launch
prepared in ``launch`` (``engine.gpu.launch.LaunchCache``): numba's dispatcher converts every
argument at every ordinary launch, tens of microseconds a launch, and a ray-space frame makes
hundreds of launches."""
from __future__ import annotations

import numpy as np

from engine.gpu.device import DeviceUnavailable, require_cuda
from engine.gpu.launch import LaunchCache

#: Views kept per buffer (one per row count asked for); past it, the buffer's views start over.
VIEWS_PER_BUFFER = 64


class Scratch:
    """Named device arrays, each reallocated only when a call needs more rows than it has.

    hint: what the one-line error says to do when an array does not fit the GPU's free memory.
    """

    def __init__(self, hint: str = "render smaller"):
        self._arrays: dict = {}
        self._views: dict = {}     # name -> {rows: view}
        self._prefixes: dict = {}  # (id(view), rows) -> (view, view[:rows])
        self.hint = hint
        self.launch = LaunchCache()

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
            # Nothing may keep the old buffer alive: its views, their prefixes, the launches over them.
            self._arrays[name] = held = None
            self._forget_views(name)
            held = cuda.device_array((grown,) + ((cols,) if cols else ()), dtype)
            self._arrays[name] = held
        views = self._views.setdefault(name, {})
        view = views.get(rows)
        if view is None:
            if len(views) >= VIEWS_PER_BUFFER:
                self._forget_views(name)
                views = self._views.setdefault(name, {})
            view = views[rows] = held[:rows]
        return view

    def _forget_views(self, name: str) -> None:
        """Drop the views of buffer ``name``, their prefixes and the launches that hold either."""
        views = list(self._views.pop(name, {}).values())
        parents = {id(v) for v in views}
        for key in [k for k in self._prefixes if k[0] in parents]:
            views.append(self._prefixes.pop(key)[1])
        self.launch.drop_using(views)

    def prefix(self, view, rows: int):
        """``view[:rows]`` of a view this scratch returned, the same object for the same request."""
        key = (id(view), int(rows))
        kept = self._prefixes.get(key)
        if kept is None or kept[0] is not view:
            if len(self._prefixes) >= VIEWS_PER_BUFFER * 4:
                self.launch.drop_using([p for _, p in self._prefixes.values()])
                self._prefixes.clear()
            kept = self._prefixes[key] = (view, view[:rows])
        return kept[1]
