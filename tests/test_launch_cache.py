"""``engine.gpu.launch.LaunchCache``: which launches it replays, which it prepares again, and what
it lets go. A stand-in kernel (``kernel[blocks, threads](*args)`` records the call) takes the
ordinary path of ``PreparedLaunch``, so no GPU is needed; the device side (every launch of a
repeated ray-space call found prepared) is tests/test_gpu_rayspace.py's."""
from __future__ import annotations

import gc
import weakref

import numpy as np

from engine.gpu.launch import LaunchCache


class RecordingKernel:
    """Records ``(blocks, threads, args)`` of every launch."""

    def __init__(self):
        self.calls = []

    def __getitem__(self, config):
        blocks, threads = config
        return lambda *args: self.calls.append((blocks, threads, args))


class Buffer:
    """A stand-in device array: anything that is not a scalar is keyed by identity."""


def test_the_same_objects_replay_a_prepared_launch():
    kernel, cache, a, b = RecordingKernel(), LaunchCache(), Buffer(), Buffer()
    cache(kernel, 4, 128, a, b, 7, np.float32(0.5))
    cache(kernel, 4, 128, a, b, 7, np.float32(0.5))
    assert (cache.misses, cache.hits) == (1, 1)
    assert kernel.calls == [(4, 128, (a, b, 7, np.float32(0.5)))] * 2  # every call launches


def test_other_objects_values_types_or_grids_are_other_launches():
    kernel, cache, a, b = RecordingKernel(), LaunchCache(), Buffer(), Buffer()
    cache(kernel, 4, 128, a, 7)
    for blocks, args in ((4, (b, 7)),                 # another array (even one "equal" to a)
                         (4, (a, 8)),                 # another value
                         (4, (a, 7.0)),               # the same value, another type: another signature
                         (4, (a, np.int32(7))),
                         (4, (a, True)), (4, (a, 1)),  # bool is not int here
                         (5, (a, 7))):                # another grid
        cache(kernel, blocks, 128, *args)
    assert cache.hits == 0 and cache.misses == 8
    cache(RecordingKernel(), 4, 128, a, 7)            # another kernel
    assert cache.misses == 9


def test_least_recently_used_entries_go_first():
    kernel, cache = RecordingKernel(), LaunchCache(limit=2)
    a, b, c = Buffer(), Buffer(), Buffer()
    cache(kernel, 1, 32, a)
    cache(kernel, 1, 32, b)
    cache(kernel, 1, 32, a)          # a is now the most recent
    cache(kernel, 1, 32, c)          # b goes
    assert len(cache.entries) == 2
    cache(kernel, 1, 32, a)
    assert cache.hits == 2
    cache(kernel, 1, 32, b)
    assert cache.misses == 4


def test_entries_hold_their_arrays_until_dropped():
    """An identity cannot be reused while its launch is cached (the entry keeps the array);
    ``drop_using`` and ``clear`` let it go."""
    kernel, cache = RecordingKernel(), LaunchCache()
    kept, other = Buffer(), Buffer()
    watch = weakref.ref(kept)
    cache(kernel, 1, 32, kept, 3)
    cache(kernel, 1, 32, other, 3)
    kernel.calls.clear()
    del kept
    gc.collect()
    assert watch() is not None
    cache.drop_using([watch()])
    assert len(cache.entries) == 1
    gc.collect()
    assert watch() is None
    cache.clear()
    assert not cache.entries


def test_dropping_finds_every_entry_of_an_array_and_no_other():
    """``drop_using`` through its index: all the launches holding the array go (whatever else
    they hold), the others stay, and an evicted entry leaves nothing behind in the index."""
    kernel, cache = RecordingKernel(), LaunchCache(limit=3)
    a, b, c = Buffer(), Buffer(), Buffer()
    cache(kernel, 1, 32, a, b)
    cache(kernel, 1, 32, b, 1)
    cache(kernel, 1, 32, c)
    cache.drop_using([b])
    assert len(cache.entries) == 1
    cache(kernel, 1, 32, c)
    assert cache.hits == 1
    for i in range(5):          # evictions of entries holding only fresh buffers
        cache(kernel, 1, 32, Buffer(), i)
    assert len(cache.entries) == 3 and len(cache._by_object) == 3


def test_a_disabled_cache_launches_the_ordinary_way_and_keeps_nothing():
    kernel, cache, a = RecordingKernel(), LaunchCache(), Buffer()
    cache.enabled = False
    cache(kernel, 2, 64, a, 5)
    cache(kernel, 2, 64, a, 5)
    assert kernel.calls == [(2, 64, (a, 5))] * 2
    assert not cache.entries and cache.hits == cache.misses == 0
