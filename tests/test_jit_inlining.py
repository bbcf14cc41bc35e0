"""numba's inliner with one scope copy per IR copy (engine/core/jit_inlining.py): the same
machine code as numba's own block-by-block copies, and copies that share nothing they must not."""
from __future__ import annotations

import contextlib
import copy

import numba
import numpy as np
from numba.core import inline_closurecall, ir
from numba.core.compiler import run_frontend

import engine  # noqa: F401  (installs the stand-in)
from engine.core import jit_inlining
from traversals.single import walk_ray
from machine_code import machine_code


@contextlib.contextmanager
def numbas_own_copies():
    """numba's inliner as numba ships it, for the duration of the block."""
    worker = inline_closurecall.InlineWorker
    stand_in, wrapped = inline_closurecall.copy, worker.inline_ir
    inline_closurecall.copy, worker.inline_ir = copy, wrapped.__wrapped__
    try:
        yield
    finally:
        inline_closurecall.copy, worker.inline_ir = stand_in, wrapped


def walk_ray_signature():
    f32_2d, i32_1d, f32_1d = numba.float32[:, ::1], numba.int32[::1], numba.float32[::1]
    none = numba.types.none
    return (f32_2d, f32_2d, i32_1d, i32_1d, i32_1d, f32_2d, f32_2d, f32_2d, f32_2d, f32_2d, f32_2d, f32_1d,
            f32_1d, numba.int64, numba.boolean, i32_1d, i32_1d, none, numba.int64, none)


def test_the_stand_in_is_installed_by_importing_engine():
    assert isinstance(inline_closurecall.copy, jit_inlining._InlinerCopies)
    assert inline_closurecall.InlineWorker.inline_ir.packetrt_linear_copies
    assert jit_inlining.use_linear_inline_copies()  # idempotent
    assert isinstance(inline_closurecall.copy, jit_inlining._InlinerCopies)
    assert not hasattr(inline_closurecall.InlineWorker.inline_ir.__wrapped__, "packetrt_linear_copies")


def test_same_machine_code_as_numbas_own_inliner():
    # single's per-ray walk inlines the slab test, the ray shear and the watertight triangle test.
    signature = walk_ray_signature()
    ours = machine_code(walk_ray.py_func, signature)
    with numbas_own_copies():
        numbas = machine_code(walk_ray.py_func, signature)
    assert ours == numbas


def _branchy(a, n):
    total = 0.0
    for i in range(n):
        if a[i] > 0:
            total += a[i]
        else:
            total -= a[i]
    return total


def test_one_ir_copy_shares_one_new_scope_and_no_statement():
    func_ir = run_frontend(_branchy)
    assert len(func_ir.blocks) > 3
    copies = jit_inlining._InlinerCopies()
    copies.scope_copies = {}
    first = {label: copies.deepcopy(block) for label, block in func_ir.blocks.items()}
    scopes = {id(block.scope) for block in first.values()}
    assert len(scopes) == 1 and id(func_ir.blocks[0].scope) not in scopes
    original = {id(stmt) for block in func_ir.blocks.values() for stmt in block.body}
    assert not original & {id(stmt) for block in first.values() for stmt in block.body}
    assert [str(b) for b in first.values()] == [str(b) for b in func_ir.blocks.values()]
    # A second copy in another inline_ir call gets a scope of its own.
    copies.scope_copies = {}
    second = copies.deepcopy(func_ir.blocks[0])
    assert id(second.scope) not in scopes
    # Outside inline_ir the stand-in is plain deepcopy: every block its own scope, as numba does.
    copies.scope_copies = None
    a, b = (copies.deepcopy(block) for block in list(func_ir.blocks.values())[:2])
    assert a.scope is not b.scope
    assert isinstance(a, ir.Block) and np.isfinite(_branchy(np.ones(3), 3))
