"""numba's data-flow copies with a shallow copy of each name set (engine/core/jit_dataflow_copies.py):
the same machine code as with numba's deep copies, and copies as independent as deepcopy's."""
from __future__ import annotations

import copy

import numba
from numba.core import ir_utils

import engine  # noqa: F401  (installs the stand-in)
from engine.core import jit_dataflow_copies
from engine.render.direct_light import light_directions
from machine_code import machine_code


def test_the_stand_in_is_installed_by_importing_engine():
    assert isinstance(ir_utils.copy, jit_dataflow_copies._DataflowCopies)
    assert jit_dataflow_copies.use_shallow_dataflow_copies()
    assert isinstance(ir_utils.copy, jit_dataflow_copies._DataflowCopies)


def test_same_machine_code_as_numbas_deep_copies():
    # A parallel kernel: its parfor passes run copy propagation and alias analysis.
    f32_2d, f32_1d, flags = numba.float32[:, ::1], numba.float32[::1], numba.boolean[::1]
    signature = (flags, f32_2d, f32_2d, f32_2d, f32_1d, f32_2d, f32_1d, f32_1d, flags, f32_1d, f32_2d)
    ours = machine_code(light_directions.py_func, signature, True)
    stand_in, ir_utils.copy = ir_utils.copy, copy
    try:
        numbas = machine_code(light_directions.py_func, signature, True)
    finally:
        ir_utils.copy = stand_in
    assert ours == numbas


def test_copies_are_independent_and_keep_shared_sets_shared():
    shared = {"a", "b"}
    names = {1: shared, 2: shared, 3: {("x", "y")}, 4: set()}
    copied = jit_dataflow_copies._DataflowCopies().deepcopy(names)
    assert copied == copy.deepcopy(names)
    assert copied[1] is copied[2] and copied[1] is not shared and copied[3] is not names[3]
    copied[1].add("c")
    assert shared == {"a", "b"}
    # Anything else is deepcopy's: here a set holding a mutable object, and a list of sets.
    other = [{"a"}]
    for x in ({1: {frozenset()}}, other):
        assert jit_dataflow_copies._DataflowCopies().deepcopy(x) == x
    assert jit_dataflow_copies._DataflowCopies().deepcopy(other)[0] is not other[0]
