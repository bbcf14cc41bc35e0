"""numba's CUDA simulator as the GPU tests run it: in their child processes only
(``NUMBA_ENABLE_CUDASIM=1``), before ``engine.gpu``'s kernels are imported.

``prepare()`` does three things:

1. Quicker thread switches and one-warp blocks: the simulator runs every GPU thread as a
   Python thread and polls them from the main one, so short switch intervals and 32-thread
   blocks cut its barrier cost several times over. The kernels are written for any block size;
   the real device keeps 128. The rayspace stream gets few blocks, each striding over several
   rows of pairs, so the striding is exercised.
2. ``lock_shared_allocation()``: the simulator (numba-cuda 0.30.4) hands out a block's
   ``cuda.shared.array`` by looking its call site up in a dict and, when absent, creating and
   storing one -- without a lock. Two threads of a block that reach the call site together can
   both create one, and then each writes a shared array of its own: the block's scan or
   reduction silently goes wrong. With the short switch interval above it shows:
   ``tests/test_cudasim.py`` measures 5% of 300 trials of 32 threads ending with more than one
   array, and a kernel summing its threads' entries of a shared array read a wrong sum in 2 of
   1,500 launches. It is the likely cause of the one failure in seven runs of
   ``test_small_pair_budget_batches_triangles`` under two pytest workers, whose pair counts come
   from block scans and block maxima in shared memory. A real GPU has no such race.
3. ``wait_at_barriers()``: the simulator's block scheduler polls. Its main thread loops over
   the block's threads asking each whether it is blocked in ``syncthreads`` or still alive until
   all are, then releases them, so it competes for the interpreter with the threads it waits
   for: a profile of the rayspace check spent 22.8 of its 23.7 s in that loop (4.5 million
   ``is_alive`` calls for 30,144 simulated threads). Here the last thread to arrive at a barrier
   (or to finish) releases the others through one condition variable, and the main thread only
   joins them. The barrier's meaning is the simulator's: the threads of a block that have not
   finished all wait, an exception in one aborts the others and is raised.
"""
from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

SWITCH_INTERVAL_S = 1e-4
SIMULATED_BLOCK = 32
SIMULATED_STREAM_BLOCKS = 4
ROOT = Path(__file__).resolve().parents[1]


def simulated(*args, timeout=300) -> subprocess.CompletedProcess:
    """Run ``python args...`` in the repository root under the CUDA simulator, from a test (the
    parent process keeps numba's CPU JIT); output captured as text."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=timeout)


def lock_shared_allocation() -> bool:
    """Make the simulator's static shared-array allocation atomic (see the module doc).

    The replacement keeps the simulator's rule -- one array per call site (file, line) for the
    whole launch -- and finds the call site from the caller's frame, as the original does from
    the stack. Returns False, changing nothing, where the simulator's class does not look like
    the one this was written against (a later numba-cuda: check whether it still races)."""
    from numba.cuda.simulator import kernelapi

    shared_class = getattr(kernelapi, "FakeCUDAShared", None)
    original = getattr(shared_class, "array", None)
    if original is None or getattr(original, "locked_allocation", False):
        return original is not None
    probe = shared_class(0)
    if not isinstance(getattr(probe, "_allocations", None), dict):
        return False
    import numpy as np
    from numba.core import types
    from numba.np import numpy_support

    lock = threading.Lock()

    def array(self, shape, dtype, alignment=None):
        if alignment is not None or shape == 0:   # errors, and dynamic shared memory: the original's
            return original(self, shape, dtype, alignment)
        if isinstance(dtype, types.Type):
            dtype = numpy_support.as_dtype(dtype)
        caller = sys._getframe(1)
        site = (caller.f_code.co_filename, caller.f_lineno)
        with lock:
            found = self._allocations.get(site)
            if found is None:
                found = np.empty(shape, dtype)
                self._allocations[site] = found
        return found

    array.locked_allocation = True
    shared_class.array = array
    return True


class _Barrier:
    """The ``syncthreads`` state of one simulated block (see ``wait_at_barriers``)."""

    def __init__(self, threads: int):
        self.cond = threading.Condition()
        self.alive = threads       # threads that have not finished
        self.waiting = 0           # threads waiting at the current barrier
        self.generation = 0        # barriers passed
        self.failed = None         # the first thread that raised

    def release_if_complete(self) -> None:
        """With ``cond`` held: every unfinished thread is waiting, so let them all pass."""
        if self.waiting and self.waiting == self.alive:
            self.waiting = 0
            self.generation += 1
            self.cond.notify_all()


def wait_at_barriers() -> bool:
    """Replace the simulator's polling block scheduler by waiting on a condition variable (see
    the module doc). Returns False, changing nothing, where the simulator's classes do not look
    like the ones this was written against."""
    from numba.cuda.simulator import kernel

    manager, thread = getattr(kernel, "BlockManager", None), getattr(kernel, "BlockThread", None)
    if not (hasattr(manager, "run") and hasattr(thread, "syncthreads") and hasattr(thread, "run")):
        return False
    if getattr(manager.run, "waits_at_barriers", False):
        return True
    import numpy as np

    thread_run = thread.run

    def syncthreads(self):
        barrier = self._manager.barrier
        with barrier.cond:
            if barrier.failed is not None:
                raise RuntimeError("abort flag set on syncthreads call")
            generation = barrier.generation
            barrier.waiting += 1
            barrier.release_if_complete()
            while barrier.generation == generation and barrier.failed is None:
                barrier.cond.wait()
            if barrier.failed is not None:
                raise RuntimeError("abort flag set on syncthreads clear")

    def run_thread(self):
        try:
            thread_run(self)   # the simulator's: keeps an exception in self.exception
        finally:
            barrier = self._manager.barrier
            with barrier.cond:
                barrier.alive -= 1
                if self.exception is not None and barrier.failed is None:
                    barrier.failed = self
                    barrier.cond.notify_all()
                else:
                    barrier.release_if_complete()

    def run_block(self, grid_point, *args):
        threads = []
        for block_point in np.ndindex(*self._block_dim):
            def target():
                self._f(*args)

            threads.append(thread(target, self, grid_point, block_point, self._debug))
        self.barrier = _Barrier(len(threads))
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        failed = self.barrier.failed
        if failed is not None:
            raise failed.exception[0].with_traceback(failed.exception[1])

    run_block.waits_at_barriers = True
    thread.syncthreads = syncthreads
    thread.run = run_thread
    manager.run = run_block
    return True


def prepare() -> None:
    """Everything above; call first thing in a simulator child process."""
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    if not lock_shared_allocation():
        print("tests/cudasim.py: the simulator's shared arrays are not locked (unknown numba-cuda layout)",
              file=sys.stderr)
    if not wait_at_barriers():
        print("tests/cudasim.py: the simulator's block scheduler is not replaced (unknown numba-cuda layout)",
              file=sys.stderr)
    from engine.gpu import device

    device.BLOCK = SIMULATED_BLOCK
    from engine.gpu.rayspace import stream

    stream.GRID_BLOCKS = SIMULATED_STREAM_BLOCKS
