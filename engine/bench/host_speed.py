"""How fast this host runs at the moment: a few milliseconds of fixed work, timed before and
after each benchmark cell, so that a cell measured while the host ran slow can be told apart.

Why: on a shared 2-core host the same cell moved by up to 40% within an hour (session 25: the
kitchen-paper frame 195 -> 300 ms, code unchanged), while the CPU share the runner records (our
CPU seconds over wall time x threads) stayed near 1: nobody took the cores from us, they ran
slower. Fixed work on every numba thread sees that directly:

- compute: a chain of dependent float multiply-adds, ``COMPUTE_STEPS`` of them on each thread
  (milliseconds; the clock speed the threads get);
- memory: a chain of dependent loads through an 8 MiB table, past a core's L2, ``LOADS`` of them
  on each thread (nanoseconds per load; the latency the BVH walks wait on);
- stream: a read of a 64 MiB array split over the threads (GB/s; the bandwidth the shading
  passes, which write and read back tens of bytes a lane, depend on).

``measure()`` -> {"compute_ms", "memory_ns", "stream_gbps", "threads"}: medians of three runs of
each, about 40 ms in all on a quiet host. Compare values from one host only.

The load table and the stream array are made once per process (``probe_arrays``): a runner probes
twice per cell, and making them each time (64 MiB written page by page, 34 ms) cost more than the
probe's own timed work. They are constants that no answer depends on.
"""
from __future__ import annotations

import functools
import statistics
import time

import numba
import numpy as np
from numba import njit, prange

COMPUTE_STEPS = 2_000_000
LOADS = 25_000  # about 2.5 ms a run at 100 ns a load: enough for the clock, and a median of three
TABLE_ENTRIES = 1 << 21  # int32: 8 MiB
STREAM_FLOATS = 1 << 24  # float32: 64 MiB
RUNS = 3


@njit(cache=True, parallel=True)
def _compute_chain(steps, out):
    """out[t] (f64[threads]) = the end of a chain of ``steps`` dependent multiply-adds, one chain
    per thread."""
    for t in prange(out.shape[0]):
        x = 1.0 + t
        for _ in range(steps):
            x = x * 0.9999999 + 1e-7
        out[t] = x


@njit(cache=True)
def _cycle(n):
    """i32[n] (n a power of two): next[i] = (a i + c) mod n, with a = 1 (mod 4) and c odd, which
    visits all n entries in one cycle (Hull and Dobell) in an order no prefetcher follows."""
    following = np.empty(n, np.int32)
    for i in range(n):
        following[i] = (i * 1103515245 + 12345) & (n - 1)
    return following


@njit(cache=True, parallel=True)
def _load_chain(following, loads, out):
    """out[t] (i64[threads]) = where a chain of ``loads`` dependent loads through ``following``
    ends, one chain per thread from its own start."""
    for t in prange(out.shape[0]):
        p = (t * 65537) & (following.shape[0] - 1)
        for _ in range(loads):
            p = following[p]
        out[t] = p


@njit(cache=True, parallel=True, fastmath=True)
def _stream(values):
    """The sum of ``values`` (f32[n]), read by every thread in parallel. fastmath lets LLVM add in
    any order, so the loads, not a chain of adds, set the pace (nothing here needs the sum's
    exact bits)."""
    total = 0.0
    for i in prange(values.shape[0]):
        total += values[i]
    return total


@functools.lru_cache(maxsize=1)
def probe_arrays():
    """(following i32[TABLE_ENTRIES]: the load chain's table, values f32[STREAM_FLOATS]: the array
    the stream reads, every page written), made once per process."""
    following = _cycle(TABLE_ENTRIES)
    values = np.ones(STREAM_FLOATS, np.float32)
    following.flags.writeable = values.flags.writeable = False  # shared by every probe: read only
    return following, values


def measure() -> dict:
    """{"compute_ms": ms for COMPUTE_STEPS steps, "memory_ns": ns per dependent load,
    "stream_gbps": GB/s read, "threads": numba threads}: medians of RUNS runs on every numba
    thread (see the module doc)."""
    threads = numba.get_num_threads()
    floats, ends = np.empty(threads), np.empty(threads, np.int64)
    following, values = probe_arrays()
    _compute_chain(1, floats)  # compiled or loaded before the clock starts
    _load_chain(following, 1, ends)
    _stream(values)
    compute, memory, stream = [], [], []
    for _ in range(RUNS):
        start = time.perf_counter()
        _compute_chain(COMPUTE_STEPS, floats)
        compute.append(time.perf_counter() - start)
        start = time.perf_counter()
        _load_chain(following, LOADS, ends)
        memory.append(time.perf_counter() - start)
        start = time.perf_counter()
        _stream(values)
        stream.append(time.perf_counter() - start)
    return {"compute_ms": 1e3 * statistics.median(compute), "memory_ns": 1e9 * statistics.median(memory) / LOADS,
            "stream_gbps": values.nbytes / statistics.median(stream) / 1e9, "threads": threads}

