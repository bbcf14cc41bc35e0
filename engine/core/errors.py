"""User-facing errors.

Anything a user can cause (a bad file, key, name, size or budget) raises
``PacketrtError`` with one line that names the cause; the CLI prints it and exits
with code 2, never with a traceback.

Python callers catch them the way they expect: every ``PacketrtError`` is a ``ValueError``
(a value the user gave is not allowed), and a value of the wrong *type* raises
``ConfigTypeError``, which is also a ``TypeError``. ``except PacketrtError`` still catches all.
"""


class PacketrtError(ValueError):
    """A user mistake, reported as one line and exit code 2."""


class SceneError(PacketrtError):
    """A scene file is missing or malformed; the message names file and line."""


class SceneTypeError(SceneError, TypeError):
    """Geometry of the wrong type (vertices of strings, objects or complex numbers)."""


class ConfigError(PacketrtError):
    """A config key, value or plugin name is not allowed; the message lists what is."""


class ConfigTypeError(ConfigError, TypeError):
    """A config or parameter value has the wrong type (a string where a number belongs)."""


def memory_errors_as(error_type):
    """Decorator: a MemoryError inside the call (numpy's, for a query of more rays than the
    memory that is free) becomes ``error_type`` (a ValueError: the input was too large), one
    line naming the call; the API's callers then catch one kind of error for every bad input."""
    import functools

    def wrap(method):
        @functools.wraps(method)
        def call(*args, **kwargs):
            try:
                return method(*args, **kwargs)
            except MemoryError as exc:
                raise error_type(f"{method.__name__}: not enough free memory for this input ({exc}); "
                                 f"split it into smaller calls") from None
        return call
    return wrap
