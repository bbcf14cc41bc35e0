"""The assembly numba makes for a function, comparable across compiles in one process."""
from __future__ import annotations

import re

import numba

#: What differs between two compiles of the same code: the version numba gives each new
#: dispatcher in its symbol names (``B2v17B``), the parallel loop's address in its name, and the
#: sizes of the error strings that quote those names (one more digit, one more byte).
PER_COMPILE = re.compile(r"B\d+v\d+B|0x[0-9a-f]+|^\s*\.size\s+\"\.const\..*$", re.MULTILINE)


def machine_code(py_func, signature, parallel: bool = False) -> str:
    """Assembly of ``py_func`` compiled afresh (no cache) for ``signature``, the per-compile
    numbers (``PER_COMPILE``) taken out."""
    dispatcher = numba.njit(parallel=parallel)(py_func)
    dispatcher.compile(signature)
    return PER_COMPILE.sub("_", dispatcher.inspect_asm(dispatcher.signatures[0]))
