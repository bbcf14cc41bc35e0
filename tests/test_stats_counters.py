"""Counters with fewer thread rows than numba runs are refused before any kernel writes past them.

The counting kernels add to row ``numba.get_thread_id()`` of ``stats.counters``; a two-thread
traversal handed ``new_stats(1)`` wrote one row past the array (session 34: crashes at exit and
wrong answers in other arrays). Every traversal that counts now checks the rows first."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest

from engine.core.bvh import build_bvh
from engine.core.threads import numba_threads
from engine.core.types import MAX_BVH_DEPTH, Stats, empty_hits, new_stats, stats_totals
from engine.packet.layout import make_batch
from engine.render.plugins import make_traversal
from scenes.catalog import load_named

COUNTING = ["single", "ranged", "masked", "partition", "simd", "auto", "rayspace"]


@pytest.fixture(scope="module")
def scene_rays():
    scene = load_named("whitted", {})
    tris = scene.triangles
    rng = np.random.default_rng(4)
    n = 256
    lo, hi = tris.v0.min(axis=0), tris.v0.max(axis=0)
    org = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    dirs = rng.normal(size=(n, 3)).astype(np.float32)
    rays, packets = make_batch("reflection", org, dirs, np.zeros(n, np.float32), np.full(n, np.inf, np.float32),
                               np.arange(n, dtype=np.int32), np.ones((n, 3), np.float32), 16, 16, 4)
    return build_bvh(tris), tris, rays, packets


@pytest.mark.parametrize("name", COUNTING)
def test_counters_without_a_row_are_refused_on_one_thread(scene_rays, name):
    """Runs on any machine: no thread row at all is refused, one row is enough for one thread."""
    bvh, tris, rays, packets = scene_rays
    plugin = make_traversal(name)
    with numba_threads(1):
        empty = Stats(np.zeros((0, 3, MAX_BVH_DEPTH), np.int64), {})
        with pytest.raises(ValueError, match="0 thread rows, fewer than the 1 threads"):
            plugin.intersect(bvh, tris, rays, packets, None, empty_hits(rays.org.shape[0]), empty)
        one = new_stats(1)
        plugin.intersect(bvh, tris, rays, packets, None, empty_hits(rays.org.shape[0]), one)
    assert stats_totals(one)["ray_tri"] > 0


@pytest.mark.parametrize("name", COUNTING)
def test_too_few_thread_rows_are_refused_and_enough_are_counted(scene_rays, name):
    if numba.config.NUMBA_NUM_THREADS < 2:
        # One core: numba may still run two threads when asked at start, so this very test
        # runs again in a process that has them.
        node = f"{Path(__file__).resolve()}::test_too_few_thread_rows_are_refused_and_enough_are_counted[{name}]"
        done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", node],
                              env={**os.environ, "NUMBA_NUM_THREADS": "2"}, capture_output=True, text=True,
                              timeout=900)
        # Passed there, not skipped: pytest -q prints "." for a pass, "s" for a skip.
        assert done.returncode == 0 and done.stdout.lstrip().startswith("."), done.stdout[-2000:] + done.stderr[-2000:]
        return
    bvh, tris, rays, packets = scene_rays
    plugin = make_traversal(name)
    with numba_threads(2):
        hits = empty_hits(rays.org.shape[0])
        with pytest.raises(ValueError, match="1 thread rows, fewer than the 2 threads"):
            plugin.intersect(bvh, tris, rays, packets, None, hits, new_stats(1))
        with pytest.raises(ValueError, match="fewer than the 2 threads"):
            plugin.occluded(bvh, tris, rays, packets, None, np.zeros(rays.org.shape[0], np.bool_), new_stats(1))
        stats = new_stats(numba.get_num_threads())
        plugin.intersect(bvh, tris, rays, packets, None, hits, stats)
    assert stats_totals(stats)["ray_tri"] > 0 and (hits.prim >= 0).any()
    with numba_threads(1):  # one row is enough for one thread
        plugin.intersect(bvh, tris, rays, packets, None, empty_hits(rays.org.shape[0]), new_stats(1))
