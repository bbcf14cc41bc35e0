"""The simulator harness of the GPU tests (``tests/cudasim.py``): with it, every thread of a
simulated block gets the same ``cuda.shared.array``, however the threads interleave.

The check runs in a child process under ``NUMBA_ENABLE_CUDASIM=1`` (the simulator replaces
numba.cuda for its whole process). 32 Python threads (a simulated block) released together by a
barrier ask one ``FakeCUDAShared`` for the array of one call site, 50 times, with thread switches
every microsecond. Left to the switch interval alone, a harness without the lock split 2 to 11% of
trials (of 300, from run to run), so each trial's allocation table sleeps between finding no array
and storing one, where a thread switch opens the race: the other threads reach the lookup inside
that window, and without the lock (or with the simulator's own allocation) 47 to 50 of the 50
trials end with more than one array. A harness that lost its lock fails here on every run.
"""
from __future__ import annotations

import itertools
import json
import textwrap

import pytest

from cudasim import simulated

pytest.importorskip("numba_cuda")

CHILD = textwrap.dedent("""
    import json, sys, threading, time
    import numpy as np
    from numba.cuda.simulator.kernelapi import FakeCUDAShared
    from tests.cudasim import lock_shared_allocation

    locked = lock_shared_allocation()
    sys.setswitchinterval(1e-6)
    TRIALS, THREADS = 50, 32

    class Allocations(dict):
        # The race is a lookup that finds no array and a store after it: sleeping in between
        # lets the other threads reach the lookup before the store, as a thread switch there can.
        def get(self, key, default=None):
            found = super().get(key, default)
            if found is None:
                time.sleep(1e-3)
            return found

    got = [None] * THREADS
    trial = {}

    def new_shared():
        trial["shared"] = FakeCUDAShared(0)
        trial["shared"]._allocations = Allocations()

    start = threading.Barrier(THREADS, action=new_shared)   # the same threads for every trial
    end = threading.Barrier(THREADS)
    arrays = []

    def ask(i):
        for _ in range(TRIALS):
            start.wait()
            got[i] = trial["shared"].array((4, 2), np.int32)   # one call site for every thread
            if end.wait() == 0:
                arrays.append(len({id(a) for a in got}))

    threads = [threading.Thread(target=ask, args=(i,)) for i in range(THREADS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    other = FakeCUDAShared(0).array(3, np.float32)    # another call site, another shared array
    print(json.dumps({"locked": locked, "trials": len(arrays), "split": sum(n > 1 for n in arrays),
                      "shape": list(got[0].shape), "dtype": str(got[0].dtype),
                      "other": [other.shape[0], str(other.dtype)]}))
""")


def test_every_thread_of_a_block_gets_the_same_shared_array():
    run = simulated("-c", CHILD, timeout=240)
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["locked"], "tests/cudasim.py did not recognise the simulator's shared-array class"
    assert result["trials"] == 50
    assert result["split"] == 0, f"{result['split']} of 50 trials handed one call site more than one array"
    assert result["shape"] == [4, 2] and result["dtype"] == "int32"
    assert result["other"] == [3, "float32"]


BARRIERS = textwrap.dedent("""
    import json, sys
    import numpy as np
    from tests.cudasim import prepare

    scheduler = sys.argv[1]
    prepare(greenlets=scheduler == "greenlets")
    mark = {"greenlets": "greenlets", "threads": "waits_at_barriers"}[scheduler]  # set on the one installed
    from numba import cuda
    from numba.cuda.simulator import kernel
    from engine.gpu.device import BLOCK
    from engine.gpu.scan import Scanner

    @cuda.jit
    def rounds(out, leave_after):
        # Three barriers; threads t >= leave_after finish before the second: the rest must pass.
        shared = cuda.shared.array(32, np.int32)
        t = cuda.threadIdx.x
        shared[t] = t
        cuda.syncthreads()
        if t >= leave_after:
            return
        x = shared[(t + 1) % 32]
        cuda.syncthreads()
        shared[t] = x * 2
        cuda.syncthreads()
        out[cuda.blockIdx.x, t] = shared[t]

    @cuda.jit
    def fails(values):
        cuda.syncthreads()
        if cuda.threadIdx.x == 3:
            values[values.shape[0] + 5] = 1   # out of bounds: the simulator raises
        cuda.syncthreads()

    @cuda.jit
    def racy(out):
        # A missing barrier: each thread reads its lower neighbour's slot right after writing its own.
        shared = cuda.shared.array(32, np.int32)
        t = cuda.threadIdx.x
        shared[t] = t + 1000
        out[t] = shared[(t + 31) % 32]

    out = np.full((3, 32), -1, np.int32)
    rounds[3, 32](out, 20)
    unsynced = np.full(32, -1, np.int32)
    racy[1, 32](unsynced)
    stale = int(np.sum(unsynced != (np.arange(32) + 31) % 32 + 1000))
    rng = np.random.default_rng(1)
    # 200 values: seven blocks, the last partial; their sums scanned by one block whose total
    # passes every lane's barriers (1,000 values, 32 blocks, cost 2 s more of OS threads here).
    values = rng.integers(0, 50, 200).astype(np.int32)
    scanned = cuda.device_array(201, np.int32)
    total = Scanner().exclusive_scan(cuda.to_device(values), 200, scanned)
    try:
        fails[1, 8](np.zeros(4, np.int32))
        raised = ""
    except Exception as error:   # the failing thread's own error, not a hang
        raised = type(error).__name__ + ": " + str(error)
    print(json.dumps({"rounds": out.tolist(), "scan": scanned.copy_to_host().tolist(), "total": total,
                      "values": values.tolist(), "block": BLOCK, "raised": raised, "stale": stale,
                      "installed": getattr(kernel.BlockManager.run, mark, False)}))
""")


@pytest.mark.parametrize("scheduler", ["greenlets", "threads"])
def test_barriers_wait_for_every_unfinished_thread_and_errors_are_raised(scheduler):
    """The harness's block schedulers (``run_blocks_in_greenlets``, what the GPU tests run, and
    ``wait_at_barriers``, its fallback with OS threads): threads that finished early are not
    waited for, the others pass every barrier together (each reads its neighbour's value before
    any overwrites it), the block scan of ``engine.gpu.scan`` is numpy's cumulative sum, and an
    error in one thread is raised by the launch instead of leaving its block waiting. Under
    greenlets, a kernel missing a barrier reads unwritten shared slots on more than one thread."""
    run = simulated("-c", BARRIERS, scheduler, timeout=240)
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    expected = [[2 * ((t + 1) % 32) if t < 20 else -1 for t in range(32)]] * 3
    assert result["rounds"] == expected
    values = result["values"]
    assert result["scan"] == [0] + list(itertools.accumulate(values)) and result["total"] == sum(values)
    assert result["block"] == 32 and result["installed"]
    assert "IndexError" in result["raised"] or "index" in result["raised"].lower(), result["raised"]
    if scheduler == "greenlets":
        # Threads in thread order would leave only thread 0 reading an unwritten slot; the
        # shuffled rounds expose a missing barrier on many threads, the same ones every run.
        assert result["stale"] > 1, result["stale"]
