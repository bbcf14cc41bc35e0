"""User mistakes in mesh queries: one line naming the argument.

Both subclass ``ValueError`` (so ``except ValueError`` catches every API mistake, as with
trimesh); a wrong *type* also subclasses ``TypeError``.
"""
from engine.core.errors import PacketrtError


class QueryInputError(PacketrtError, ValueError):
    """An argument has the wrong shape or value (names the argument)."""


class QueryTypeError(QueryInputError, TypeError):
    """An argument has the wrong type (a string, an object or complex array...)."""


class BadRayWarning(UserWarning):
    """Some rays had a NaN/inf component, a zero direction or an origin too far from the mesh for
    float32 (``engine.query.frame.FAR_ORIGIN`` mesh sizes); they were answered as misses."""
