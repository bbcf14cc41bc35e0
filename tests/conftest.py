"""Shared fixtures: the scene search path and small camera-ray batches on real scenes."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

SHARED_SCENES = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"

if "PACKETRT_SCENE_PATH" not in os.environ and SHARED_SCENES.is_dir():
    os.environ["PACKETRT_SCENE_PATH"] = str(SHARED_SCENES)


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
