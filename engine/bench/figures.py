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
    """The machine under a table: the first record's CPU, threads, versions and commit; where
    other records ran on another CPU or thread count (a cluster's workers, a --resume on another
    host), each distinct (CPU, threads) with its count of records, so no table claims one machine
    for rows that did not share it."""
    m = records[0]["machine"]
    dirty = " (with uncommitted changes)" if m["git"]["dirty"] else ""
    hosts = ordered((cpu_label(r["machine"]), r["threads"]) for r in records)
    if len(hosts) == 1:
        where = f"{hosts[0][0]}, {hosts[0][1]} threads"
    else:
        counts = {host: 0 for host in hosts}
        for r in records:
            counts[(cpu_label(r["machine"]), r["threads"])] += 1
        where = "mixed machines: " + "; ".join(f"{cpu}, {threads} threads ({n} row{'s' if n != 1 else ''})"
                                               for (cpu, threads), n in counts.items())
    return (f"{where}; Python {m['python']}, numpy {m['numpy']}, numba "
            f"{m['numba']}, embreex {m['embreex']} (Embree {m['embree']}); commit {m['git']['commit'][:10]}{dirty}")
