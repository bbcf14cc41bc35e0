"""Shared fixtures: the scene search path and small camera-ray batches on real scenes."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

SHARED_SCENES = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"

if "PACKETRT_SCENE_PATH" not in os.environ and SHARED_SCENES.is_dir():
    os.environ["PACKETRT_SCENE_PATH"] = str(SHARED_SCENES)


#: The test files with the most test time (longest first; session 27, warm cache: 40 s down to
#: 6 s each). ``make test`` gives whole files to its two workers (``--dist loadfile``) in
#: collection order (``--no-loadscope-reorder``; xdist's own reorder puts the files with most
#: tests first, which left the few-test cluster and GPU files to the end, one worker running
#: alone); so these are collected first and the short ones fill in behind them.
LONGEST_FIRST = ("test_bench.py", "test_bench_cluster.py", "test_rayspace.py", "test_cli.py", "test_show.py",
                 "test_gpu_frame.py", "test_gpu_lower_check.py", "test_scene_library.py", "test_animate.py",
                 "test_jit_cache.py", "test_offset.py", "test_view.py", "test_frame_pipeline.py",
                 "test_gpu_rayspace.py", "test_hardening.py")


def pytest_collection_modifyitems(config, items):
    """Files of ``LONGEST_FIRST`` first, in its order; every other file after them, as collected
    (a stable sort: a file's own tests keep their order)."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def needs_shared_scenes():
    """Skip (with the reason) when the third-party scene folder is not beside the checkout."""
    if not SHARED_SCENES.is_dir():
        pytest.skip(f"shared scene data not found at {SHARED_SCENES}")


@pytest.fixture
def shared_scenes():
    needs_shared_scenes()
    return SHARED_SCENES


def primary_batch(scene, width=64, height=64, n=8):
    """(RayBatch, Packets) of camera rays in packet order."""
    from engine.packet.layout import make_batch
    from engine.render.camera import camera_rays

    org, d = camera_rays(scene, width, height)
    count = width * height
    return make_batch("primary", org, d, np.zeros(count), np.full(count, np.inf),
                      np.arange(count, dtype=np.int32), np.ones((count, 3)), width, height, n)
