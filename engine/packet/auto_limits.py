"""The ``auto`` chooser's thresholds: the fitted ones from ``auto_thresholds.json`` beside this
file (written by ``tools/fit_auto.py``), and their checked conversion to the kernel's array.

The file holds ``{"limits": {name: value}, "fit": {...how they were fitted...}}`` with the
names of ``engine.packet.choose.LIMIT_NAMES``: ``ranged_max_footprint``,
``masked_max_footprint`` (numbers; a packet's footprint is a fraction of the scene diagonal),
``min_live`` (a fraction of lanes, 0..1) and ``invalid_frustum`` (the strategy for packets
without a frustum: "ranged", "partition" or "masked").
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from engine.core.errors import ConfigError
from engine.packet.choose import INVALID_CHOICE, LIMIT_NAMES, MASKED_MAX, MIN_LIVE, N_LIMITS, RANGED_MAX
from engine.packet.strategies import CHOSEN_NAMES

THRESHOLDS_FILE = Path(__file__).with_name("auto_thresholds.json")


def fitted_limits(path: Path = THRESHOLDS_FILE) -> dict:
    """{limit name: value} as fitted (the file's "limits")."""
    data = json.loads(Path(path).read_text())
    return dict(data["limits"])


def limits_array(limits: dict, where: str = "options.auto") -> np.ndarray:
    """f64[N_LIMITS] for the kernel from {name: value} (every name of LIMIT_NAMES); a missing,
    unknown or bad value is a ConfigError naming ``where``."""
    unknown = set(limits) - set(LIMIT_NAMES)
    missing = set(LIMIT_NAMES) - set(limits)
    if unknown or missing:
        raise ConfigError(f"{where}: limits must be exactly {', '.join(LIMIT_NAMES)}"
                          f" (unknown {sorted(unknown)}, missing {sorted(missing)})")
    out = np.zeros(N_LIMITS, np.float64)
    for name, index in (("ranged_max_footprint", RANGED_MAX), ("masked_max_footprint", MASKED_MAX),
                        ("min_live", MIN_LIVE)):
        value = limits[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
            raise ConfigError(f"{where}.{name} must be a number, got {value!r}")
        if name == "min_live" and not 0.0 <= value <= 1.0:
            raise ConfigError(f"{where}.min_live is a fraction of a packet's lanes, in 0..1, got {value!r}")
        out[index] = float(value)
    choice = limits["invalid_frustum"]
    if choice not in CHOSEN_NAMES:
        raise ConfigError(f"{where}.invalid_frustum must be one of {', '.join(CHOSEN_NAMES)}, got {choice!r}")
    out[INVALID_CHOICE] = CHOSEN_NAMES.index(choice)
    return out
