"""User mistakes in mesh queries: one line naming the argument.

Both subclass ``ValueError`` (so ``except ValueError`` catches every API mistake, as with
trimesh); a wrong *type* also subclasses ``TypeError``.
"""
import sys
from pathlib import Path

from engine.core.errors import PacketrtError

#: The package whose frames a warning skips to reach the caller's line.
_ENGINE = str(Path(__file__).resolve().parents[1])


class QueryInputError(PacketrtError, ValueError):
    """An argument has the wrong shape or value (names the argument)."""


class QueryTypeError(QueryInputError, TypeError):
    """An argument has the wrong type (a string, an object or complex array...)."""


class BadRayWarning(UserWarning):
    """Some rays had a NaN/inf component, a zero direction or an origin too far from the mesh for
    float32 (``engine.query.frame.FAR_ORIGIN`` mesh sizes); they were answered as misses."""


def caller_stacklevel() -> int:
    """The ``stacklevel`` for ``warnings.warn`` called from inside ``engine`` that names the
    first frame outside it (the user's call). A fixed level named a decorator's line in
    ``engine/core/threads.py`` instead, and Python's default filter, once per location, then
    hid the warning of every later call."""
    level, frame = 1, sys._getframe(1)
    while frame is not None and frame.f_code.co_filename.startswith(_ENGINE):
        level += 1
        frame = frame.f_back
    return level
