"""The benchmark's results folder: ``results.jsonl`` (the record) and ``results.csv`` (a flat view).

``results.jsonl`` holds one JSON object per finished cell, appended whole (one write, flushed and
fsynced, with Ctrl-C held off meanwhile), so an interrupted run leaves only complete lines --
and a torn last line, should a crash leave one, is ignored on reading and cut off before the
next append. Everything else in the folder (CSV, plots, tables) is regenerated from it.

One line (schema 1; ``K`` = a ray kind, summaries = {median, min, max, q1, q3, runs}):

    {"schema", "id", "matrix", "tags", "labels": {scene, traversal, frustum, recursion, packet,
     resolution}, "cell": <the cell's identity: scene, plugins per kind, packet, recursion preset,
     size, threads, options, embree, open3d (only when on)>, "config": <engine.render.config.Config.to_dict()>,
     "scene": {name, triangles, lights}, "repeat", "threads",
     "seconds": {"bvh", "plugin_build": {plugin: s}, "frame": summary, "shade": summary,
                 "trace": {K: summary}            # inside the timed renders
                 "replay": {K: summary},          # our plugins on the recorded batches
                 "embree": {K: summary} | null,   # Embree (the embree traversal) on the very same batches
                 "open3d": {K: summary} | null,   # Open3D's RaycastingScene on them (engine.bench.open3d_yardstick)
                 "floor": {K: summary} | null},   # packet cells: the per-ray floor (engine.bench.floor)
     "rays": {K: n, "all": n}, "batches": {K: n}, "packets": {K: n}  # packets traced per frame
     "mrays_per_s": {K: x, "all": x}, "embree_mrays_per_s": {...} | null,
     "ratio_to_embree": {K: ours / Embree Mrays/s, "all": x} | null,
     "open3d_mrays_per_s": {...} | null, "ratio_to_open3d": {K: ours / Open3D Mrays/s, "all": x} | null,
     "checks": {"ours" | "embree" | "open3d": {K: {"checked", "ties", "mismatches"}}},  # answers of
               # the timed replays against the ``single`` reference; a mismatching kind's rate is
               # null -- except Open3D's, kept (and flagged by its mismatch count) up to
               # engine.bench.open3d_yardstick.OPEN3D_MISMATCH_TOLERANCE of the kind's rays
     "fps": {"frame", "trace", "embree_trace", "open3d_trace"},  # 1 / trace seconds of a frame
     "counters": {name: {K: n}}, "counters_by_depth": {name: {K: [n per BVH depth]}},
     "extra": {K: plugin statistics}, "machine": {...}, "started", "wall_seconds",
     "load": {"loadavg_at_start": [1, 5, 15 min], "cpu_share_replay": our CPU seconds / (wall x
              threads) while replaying: near 1 on an idle machine, low when others compete},
     "host": {"before" | "after": {"compute_ms", "memory_ns", "stream_gbps", "threads"},
              "measured": n}}  # the host's speed just before and after the cell
              # (engine.bench.host_speed); "measured": how many times --steady measured the cell;
              # absent in older records
"""
from __future__ import annotations

import csv
import json
import signal
import threading
from contextlib import contextmanager
from pathlib import Path

from engine.core import atomic
from engine.core.types import RAY_KINDS

RESULTS = "results.jsonl"
CSV = "results.csv"
SCHEMA = 1


def free_backup_name(path: Path) -> Path:
    """``results.jsonl.prev``, else ``.prev2``, ``.prev3``, ...: the first name not yet taken, so
    starting afresh again never overwrites an earlier run's backup."""
    candidate, n = path.with_name(path.name + ".prev"), 1
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.name}.prev{n}")
    return candidate


def read_results(path: Path) -> tuple[list, int]:
    """(records, bytes of complete lines) of a results.jsonl; a torn or unreadable line, or a record
    the tables cannot read (``_readable``), is skipped (``skipped_lines`` says which)."""
    records, complete, _ = _read(path)
    return records, complete


def skipped_lines(path: Path) -> tuple[list, int]:
    """(numbers of the complete lines ``read_results`` skips, bytes of a torn last line): what a
    ``--resume`` measures again, for its warning."""
    if not path.is_file():
        return [], 0
    _, complete, skipped = _read(path)
    return skipped, path.stat().st_size - complete


