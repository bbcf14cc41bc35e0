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
   reduction silently goes wrong. With the short switch interval above it shows: 2 to 11% of
   300 trials of 32 threads ended with more than one array (``tests/test_cudasim.py`` widens
   that window until nearly every trial does), and a kernel summing its threads' entries of a
   shared array read a wrong sum in 2 of 1,500 launches. It is the likely cause of the one failure in seven runs of
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
5. ``simulated()`` forks its children from a warm process (``serve``: one per pytest worker and
   environment, started at the first call). A fresh interpreter spent about 2 s of CPU before a
   child's own code ran -- Python, ``prepare()`` importing numba and its simulator, the engine's
   GPU and render modules, numba's CPU target set up at its first compile or cache load -- and
   the GPU tests start over a dozen children. A fork is a process of its own in every other way:
   its own state, environment, output, exit status and timeout. What ``prepare()`` printed
   begins every child's output, as it would have; warming beyond it (imports only: no JIT call,
   no thread) that prints or fails is dropped. The warm objects are frozen out of the garbage
   collector (``gc.freeze``): a child's collections would otherwise touch, and so copy, every
   page they sit on (3 s more CPU over six children). Without ``os.fork``, or once a thread has
   started in it, the children are fresh interpreters again.
"""
from __future__ import annotations

import atexit
import gc
import json
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

SWITCH_INTERVAL_S = 1e-4
SIMULATED_BLOCK = 32
SIMULATED_STREAM_BLOCKS = 4
ROOT = Path(__file__).resolve().parents[1]


#: Modules most children import, imported by the warm process after ``prepare()`` (never one run
#: with ``-m``: runpy warns when its module is already imported).
WARM_IMPORTS = ("engine.gpu.frame", "engine.gpu.queries", "engine.render.whitted", "engine.api",
                "scenes.catalog", "validation.audit")


def simulated(*args, timeout=300) -> subprocess.CompletedProcess:
    """Run ``python args...`` (``-m MODULE ...`` or ``-c CODE ...``) in the repository root under
    the CUDA simulator as ``prepare()`` sets it up, from a test (the parent process keeps numba's
    CPU JIT); output captured as text. The child is forked from a warm process (5 above)."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "PYTHONPATH": str(ROOT)}
    command = [sys.executable, "-m", "tests.cudasim", *args]
    key = tuple(sorted((k, v) for k, v in env.items() if k not in PER_TEST))
    if key not in _servers:
        _servers[key] = _Server(env) if hasattr(os, "fork") else None
    if _servers[key] is not None:
        done = _servers[key].run(command, list(args), env, timeout)
        if done is not None:
            return done
        _servers[key] = None    # the warm process cannot fork: fresh interpreters from now on
    return subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)


#: Variables that change from test to test: one warm process serves them all, and each child
#: gets the values of its own call.
PER_TEST = ("PYTEST_CURRENT_TEST",)
#: The warm process of each environment (less ``PER_TEST``); None: it cannot fork.
_servers = {}


class _Server:
    """The pytest side of a warm process (``serve``): requests and replies are JSON lines, output
    goes through files in a folder of its own."""

    def __init__(self, env: dict):
        self.env, self.process, self.state = env, None, None
        atexit.register(self.close)

    def _start(self, warm: bool) -> None:
        self.folder, self.state, self.buffer = tempfile.mkdtemp(prefix="cudasim-"), None, b""
        with open(self._path("warm.err"), "wb") as err:
            self.process = subprocess.Popen([sys.executable, "-m", "tests.cudasim", "--serve", self.folder,
                                             "warm" if warm else "plain"], cwd=ROOT, env=self.env,
                                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err)

    def _path(self, name: str) -> str:
        return os.path.join(self.folder, name)

    def _read(self, name: str) -> str:
        with open(self._path(name), encoding="utf-8", errors="replace") as f:
            return f.read()

    def _line(self, deadline: float):
        """The next reply line; None at the end of the replies; TimeoutError past the deadline."""
        fd = self.process.stdout.fileno()
        while b"\n" not in self.buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise TimeoutError
            chunk = os.read(fd, 65536)
            if not chunk:
                return None
            self.buffer += chunk
        line, _, self.buffer = self.buffer.partition(b"\n")
        return line.decode()

    def _died(self) -> RuntimeError:
        return RuntimeError(f"tests/cudasim.py: the warm process died:\n{self._read('server.err')[-3000:]}")

    def run(self, command: list, args: list, env: dict, timeout: float):
        """The child's CompletedProcess, as ``subprocess.run`` gives it; None where the warm process
        cannot fork."""
        deadline = time.monotonic() + timeout
        if self.process is None:
            self._start(warm=True)
        while self.state != "ready":
            try:
                self.state = self._line(deadline)
            except TimeoutError:
                self.close(kill=True)
                raise subprocess.TimeoutExpired(command, timeout) from None
            if self.state is None:    # prepare() failed: what a fresh child would print and exit with
                done = subprocess.CompletedProcess(command, self.process.wait(), self._read("warm.out"),
                                                   self._read("warm.err"))
                self.close()
                return done
            if self.state == "threaded":
                self.close()
                return None
            if self.state == "noisy":  # the warm imports printed or failed: warm with prepare() alone
                self.close()
                self._start(warm=False)
        out, err = self._path("child.out"), self._path("child.err")
        request = {"args": args, "env": env, "stdout": out, "stderr": err}
        self.process.stdin.write((json.dumps(request) + "\n").encode())
        self.process.stdin.flush()
        started = self._line(time.monotonic() + 60)
        if started is None:
            raise self._died()
        pid = json.loads(started)["pid"]
        try:
            reply = self._line(deadline)
        except TimeoutError:
            os.kill(pid, signal.SIGKILL)
            self._line(time.monotonic() + 60)
            raise subprocess.TimeoutExpired(command, timeout, self._read("child.out"),
                                            self._read("child.err")) from None
        if reply is None:
            raise self._died()
        return subprocess.CompletedProcess(command, json.loads(reply)["returncode"], self._read("child.out"),
                                           self._read("child.err"))

    def close(self, kill: bool = False) -> None:
        """End the warm process (its requests end; killed if ``kill``) and remove its folder."""
        if self.process is None:
            return
        self.process.stdin.close()
        if kill:
            self.process.kill()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.process.stdout.close()
        self.process = None
        shutil.rmtree(self.folder, ignore_errors=True)


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


