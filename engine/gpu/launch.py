"""Kernel launches prepared once and replayed every frame.

A numba-cuda launch turns each argument into its driver form in Python, several microseconds
per array: a frame of two dozen launches with twenty to thirty arrays each spends more time
there than the GPU spends tracing. The frame's arrays never move between frames, so
``PreparedLaunch`` converts the arguments once and every later call goes straight to the
driver's launch.

That conversion is numba-cuda's own (``_Kernel._prepare_args``, the step ``_Kernel.launch``
runs); it is not public API, so a version where it moved falls back, silently and correctly, to
the ordinary ``kernel[blocks, threads](*args)`` (as does the simulator).
"""
from __future__ import annotations

import functools
from collections import OrderedDict

import numpy as np

from engine.gpu.device import simulated

#: Scalar argument types keyed by value (everything else, device arrays above all, by identity).
_SCALARS = (bool, int, float, np.bool_, np.integer, np.floating)


class PreparedLaunch:
    """``kernel[blocks, threads](*args)`` as a callable whose arguments are converted once.
    Device arrays in ``args`` must stay allocated while it is used; host arrays are refused."""

    def __init__(self, kernel, blocks: int, threads: int, args: tuple):
        self.kernel, self.blocks, self.threads, self.args = kernel, blocks, threads, tuple(args)
        self.fast = None
        if not simulated():
            try:
                self.fast = _prepare(kernel, blocks, threads, self.args)
            except Exception:  # noqa: BLE001 - numba-cuda internals moved: the ordinary path
                self.fast = None

    def __call__(self) -> None:
        if self.fast is not None:
            try:
                self.fast()
                return
            except TypeError:  # the driver call's signature moved: nothing was launched
                self.fast = None
        self.kernel[self.blocks, self.threads](*self.args)


def _prepare(dispatcher, blocks: int, threads: int, args: tuple):
    """The driver-level launch of ``dispatcher`` with ``args`` converted, as ``_Kernel.launch``
    does it (numba-cuda 0.2x-0.3x)."""
    from numba.cuda import dispatcher as numba_dispatcher
    from numba.cuda.cudadrv import driver

    kernel = dispatcher._compile_for_args(*args)
    if getattr(kernel, "debug", False) or kernel.extensions:
        raise RuntimeError("debug kernels and argument extensions take the ordinary path")
    function = kernel._codelibrary.get_cufunc()
    converted, write_back = [], []
    for kind, value in zip(kernel.argument_types, args):
        kernel._prepare_args(kind, value, 0, write_back, converted)
    if write_back:
        raise RuntimeError("host arrays would be copied at every launch")
    flag = "is_cooperative" if numba_dispatcher.CUDA_CORE_GE_1_0 else "cooperative_launch"
    config = numba_dispatcher.LaunchConfig(grid=(blocks, 1, 1), block=(threads, 1, 1), shmem_size=0,
                                           **{flag: kernel.cooperative})
    stream = driver._to_core_stream(0)  # the default stream, as an ordinary launch gets it
    return functools.partial(numba_dispatcher.launch, stream, config, function.kernel, *converted)


class LaunchCache:
    """Launches prepared on first use and replayed when the same kernel is launched again with
    the same grid and the same arguments: device arrays (any object that is not a scalar) by
    identity, scalars by type and value. ``cache(kernel, blocks, threads, *args)`` launches.

    For launch sequences whose arguments differ from call to call but repeat from frame to frame
    (the ray-space traversal's levels and generations): a static view's frames find every launch
    prepared. Each entry holds its arguments, so an identity cannot be reused while it is cached;
    at most ``limit`` entries, the least recently used dropped first. The owner drops the entries
    that hold arrays it is about to free (``drop_using``, which finds them through an index by
    argument, so an animation that makes new views every frame does not scan the whole cache);
    ``engine.gpu.rayspace.scratch.Scratch`` does. ``hits`` and ``misses`` count launches.
    ``enabled = False`` launches every kernel the ordinary way instead (and counts nothing): the
    same frames with and without it, for a measurement in one process
    (``tools/gpu_rayspace_profile.py --compare-prepared``)."""

    def __init__(self, limit: int = 4096):
        self.enabled = True
        self.limit = limit
        self.entries: OrderedDict = OrderedDict()
        self._by_object: dict = {}  # id of a non-scalar argument -> keys of the entries holding it
        self.hits = self.misses = 0

    def __call__(self, kernel, blocks: int, threads: int, *args) -> None:
        if not self.enabled:
            kernel[blocks, threads](*args)
            return
        key = (id(kernel), blocks, threads) + tuple(
            (type(a), a) if isinstance(a, _SCALARS) else id(a) for a in args)
        launch = self.entries.get(key)
        if launch is None:
            self.misses += 1
            launch = PreparedLaunch(kernel, blocks, threads, args)
            self.entries[key] = launch
            for a in args:
                if not isinstance(a, _SCALARS):
                    self._by_object.setdefault(id(a), set()).add(key)
            if len(self.entries) > self.limit:
                self._forget(next(iter(self.entries)))
        else:
            self.hits += 1
            self.entries.move_to_end(key)
        launch()

    def _forget(self, key) -> None:
        launch = self.entries.pop(key, None)
        if launch is None:
            return
        for a in launch.args:
            held = self._by_object.get(id(a))
            if held is not None:
                held.discard(key)
                if not held:
                    del self._by_object[id(a)]

    def clear(self) -> None:
        """Forget every prepared launch (and the arrays they hold)."""
        self.entries.clear()
        self._by_object.clear()

    def drop_using(self, objects) -> None:
        """Forget the prepared launches that hold any of ``objects`` (arrays about to be freed)."""
        for o in objects:
            for key in list(self._by_object.get(id(o), ())):
                self._forget(key)