def _read(path: Path) -> tuple[list, int, list]:
    if not path.is_file():
        return [], 0, []
    data = path.read_bytes()
    complete = data.rfind(b"\n") + 1  # anything after the last newline is a torn write
    records, skipped = [], []
    for number, line in enumerate(data[:complete].split(b"\n"), 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except ValueError:
            skipped.append(number)
            continue
        if isinstance(record, dict) and "id" in record and _readable(record):
            records.append(record)
        else:
            skipped.append(number)
    return records, complete, skipped


def _readable(record: dict) -> bool:
    """Whether a cell's record has what the tables read (``csv_row`` takes it): a record edited
    or damaged by hand is skipped, so ``--resume`` measures its cell again rather than failing in
    the reports. Dynamic-path records (``engine.bench.dynamic``) have their own reader."""
    if record.get("kind") == "dynamic":
        return True
    try:
        csv_row(record)
    except (KeyError, TypeError, AttributeError, ValueError, IndexError):
        return False
    return True


def repair(path: Path) -> None:
    """Cut a torn last line off, so the next append starts on a line of its own."""
    if path.is_file():
        _, complete = read_results(path)
        if complete != path.stat().st_size:
            atomic.truncate(path, complete)


@contextmanager
def _sigint_held():
    """Hold off Ctrl-C (delivered right after) while a line is written; main thread only."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def append(path: Path, record: dict) -> None:
    """Append one record as one complete line, flushed to disk."""
    # Strict JSON: a NaN timing becomes null, not a token other readers reject.
    line = json.dumps(atomic.plain_json(record), separators=(",", ":"), allow_nan=False) + "\n"
    with _sigint_held():
        atomic.append_line(path, line)


def _median(summary):
    return None if summary is None else summary.get("median")


def csv_row(r: dict) -> dict:
    """One flat row of a record (medians of the timings)."""
    s = r["seconds"]
    row = {"id": r["id"], "matrix": r["matrix"], "tags": " ".join(r.get("tags", [])),
           "scene": r["scene"]["name"], "scene_label": r["labels"]["scene"], "triangles": r["scene"]["triangles"],
           "traversal": r["labels"]["traversal"], "frustum": r["labels"]["frustum"], "packet": r["labels"]["packet"],
           "recursion": r["labels"]["recursion"], "width": r["cell"]["width"], "height": r["cell"]["height"],
           "threads": r["threads"], "repeat": r["repeat"],
           "frame_s": _median(s["frame"]), "frame_min_s": s["frame"]["min"], "frame_max_s": s["frame"]["max"],
           "shade_s": _median(s["shade"]), "bvh_s": s["bvh"],
           "fps_frame": r["fps"]["frame"], "fps_trace": r["fps"]["trace"], "fps_embree_trace": r["fps"]["embree_trace"],
           "fps_open3d_trace": r["fps"].get("open3d_trace"),
           "rays_all": r["rays"]["all"], "mrays_all": r["mrays_per_s"]["all"],
           "embree_mrays_all": (r["embree_mrays_per_s"] or {}).get("all"),
           "ratio_all": (r["ratio_to_embree"] or {}).get("all"),
           "open3d_mrays_all": (r.get("open3d_mrays_per_s") or {}).get("all"),
           "ratio_open3d_all": (r.get("ratio_to_open3d") or {}).get("all")}
    open3d_checks = r["checks"].get("open3d") or {}
    for k in RAY_KINDS:
        row[f"rays_{k}"] = r["rays"].get(k, 0)
        row[f"trace_s_{k}"] = _median(s["replay"].get(k))
        row[f"mrays_{k}"] = r["mrays_per_s"].get(k)
        row[f"floor_s_{k}"] = _median((s.get("floor") or {}).get(k))
        row[f"embree_s_{k}"] = _median((s["embree"] or {}).get(k))
        row[f"embree_mrays_{k}"] = (r["embree_mrays_per_s"] or {}).get(k)
        row[f"ratio_{k}"] = (r["ratio_to_embree"] or {}).get(k)
        row[f"open3d_s_{k}"] = _median((s.get("open3d") or {}).get(k))
        row[f"open3d_mrays_{k}"] = (r.get("open3d_mrays_per_s") or {}).get(k)
        row[f"ratio_open3d_{k}"] = (r.get("ratio_to_open3d") or {}).get(k)
        row[f"open3d_mismatches_{k}"] = (open3d_checks.get(k) or {}).get("mismatches")
        for name in ("ray_aabb", "ray_tri"):
            row[f"{name}_{k}"] = r["counters"].get(name, {}).get(k)
    row["cpu_share_replay"] = r.get("load", {}).get("cpu_share_replay")
    host = r.get("host") or {}
    for when in ("before", "after"):
        for name in HOST_MEASURES:
            row[f"host_{name}_{when}"] = (host.get(when) or {}).get(name)
    row["commit"] = r["machine"]["git"]["commit"]
    row["dirty"] = r["machine"]["git"]["dirty"]
    return row


#: The host probe's measures (``engine.bench.host_speed``) and whether a larger value is slower.
HOST_MEASURES = {"compute_ms": True, "memory_ns": True, "stream_gbps": False}


def fastest_host(records: list, fastest: dict | None = None) -> dict:
    """{measure: its fastest value} over the host probes (before and after) of ``records`` and
    the values already in ``fastest``."""
    best = dict(fastest or {})
    for record in records:
        for probe in ((record.get("host") or {}).get(when) for when in ("before", "after")):
            for name, larger_is_slower in HOST_MEASURES.items():
                value = (probe or {}).get(name)
                if value:
                    known = best.get(name)
                    best[name] = value if known is None else (min if larger_is_slower else max)(known, value)
    return best


def host_slowness(record: dict, fastest: dict):
    """How many times slower than ``fastest`` (``fastest_host``) the host ran around a record's
    cell: the largest ratio over its two probes and the measures both have (compute, memory
    latency, streaming bandwidth), 1.0 at the fastest; None without a probe."""
    host = record.get("host")
    if not host:
        return None
    ratios = []
    for probe in (host.get("before") or {}, host.get("after") or {}):
        for name, larger_is_slower in HOST_MEASURES.items():
            value, best = probe.get(name), fastest.get(name)
            if value and best:
                ratios.append(value / best if larger_is_slower else best / value)
    return max(ratios) if ratios else None


def host_slowdown(records: list) -> list:
    """Per record: ``host_slowness`` against the fastest probes of all of ``records`` (None for a
    record without a probe: older runs, other matrix kinds)."""
    fastest = fastest_host(records)
    return [host_slowness(r, fastest) for r in records]


def write_atomic(path: Path, text: str) -> None:
    """Write through a temporary file and rename: readers never see half a file."""
    atomic.write_text(path, text)


def write_csv(path: Path, records: list) -> None:
    """results.csv: one row per record (header only when there is none)."""
    import io

    rows = [csv_row(r) for r in records]
    buffer = io.StringIO()
    if rows:
        writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows({k: ("" if v is None else v) for k, v in row.items()} for row in rows)
    write_atomic(path, buffer.getvalue())