def _redirect(fd: int, path: str, mode: int = os.O_WRONLY | os.O_CREAT | os.O_TRUNC) -> None:
    target = os.open(path, mode)
    os.dup2(target, fd)
    os.close(target)


def serve(folder: str, warm: bool):
    """``python -m tests.cudasim --serve FOLDER warm|plain``: the warm process of ``simulated`` (5
    above). Reads requests (JSON lines: args, environment, stdout and stderr paths) on stdin,
    forks a child for each and replies with its pid, then its exit status. Returns the args in a
    child, which then runs them; None in the warm process, at the end of the requests."""
    requests = os.fdopen(os.dup(0), "rb")
    replies = os.fdopen(os.dup(1), "w")
    _redirect(0, os.devnull, os.O_RDONLY)
    paths = {1: os.path.join(folder, "warm.out"), 2: os.path.join(folder, "warm.err")}
    _redirect(1, paths[1])                 # stderr already goes to warm.err
    prepare()      # what every child runs first: its output begins theirs, its failure is theirs
    sys.stdout.flush(), sys.stderr.flush()
    state, printed = "ready", [os.path.getsize(p) for p in paths.values()]
    if warm:
        try:
            import importlib

            for name in WARM_IMPORTS:
                importlib.import_module(name)
            from numba.core.registry import cpu_target

            cpu_target.target_context.refresh()    # what numba's first compile or cache load does
        except Exception:   # noqa: BLE001 - a child that imports it meets the error itself
            state = "noisy"
        sys.stdout.flush(), sys.stderr.flush()
        if [os.path.getsize(p) for p in paths.values()] != printed:
            state = "noisy"
    if threading.active_count() > 1:
        state = "threaded"   # fork copies one thread
    _redirect(1, os.devnull)
    _redirect(2, os.path.join(folder, "server.err"))
    print(state, file=replies, flush=True)
    if state != "ready":
        return None
    gc.freeze()    # the children's collections leave the warm objects alone: no copy of their pages
    for line in requests:
        request = json.loads(line)
        sys.stdout.flush(), sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            requests.close()
            replies.close()
            for fd, name in ((1, "stdout"), (2, "stderr")):
                shutil.copyfile(paths[fd], request[name])
                _redirect(fd, request[name], os.O_WRONLY | os.O_APPEND)
            os.environ.clear()
            os.environ.update(request["env"])
            return request["args"]
        print(json.dumps({"pid": pid}), file=replies, flush=True)
        _, status = os.waitpid(pid, 0)
        print(json.dumps({"returncode": os.waitstatus_to_exitcode(status)}), file=replies, flush=True)
    shutil.rmtree(folder, ignore_errors=True)   # a pytest worker may end without its atexit
    return None


def run(argv: list) -> None:
    """Run ``-m MODULE ARGS...`` or ``-c CODE ARGS...`` as ``python`` would (after ``prepare()``)."""
    import runpy

    if argv[0] == "-m":
        sys.argv = [argv[1], *argv[2:]]
        runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
    else:
        sys.argv = ["-c", *argv[2:]]
        exec(compile(argv[1], "<string>", "exec"), {"__name__": "__main__"})


def main(argv: list) -> None:
    """``python -m tests.cudasim -m MODULE ARGS...`` or ``... -c CODE ARGS...``: what ``python``
    would run, after ``prepare()``; each child of ``simulated`` starts here (or is forked from
    ``--serve``, 5 above), so a command-line run (``engine.cli``) gets the same simulator as the
    check scripts."""
    if argv[:1] == ["--serve"]:
        args = serve(argv[1], argv[2] == "warm")
        if args is not None:
            run(args)
        return
    if len(argv) < 2 or argv[0] not in ("-m", "-c"):
        raise SystemExit("usage: python -m tests.cudasim (-m MODULE | -c CODE) [ARGS...]")
    prepare()
    run(argv)


if __name__ == "__main__":
    main(sys.argv[1:])
