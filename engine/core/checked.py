"""Checked conversions: the one way a number from a user (a config key, a scene parameter, a
word in a scene file, a command-line value) enters the engine.

Each function takes the raw value, ``where`` (what names it for the user: ``"cfg.toml
[render] width"``, ``"box.mtl:7: 'illum'"``), the allowed range and the error class to raise,
and either returns a plain ``int``/``float`` or raises one line that says where, what was
expected and what was given. NaN, infinities and anything beyond ``COORDINATE_LIMIT`` never get
through, so nothing becomes ``inf`` when it is later stored as float32.
"""
from __future__ import annotations

import math

import numpy as np

from engine.core.errors import ConfigError, ConfigTypeError

#: The largest magnitude any number may have: float32 holds up to 3.4e38, and products of two
#: coordinates (dot products, squared lengths) must stay finite long before that.
COORDINATE_LIMIT = 1e30


def _type_error(error):
    """The TypeError-flavoured class for ``error`` (a config mistake of the wrong type)."""
    return ConfigTypeError if error is ConfigError else error


def _span(lo, hi, integer: bool) -> str:
    if integer:
        return f"an integer in {lo}..{hi}"
    return f"a number in [{lo:g}, {hi:g}]"


def _range(lo, hi) -> str:
    return f"in {lo}..{hi}"


def one_of(value, where: str, allowed: tuple, error=ConfigError) -> str:
    """``value`` if it is one of the words ``allowed``, else ``error`` naming them."""
    if not isinstance(value, str) or value not in allowed:
        raise error(f"{where} must be one of {', '.join(map(repr, allowed))}, got {value!r}")
    return value


def is_flag(value) -> bool:
    """Whether ``value`` is a yes/no argument as Python callers pass them: True, False (numpy's
    too) or 1 / 0 -- not a string ("no" would read as yes) or an array."""
    return isinstance(value, (bool, np.bool_)) or (isinstance(value, (int, np.integer)) and value in (0, 1))


def to_int(value, where: str, lo: int, hi: int, error=ConfigError) -> int:
    """``value`` (a Python or numpy integer, not a bool) if lo <= value <= hi, else ``error``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise _type_error(error)(f"{where} must be {_span(lo, hi, True)}, got {value!r}")
    if not lo <= value <= hi:
        raise error(f"{where} must be {_range(lo, hi)}, got {value}")
    return int(value)


def to_float(value, where: str, lo: float = -COORDINATE_LIMIT, hi: float = COORDINATE_LIMIT,
             error=ConfigError) -> float:
    """``value`` (int or float, not a bool) as a float if finite and within [lo, hi]."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise _type_error(error)(f"{where} must be {_span(lo, hi, False)}, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise error(f"{where} is not finite: must be {_span(lo, hi, False)}, got {value!r}")
    if not lo <= number <= hi:
        raise error(f"{where} must be {_span(lo, hi, False)}, got {value!r}")
    return number


def parse_int(text: str, where: str, lo: int, hi: int, error=ConfigError) -> int:
    """An integer word of a file or command line (``"3"``; ``"3.0"`` and ``"nan"`` are not)."""
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise error(f"{where} must be {_span(lo, hi, True)}, got {text!r}") from None
    return to_int(value, where, lo, hi, error)


def parse_float(text: str, where: str, lo: float = -COORDINATE_LIMIT, hi: float = COORDINATE_LIMIT,
                error=ConfigError) -> float:
    """A number word of a file or command line, finite and within [lo, hi]."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise error(f"{where} must be {_span(lo, hi, False)}, got {text!r}") from None
    return to_float(value, where, lo, hi, error)


def vector(values, where: str, n: int = 3, lo: float = -COORDINATE_LIMIT, hi: float = COORDINATE_LIMIT,
           error=ConfigError) -> tuple:
    """A tuple of ``n`` checked floats (a colour, a position) from a list, tuple or array."""
    if isinstance(values, (str, bytes)) or not hasattr(values, "__len__") or len(values) != n:
        raise _type_error(error)(f"{where} must be {n} numbers in [{lo:g}, {hi:g}], got {values!r}")
    return tuple(to_float(v, f"{where}[{k}]", lo, hi, error) for k, v in enumerate(values))


def array(values: np.ndarray, where, lo: float = -COORDINATE_LIMIT, hi: float = COORDINATE_LIMIT,
          error=ConfigError) -> np.ndarray:
    """f64 ``values`` unchanged if every element is finite and within [lo, hi]; else ``error``
    naming the first bad element. ``where(index)`` may be a function of the flat index (to name
    a file's line), or a string."""
    values = np.asarray(values, np.float64)
    bad = ~(np.isfinite(values) & (values >= lo) & (values <= hi))
    if bad.any():
        index = int(np.flatnonzero(bad)[0])
        name = where(index) if callable(where) else f"{where} (element {index})"
        value = float(values.flat[index])
        problem = "must be" if math.isfinite(value) else "is not finite: must be"
        raise error(f"{name} {problem} {_span(lo, hi, False)}, got {value!r}")
    return values
