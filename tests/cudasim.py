"""numba's CUDA simulator as the GPU tests run it: in their child processes only
(``NUMBA_ENABLE_CUDASIM=1``), before ``engine.gpu``'s kernels are imported.

``prepare()`` does these things:

1. One-warp blocks: every simulated thread costs Python time, and 32-thread blocks cut the
   barrier cost several times over. The kernels are written for any block size; the real
   device keeps 128. The rayspace stream gets few blocks, each striding over several rows of
   pairs, so the striding is exercised. Where the block's threads stay OS threads (3 below),
   thread switches are made quicker too.
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
4. ``run_blocks_in_greenlets()``, which supersedes 3 where the ``greenlet`` package is installed
   (the ``test`` extra installs it): a block's threads become greenlets, coroutines that one OS
   thread runs in turn, each until it finishes or reaches ``syncthreads``; when every unfinished
   thread has reached it, the next round starts. With OS threads, every simulated thread cost a
   thread start and a GIL hand-off at each switch: the rayspace check (942 blocks, 30,144
   threads) spent 29.7 s of a 31 s run waiting in lock acquisitions, 21 s of it system time. The
   order the greenlets run in, shuffled round by round from a seed per block, is one schedule a
   GPU may run too (threads between two barriers in any order), the same every run; the barrier
   means what it means in 3.
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
    """Run ``python args...`` (``-m MODULE ...`` or ``-c CODE ...``) in the repository root under
    the CUDA simulator as ``prepare()`` sets it up, from a test (the parent process keeps numba's
    CPU JIT); output captured as text."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "tests.cudasim", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)


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


#: The simulator's block reductions, kept as they are on the greenlet threads.
REDUCTIONS = ("syncthreads_count", "syncthreads_and", "syncthreads_or")


class _SimulatedThread:
    """One simulated GPU thread run as a greenlet: what the simulator's ``kernelapi`` asks of
    ``threading.current_thread()`` inside a kernel (its indices, ``syncthreads`` and the
    ``syncthreads_count/and/or`` reductions, which are the simulator's own methods)."""

    def __init__(self, manager, block_idx, thread_idx, dim3):
        self._manager = manager
        self.blockIdx = dim3(*block_idx)
        self.threadIdx = dim3(*thread_idx)
        bx, by, _ = manager._block_dim
        self.thread_id = self.threadIdx.x + bx * (self.threadIdx.y + by * self.threadIdx.z)

    def syncthreads(self):
        """Hand the block back to its scheduler, which resumes this thread once every unfinished
        thread of the block has arrived (``run_blocks_in_greenlets``)."""
        self._manager.scheduler.switch()


class _CurrentThread:
    """Stands for the ``threading`` module in the simulator's ``kernelapi``: inside a block run by
    ``run_blocks_in_greenlets`` the current thread is the simulated thread whose greenlet runs."""

    def __init__(self, real):
        self._real = real
        self.running = None

    def current_thread(self):
        return self._real.current_thread() if self.running is None else self.running

    def __getattr__(self, name):
        return getattr(self._real, name)


def run_blocks_in_greenlets() -> bool:
    """Run each simulated block's threads as greenlets in this thread (see the module doc).
    Returns False, changing nothing, where ``greenlet`` is missing or the simulator's classes do
    not look like the ones this was written against."""
    try:
        import greenlet
    except ImportError:
        return False
    from numba.cuda.simulator import kernel, kernelapi

    manager, thread = getattr(kernel, "BlockManager", None), getattr(kernel, "BlockThread", None)
    real_threading = getattr(kernelapi, "threading", None)
    if not (hasattr(manager, "run") and all(hasattr(thread, name) for name in REDUCTIONS)
            and hasattr(real_threading, "current_thread") and hasattr(kernel, "Dim3")):
        return False
    if getattr(manager.run, "greenlets", False):
        return True
    import random

    import numpy as np

    for name in REDUCTIONS:  # they store into the block's state and call self.syncthreads()
        setattr(_SimulatedThread, name, getattr(thread, name))
    current = _CurrentThread(real_threading)
    threaded_run = manager.run

    def run_block(self, grid_point, *args):
        if self._debug:   # the simulator's debug wrapper (floating-point errors raise) needs its threads
            return threaded_run(self, grid_point, *args)
        self.scheduler = greenlet.getcurrent()
        threads = [_SimulatedThread(self, grid_point, point, kernel.Dim3) for point in np.ndindex(*self._block_dim)]
        lets = [greenlet.greenlet(lambda: self._f(*args)) for _ in threads]
        # Each round runs the unfinished threads in a shuffled order, seeded by the block's index:
        # a kernel that reads another thread's write without a barrier between them fails
        # whichever thread it reads (in thread order, a read of a lower thread's value always
        # passed), and every run of a test takes the same schedule.
        shuffle = random.Random(hash(tuple(grid_point))).shuffle
        waiting = list(range(len(threads)))
        while waiting:    # one round: every unfinished thread runs to the next barrier or its end
            arrived = []
            shuffle(waiting)
            for i in waiting:
                current.running = threads[i]
                try:
                    lets[i].switch()
                except Exception as error:   # as the simulator words it: the thread, its block, the error
                    where = f"tid={list(threads[i].threadIdx)} ctaid={list(threads[i].blockIdx)}"
                    raise type(error)(f"{where}: {error}" if str(error) else where).with_traceback(
                        error.__traceback__) from None
                finally:
                    current.running = None
                if not lets[i].dead:
                    arrived.append(i)
            waiting = arrived

    run_block.greenlets = True
    kernelapi.threading = current
    manager.run = run_block
    return True



def prepare(greenlets: bool = True) -> None:
    """Everything above; call first thing in a simulator child process. ``greenlets=False``
    keeps the OS threads with the barrier of 3 (``tests/test_cudasim.py`` checks both)."""
    if not lock_shared_allocation():
        print("tests/cudasim.py: the simulator's shared arrays are not locked (unknown numba-cuda layout)",
              file=sys.stderr)
    if not (greenlets and run_blocks_in_greenlets()):
        # The simulated threads stay OS threads: quicker switches cut the cost of their barriers.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        if not wait_at_barriers():
            print("tests/cudasim.py: the simulator's block scheduler is not replaced (unknown numba-cuda layout)",
                  file=sys.stderr)
    from engine.gpu import device

    device.BLOCK = SIMULATED_BLOCK
    from engine.gpu.rayspace import stream

    stream.GRID_BLOCKS = SIMULATED_STREAM_BLOCKS


def main(argv: list) -> None:
    """``python -m tests.cudasim -m MODULE ARGS...`` or ``... -c CODE ARGS...``: what ``python``
    would run, after ``prepare()``; each child of ``simulated`` starts here, so a command-line
    run (``engine.cli``) gets the same simulator as the check scripts."""
    import runpy

    if len(argv) < 2 or argv[0] not in ("-m", "-c"):
        raise SystemExit("usage: python -m tests.cudasim (-m MODULE | -c CODE) [ARGS...]")
    prepare()
    if argv[0] == "-m":
        sys.argv = [argv[1], *argv[2:]]
        runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
    else:
        sys.argv = ["-c", *argv[2:]]
        exec(compile(argv[1], "<string>", "exec"), {"__name__": "__main__"})


if __name__ == "__main__":
    main(sys.argv[1:])
