"""numba's thread count for one piece of work, given back afterwards.

numba keeps one thread count per calling thread (``numba.set_num_threads``), and it outlives the
call that sets it. A query that set it and left it would run every later numba kernel of the
caller at its count: after ``RayTracer(mesh, threads=1)`` answered once, a
``RayMeshIntersector`` query ran on one core. Everything that runs kernels at a configured count
(the Python API, the Whitted and animation renderers, the benchmark runner) therefore sets it for
the duration of each call only, through ``numba_threads`` or the ``at_own_threads`` decorator.
"""
from __future__ import annotations

import functools
from contextlib import contextmanager

import numba


def thread_count(threads: int) -> int:
    """The count ``threads`` stands for: 0, or more than numba started with, is all of
    ``NUMBA_NUM_THREADS``."""
    available = numba.config.NUMBA_NUM_THREADS
    return min(threads or available, available)


@contextmanager
def numba_threads(threads: int):
    """Run the block with numba's parallel kernels on ``thread_count(threads)`` threads, then
    restore the caller's count."""
    before = numba.get_num_threads()
    numba.set_num_threads(thread_count(threads))
    try:
        yield
    finally:
        numba.set_num_threads(before)


def at_own_threads(method):
    """Decorates a method of an object with a ``threads`` attribute (0 = all): the method runs
    inside ``numba_threads(self.threads)``, so the caller's count is back when it returns."""

    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with numba_threads(self.threads):
            return method(self, *args, **kwargs)

    return run
