"""``tools/gpu_rayspace_profile.py`` on numba's CUDA simulator (a child process): a tiny rayspace
frame, its per-kernel profile and the in-process comparison of prepared launches with numba's
dispatcher, so a change to the frame or the traversal breaks this test rather than a lease."""
from __future__ import annotations

import re

import pytest

from cudasim import simulated

pytest.importorskip("numba_cuda")


def test_the_profile_tool_runs_and_compares_prepared_launches():
    run = simulated("-c", "import sys, runpy\n"
                    "from tests.cudasim import prepare\n"
                    "prepare()\n"
                    "sys.argv = ['gpu_rayspace_profile.py', '--scene', 'whitted', '--recursion', 'shadows',\n"
                    "            '--size', '8', '--frames', '1', '--pair-budget', '200000', '--compare-prepared']\n"
                    "runpy.run_path('tools/gpu_rayspace_profile.py', run_name='__main__')\n", timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    out = run.stdout
    assert re.search(r"^frames ms \[", out, re.M) and "profiled frame" in out
    prepared = re.search(r"prepared launches: (\d+) replayed, (\d+) prepared", out)
    assert prepared and int(prepared.group(1)) > 0 and int(prepared.group(2)) > 0
    assert re.search(r"alternating frames ms: prepared \[[\d., ]+\] median [\d.]+ \| dispatcher", out)
    assert re.search(r"^  _expand@1 ", out, re.M) and "cone-sphere tests" in out
