"""Animation on the CUDA device without a GPU: the device refit and ``packetrt animate --device
cuda`` on numba's CUDA simulator, in child processes, against the CPU. A file of its own beside
``test_gpu_frame.py`` so that pytest-xdist can give the two simulator files to two workers.
"""
from __future__ import annotations

import json
import re

import pytest

from cudasim import simulated


@pytest.mark.parametrize("traversal", [None, "wide", "bvh"])
def test_animation_on_the_device_refits_and_matches_the_cpu_frames(tmp_path, traversal):
    """``packetrt animate --device cuda --accel refit``: each frame's moved triangles and refitted
    boxes are copied into the device arrays in place; frames equal the CPU's, audits clean. With
    ``wide`` on both devices the device's 8-wide tree is collapsed again from each refitted host
    tree (stale boxes would lose the moved triangles' hits: audit mismatches). The device's own
    name ``bvh`` is accepted as render, audit and bench accept it (animate refused it)."""
    run = simulated("-m", "tests.gpu_sim_animate_check", str(tmp_path), *([traversal] if traversal else []))
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["codes"] == {"cpu": 0, "cuda": 0}
    assert result["policies"] == ["rebuild", "refit", "refit"]
    assert result["rays"] == result["cpu_rays"]
    assert result["png_difference"] == 0
    counts = re.findall(r"([\d,]+) mismatch", run.stdout)
    assert counts and all(c == "0" for c in counts), counts  # every audited frame


def test_device_refit_equals_the_cpu_refit():
    run = simulated("-m", "tests.gpu_sim_refit_check")
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["triangles"] > 100
    assert result["equal"] == [{"child_boxes": True, "root_row": True, "leaf_tris": True}] * 2


def test_a_refit_that_collapses_into_other_wide_links_renders_like_the_cpu():
    """The 8-wide collapse opens the larger child first, so a refit (a stretched sphere) can keep
    the node count and change the links; the device copied only the boxes, over the old links."""
    run = simulated("-m", "tests.gpu_sim_wide_refit_check")
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["same_wide_nodes"] and not result["same_links"]   # the case this is about
    assert result["differing_pixels"] == {"bvh": 0, "wide": 0}
