"""Helpers every benchmark figure and table shares: number format, record order, matplotlib
(Agg, imported only when a figure is drawn), the machine line under each table."""
from __future__ import annotations

from pathlib import Path

from engine.bench.machine import cpu_label
from engine.core.atomic import replacing
from engine.core.types import RAY_KINDS


def trace_seconds(r: dict, kinds=RAY_KINDS, stat: str = "median") -> float:
    """Our trace time per frame over ``kinds`` (sum of per-kind statistics)."""
    return sum(r["seconds"]["replay"][k][stat] for k in kinds)


def ordered(values) -> list:
    return list(dict.fromkeys(values))


def fmt(value, digits: int = 2) -> str:
    if value is None:
        return "–"
    return f"{value:,.{digits}f}"


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: Path) -> Path:
    with replacing(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    pyplot().close(fig)
    return path


def machine_line(records: list) -> str:
    m = records[0]["machine"]
    dirty = " (with uncommitted changes)" if m["git"]["dirty"] else ""
    return (f"{cpu_label(m)}, {records[0]['threads']} threads; Python {m['python']}, numpy {m['numpy']}, numba "
            f"{m['numba']}, embreex {m['embreex']} (Embree {m['embree']}); commit {m['git']['commit'][:10]}{dirty}")
