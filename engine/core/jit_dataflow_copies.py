"""numba's data-flow passes copy their sets of variable names by ``copy.deepcopy``; a shallow copy
of each set is the same copy, at a fraction of the cost.

Every ``parallel=True`` kernel goes through numba's copy propagation (``ir_utils.copy_propagate``,
run by the parfor passes' ``simplify``) and alias analysis (``find_potential_aliases``). Both copy
a dict of sets of variable names (str, or pairs of str) with ``copy.deepcopy``, the first at every
step of its fixed-point iteration. deepcopy visits every string of every set; but strings and
tuples of strings cannot change, so copying each set is enough. On a packet walk this was 0.5-1.3 s
of its 6-7 s cold compile.

``use_shallow_dataflow_copies`` gives ``numba.core.ir_utils`` a stand-in for ``copy`` whose
``deepcopy`` copies exactly such a dict set by set (sets shared between keys stay shared, as
deepcopy's memo keeps them) and hands anything else to ``copy.deepcopy``. The machine code numba
makes is the same (``tests/test_jit_dataflow_copies.py``), and numba's own tests of these passes
pass with it (``tools/numba_stand_ins_check.py``).
"""
from __future__ import annotations

import copy

from numba.core import ir_utils


def _sets_of_names(x) -> bool:
    """Is ``x`` a dict of sets of variable names (str) or tuples of them: nothing deepcopy would
    need to copy but the sets? Plain loops: this runs on every copy, over every name."""
    if type(x) is not dict:
        return False
    for names in x.values():
        if type(names) is not set:
            return False
        for item in names:
            if type(item) is str:
                continue
            if type(item) is not tuple:
                return False
            for part in item:
                if type(part) is not str:
                    return False
    return True


class _DataflowCopies:
    """Stands in for the ``copy`` module inside ``numba.core.ir_utils``."""

    def __getattr__(self, name):
        return getattr(copy, name)

    def deepcopy(self, x, memo=None):
        if memo is not None or not _sets_of_names(x):
            return copy.deepcopy(x, memo)
        copies = {}
        for key, names in x.items():
            if id(names) not in copies:
                copies[id(names)] = set(names)
        return {key: copies[id(names)] for key, names in x.items()}


def use_shallow_dataflow_copies() -> bool:
    """Install the stand-in (see the module doc); idempotent. Returns whether it is installed
    (False when ``ir_utils`` has no module-level ``copy`` to stand in for)."""
    current = getattr(ir_utils, "copy", None)
    if isinstance(current, _DataflowCopies):
        return True
    if current is not copy:
        return False
    ir_utils.copy = _DataflowCopies()
    return True
