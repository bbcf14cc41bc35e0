"""The simulator harness of the GPU tests (``tests/cudasim.py``): with it, every thread of a
simulated block gets the same ``cuda.shared.array``, however the threads interleave.

The check runs in a child process under ``NUMBA_ENABLE_CUDASIM=1`` (the simulator replaces
numba.cuda for its whole process). 32 Python threads released by a barrier ask one
``FakeCUDAShared`` for the array of one call site, 300 times, with thread switches every
microsecond. Without the lock, 5% of such trials ended with more than one array (15 of 300
when measured), so a harness that lost its lock fails here.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("numba_cuda")

ROOT = Path(__file__).resolve().parents[1]

CHILD = textwrap.dedent("""
    import json, sys, threading
    import numpy as np
    from numba.cuda.simulator.kernelapi import FakeCUDAShared
    from tests.cudasim import lock_shared_allocation

    locked = lock_shared_allocation()
    sys.setswitchinterval(1e-6)
    TRIALS, THREADS = 300, 32
    split = 0
    for trial in range(TRIALS):
        shared = FakeCUDAShared(0)
        got = [None] * THREADS
        barrier = threading.Barrier(THREADS)

        def ask(i):
            barrier.wait()
            got[i] = shared.array((4, 2), np.int32)   # one call site for every thread

        threads = [threading.Thread(target=ask, args=(i,)) for i in range(THREADS)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        split += len({id(a) for a in got}) > 1
    other = FakeCUDAShared(0).array(3, np.float32)    # another call site, another shared array
    print(json.dumps({"locked": locked, "split": split, "shape": list(got[0].shape),
                      "dtype": str(got[0].dtype), "other": [other.shape[0], str(other.dtype)]}))
""")


def test_every_thread_of_a_block_gets_the_same_shared_array():
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "PYTHONPATH": str(ROOT)}
    run = subprocess.run([sys.executable, "-c", CHILD], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=240)
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["locked"], "tests/cudasim.py did not recognise the simulator's shared-array class"
    assert result["split"] == 0, f"{result['split']} of 300 trials handed one call site more than one array"
    assert result["shape"] == [4, 2] and result["dtype"] == "int32"
    assert result["other"] == [3, "float32"]
