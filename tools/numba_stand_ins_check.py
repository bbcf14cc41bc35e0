"""Run numba's own tests of the passes packetrt changes, with packetrt's stand-ins installed.

    python tools/numba_stand_ins_check.py

``import engine`` gives two of numba's compile passes cheaper copies
(``engine/core/jit_inlining.py``, ``engine/core/jit_dataflow_copies.py``). Our tests compare
machine code with and without them on our kernels; this runs numba's own test modules for
inlining, copy propagation and the analyses around them (shipped inside the numba wheel) with
the stand-ins in place, so a numba upgrade can be checked in under a minute. Prints one line per
module and exits 1 if any test fails or the stand-ins are not installed.
"""
from __future__ import annotations

import io
import sys
import unittest
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

MODULES = ("numba.tests.test_ir_inlining", "numba.tests.test_inlining", "numba.tests.test_copy_propagate",
           "numba.tests.test_analysis", "numba.tests.test_ir_utils", "numba.tests.test_array_analysis")


def main() -> int:
    from engine.core.jit_dataflow_copies import use_shallow_dataflow_copies
    from engine.core.jit_inlining import use_linear_inline_copies

    if not (use_linear_inline_copies() and use_shallow_dataflow_copies()):
        print("the stand-ins are not installed: this numba does not look as engine/core/jit_*.py expect")
        return 1
    from numba.core.errors import NumbaPerformanceWarning

    warnings.simplefilter("ignore", NumbaPerformanceWarning)  # numba's tests' own, expected
    failed = 0
    for name in MODULES:
        # The runner's own report is dropped: one line per module is printed below.
        result = unittest.TextTestRunner(stream=io.StringIO(), verbosity=0).run(
            unittest.defaultTestLoader.loadTestsFromName(name))
        bad = result.failures + result.errors
        failed += len(bad)
        print(f"{name}: {result.testsRun} run, {len(bad)} failed, {len(result.skipped)} skipped")
        for test, _ in bad:
            print(f"  FAILED {test.id()}")
    return 1 if failed else 0


if __name__ == "__main__":
    import argparse

    argparse.ArgumentParser(prog="numba_stand_ins_check.py", description=__doc__.splitlines()[0]).parse_args()
    sys.exit(main())
