"""numba's inliner made linear: one copy of a callee's scope per copy of its IR, not one per block.

Every ``inline="always"`` helper (the traversals, triangle tests and shading lanes share code
this way) is inlined by ``numba.core.inline_closurecall.InlineWorker.inline_ir``. It copies the
callee's IR twice, and each copy deep-copies the IR *block by block*, every block with a fresh
memo. A block's variables point at the function's one ``Scope``, which holds every variable of
the function, so each block drags a whole copy of the scope along: the copy costs blocks x
variables. For a packet walk (hundreds of blocks and thousands of variables after its helpers
are inlined) that was more than half of a cold compile: 2.5 of the 5.1 s of ``walk_ranged``
compiled without ``parallel`` (the default scene's signature), 2.5 of 9.3 s with it.

``use_linear_inline_copies`` gives that module a stand-in for ``copy`` whose ``deepcopy`` copies
a block with its scope already mapped to one copy of that scope, made once per IR copy (during
one ``inline_ir`` call, keyed by the scope being copied). Everything else in a block is copied as
before, one block at a time. The copies therefore differ from numba's only in that the blocks of
one copied IR share one scope, as the blocks of the IR they were copied from do; numba's inliner
replaces every inlined block's scope by the caller's right after (and asserts that a callee has
a single scope, by equality). The machine code numba makes is the same byte for byte (checked on
the packet walks; ``tests/test_jit_inlining.py`` compares a kernel's assembly with and without),
and numba's own inlining tests pass with it (``tools/numba_stand_ins_check.py``).

The same cost is numba-cuda issue #688 (an open pull request there removes one of the two
copies); numba 0.68 still copies this way. If numba's module no longer looks as described here
(no module-level ``copy``, no ``InlineWorker.inline_ir``), nothing is changed.
"""
from __future__ import annotations

import copy
import functools

from numba.core import inline_closurecall, ir


class _InlinerCopies:
    """Stands in for the ``copy`` module inside ``numba.core.inline_closurecall``."""

    def __init__(self):
        # {id(scope): (scope, its copy)} while one inline_ir call runs, else None. The scope is
        # kept in the entry so that its id cannot be reused by another object meanwhile.
        self.scope_copies = None

    def __getattr__(self, name):
        return getattr(copy, name)

    def deepcopy(self, x, memo=None):
        if memo is not None or self.scope_copies is None or not isinstance(x, ir.Block):
            return copy.deepcopy(x, memo)
        entry = self.scope_copies.get(id(x.scope))
        if entry is None:
            entry = self.scope_copies[id(x.scope)] = (x.scope, copy.deepcopy(x.scope))
        return copy.deepcopy(x, {id(x.scope): entry[1]})


def _scope_copies_per_call(inline_ir, copies: _InlinerCopies):
    """``inline_ir`` run with a fresh table of scope copies, so that no two calls share one."""

    @functools.wraps(inline_ir)
    def inline_ir_with_linear_copies(self, *args, **kwargs):
        outer, copies.scope_copies = copies.scope_copies, {}
        try:
            return inline_ir(self, *args, **kwargs)
        finally:
            copies.scope_copies = outer

    inline_ir_with_linear_copies.packetrt_linear_copies = True
    return inline_ir_with_linear_copies


def use_linear_inline_copies() -> bool:
    """Install the stand-in (see the module doc); idempotent. Returns whether it is installed."""
    worker = getattr(inline_closurecall, "InlineWorker", None)
    inline_ir = getattr(worker, "inline_ir", None)
    if inline_ir is None or getattr(inline_closurecall, "copy", None) is not copy:
        return getattr(inline_ir, "packetrt_linear_copies", False)
    copies = _InlinerCopies()
    inline_closurecall.copy = copies
    worker.inline_ir = _scope_copies_per_call(inline_ir, copies)
    return True
