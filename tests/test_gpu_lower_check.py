"""``tools/gpu_lower_check.py``: every GPU kernel types and lowers for a real GPU (sm_90) on this
machine without one, with the argument types the simulator's workloads launch it with."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("numba_cuda")

ROOT = Path(__file__).resolve().parents[1]
TOOL = ROOT / "tools" / "gpu_lower_check.py"


def defined_kernels() -> set:
    """Module-qualified names (``engine.gpu.bvh_trace.closest_kernel``) of the kernels
    (``@cuda.jit`` without device=True) under engine/gpu: two modules may name a kernel alike."""
    names = set()
    for path in (ROOT / "engine" / "gpu").rglob("*.py"):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        lines = path.read_text().splitlines()
        for i, line in enumerate(lines[:-1]):
            match = re.match(r"def (\w+)", lines[i + 1])
            if line.strip() == "@cuda.jit" and match:
                names.add(f"{module}.{match.group(1)}")
    return names


def test_every_gpu_kernel_lowers_for_sm90(tmp_path):
    report = tmp_path / "report.json"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    done = subprocess.run([sys.executable, str(TOOL), "--json", str(report)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    rows = json.loads(report.read_text())
    assert not [r for r in rows if "error" in r]
    lowered = {r["kernel"] for r in rows}  # module.kernel
    # The workloads reach every kernel: a new one that no workload launches is not checked.
    assert defined_kernels() <= lowered, sorted(defined_kernels() - lowered)
    assert all(r["llvm_ir_chars"] > 0 for r in rows)


def test_a_kernel_numba_cannot_type_fails_the_check(tmp_path):
    """The simulator runs np.zeros in a kernel as Python; numba's CUDA target has no np.zeros:
    the check reports it by name and exits 1."""
    (tmp_path / "broken_kernels.py").write_text(
        "import numpy as np\nfrom numba import cuda\n\n\n@cuda.jit\ndef fill(out, n):\n    i = cuda.grid(1)\n"
        "    if i < n:\n        out[i] = np.zeros(1, np.float32)[0]\n")
    launches = tmp_path / "launches.json"
    launches.write_text(json.dumps([{"module": "broken_kernels", "kernel": "fill", "launches": 1,
                                     "args": [["array", "float32", 1, "C"], ["scalar", "int64"]]}]))
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(ROOT)])
    done = subprocess.run([sys.executable, str(TOOL), "--lower", str(launches)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "FAILED broken_kernels.fill" in done.stderr and "TypingError" in done.stderr
    assert "1 failed" in done.stdout
