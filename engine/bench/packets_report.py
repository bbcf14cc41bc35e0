"""The ``packets`` report: the large-packet study (Overbeck, Ramamoorthi, Mark 2008) as the
issue states it -- Mrays/s per ray kind for every traversal x packet size x culling on/off,
Embree on the same rays, the targets, and a cost model of where the time goes.

It reads the cells whose every ray kind uses a packet traversal (simd, masked, ranged,
partition; ``paper`` mixes them), one section per scene x recursion x image size.

packets.md
    1. One table per ray kind: rows traversal x culling (on = the cell's frustum builders, off =
       ``none``), columns packet sizes, Mrays/s (median replay); last row Embree on the same
       batches (per packet size: a frame's rays are ordered packet by packet, so each size is
       its own batch set).
    2. Targets: trace FPS of each traversal at 16x16 with culling over the 2x2 SIMD baseline
       (``simd``, smallest packet, no culling); culling benefit (on / off) on primary and shadow
       rays; ratio to Embree per kind.
    3. The per-ray floor (``engine.bench.floor``, measured per cell): trace, floor and walk
       (trace - floor) time of the baseline and every 16x16 cell, the speed-ups of the whole
       trace and of the walk alone, and the bound on the speed-up if the walk cost nothing.
    4. Cost model: per ray kind, a non-negative least-squares fit over the cells of
           walk core seconds = a * packets + b * node visits + c * SIMD box tests
                               + d * SIMD triangle tests
       (core seconds = seconds x threads; a SIMD test = 4 ray tests), in ns per operation.
packets.png
    Mrays/s vs packet size, one panel per ray kind, a colour per traversal, solid with culling
    and dashed without, Embree dotted grey.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from engine.bench.figures import fmt, machine_line, ordered, pyplot, save, trace_seconds
from engine.core.atomic import write_text
from engine.core.types import RAY_KINDS

#: Targets of the issue: 16x16 over 2x2 SIMD for the frame, culling benefit (primary and
#: shadow rays), ours / Embree per kind.
TARGET_SPEEDUP = 3.0
TARGET_CULLING = 1.2
TARGET_EMBREE = {"primary": 1.5, "shadow": 1.5, "reflection": 0.75, "refraction": 0.75}
LARGE = 16
PACKET_TRAVERSALS = frozenset({"simd", "masked", "ranged", "partition", "auto"})
COST_TERMS = ("packets", "node visits", "SIMD box tests", "SIMD triangle tests")


def _culling(r: dict) -> str:
    return "off" if r["labels"]["frustum"] == "none" else "on"


def _rate(r: dict, kind: str):
    return (r["mrays_per_s"] or {}).get(kind)


def _embree_rate(r: dict, kind: str):
    return (r["embree_mrays_per_s"] or {}).get(kind)


def _met(value, target) -> str:
    if value is None:
        return "–"
    return "met" if value >= target else "not met"


def _baseline(records: list):
    """The 2x2 SIMD baseline: ``simd`` without culling at its smallest packet, or None."""
    simd = [r for r in records if r["labels"]["traversal"] == "simd" and _culling(r) == "off"]
    return min(simd, key=lambda r: r["labels"]["packet"]) if simd else None


# -- floor and cost model ------------------------------------------------------------------------

def floor_seconds(r: dict, kinds=RAY_KINDS):
    """The cell's measured per-ray floor (``engine.bench.floor``) over ``kinds``, or None."""
    floor = r["seconds"].get("floor")
    return None if floor is None else sum(floor[k]["median"] for k in kinds)


def cost_features(r: dict, kind: str):
    """(packets, node visits, SIMD box tests, SIMD triangle tests) of one cell's ``kind`` rays
    per frame, or None when the record lacks counters, packet counts or the floor."""
    counters = r.get("counters") or {}
    packets = r.get("packets")
    if not packets or r["seconds"].get("floor") is None or \
            not all(name in counters for name in ("nodes", "ray_aabb", "ray_tri")):
        return None
    return (packets[kind], counters["nodes"][kind], counters["ray_aabb"][kind] / 4, counters["ray_tri"][kind] / 4)


def nonnegative_fit(a: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares x >= 0 for a @ x ~ y (a: f64[M,N], y: f64[M]): fit, drop the most negative
    term, refit, until none is negative (an active-set approximation, enough for 4 terms)."""
    active = list(range(a.shape[1]))
    x = np.zeros(a.shape[1])
    while active:
        sol, *_ = np.linalg.lstsq(a[:, active], y, rcond=None)
        if sol.min() >= 0:
            x[active] = sol
            break
        active.pop(int(np.argmin(sol)))
    return x


def cost_model(records: list, kind: str):
    """Fit of the walk's core seconds ((replay - floor) x threads) of ``kind`` rays over the
    cells: {"ns": core ns per operation (COST_TERMS order), "median_error": relative, "cells":
    how many cells were fitted}, or None with fewer than twice as many usable cells as terms."""
    rows, times = [], []
    for r in records:
        features = cost_features(r, kind)
        if features is None or not r["rays"][kind]:
            continue
        walk = r["seconds"]["replay"][kind]["median"] - r["seconds"]["floor"][kind]["median"]
        if walk <= 0:
            continue
        rows.append(features)
        times.append(walk * r["threads"])
    if len(rows) < 2 * len(COST_TERMS):
        return None
    a, y = np.asarray(rows, np.float64), np.asarray(times, np.float64)
    # Scale columns to comparable sizes so the solver is well conditioned.
    scale = np.maximum(a.max(axis=0), 1.0)
    x = nonnegative_fit(a / scale, y) / scale
    return {"ns": x * 1e9, "median_error": float(np.median(np.abs(a @ x - y) / y)), "cells": len(rows)}


# -- report ------------------------------------------------------------------------------------

def _rate_tables(records: list, packets: list, travs: list) -> list:
    lines = []
    for kind in RAY_KINDS:
        if not any(r["rays"][kind] for r in records):
            continue
        rays = max(r["rays"][kind] for r in records)
        lines += [f"**{kind} rays** ({rays:,} per frame), Mrays/s:", "",
                  "| traversal | culling | " + " | ".join(f"{p}×{p}" for p in packets) + " |",
                  "|---|---|" + "---:|" * len(packets)]
        for trav in travs:
            for culling in ("on", "off"):
                by_packet = {r["labels"]["packet"]: r for r in records
                             if r["labels"]["traversal"] == trav and _culling(r) == culling}
                if by_packet:
                    lines.append(f"| {trav} | {culling} | " + " | ".join(
                        fmt(_rate(by_packet[p], kind)) if p in by_packet else "" for p in packets) + " |")
        embree = {p: [_embree_rate(r, kind) for r in records
                      if r["labels"]["packet"] == p and _embree_rate(r, kind)] for p in packets}
        if any(embree.values()):
            lines.append("| Embree | – | " + " | ".join(
                fmt(float(np.median(embree[p]))) if embree[p] else "" for p in packets) + " |")
        lines.append("")
    return lines


def _target_lines(records: list, travs: list) -> list:
    lines = ["### Targets", ""]
    base = _baseline(records)
    large = {(r["labels"]["traversal"], _culling(r)): r for r in records if r["labels"]["packet"] == LARGE}
    if base is not None:
        p = base["labels"]["packet"]
        lines += [f"Frame trace FPS (all ray kinds, frustum build + traversal) at {LARGE}×{LARGE} with culling, "
                  f"over the {p}×{p} SIMD baseline (`simd`, no culling: {1 / trace_seconds(base):.2f} FPS); "
                  f"target {TARGET_SPEEDUP:g}×.", "",
                  "| traversal | FPS | speed-up | target |", "|---|---:|---:|---|"]
        for trav in travs:
            r = large.get((trav, "on"))
            if r is not None:
                speedup = trace_seconds(base) / trace_seconds(r)
                lines.append(f"| {trav} | {1 / trace_seconds(r):.2f} | {speedup:.2f}× | "
                             f"{_met(speedup, TARGET_SPEEDUP)} |")
        lines.append("")
    lines += [f"Culling benefit at {LARGE}×{LARGE} (Mrays/s with / without); target {TARGET_CULLING:g}× on "
              "primary and shadow rays.", "",
              "| traversal | " + " | ".join(RAY_KINDS) + " |", "|---|" + "---:|" * len(RAY_KINDS)]
    for trav in travs:
        on, off = large.get((trav, "on")), large.get((trav, "off"))
        if on is None or off is None:
            continue
        cells = []
        for kind in RAY_KINDS:
            a, b = _rate(on, kind), _rate(off, kind)
            benefit = a / b if a and b else None
            mark = f" ({_met(benefit, TARGET_CULLING)})" if kind in ("primary", "shadow") and benefit else ""
            cells.append(f"{fmt(benefit)}×{mark}" if benefit else "–")
        lines.append(f"| {trav} | " + " | ".join(cells) + " |")
    lines += ["", f"Ours / Embree at {LARGE}×{LARGE} with culling; targets "
              + ", ".join(f"{k} {v:g}×" for k, v in TARGET_EMBREE.items()) + ".", "",
              "| traversal | " + " | ".join(RAY_KINDS) + " |", "|---|" + "---:|" * len(RAY_KINDS)]
    for trav in travs:
        r = large.get((trav, "on"))
        if r is None or not r["ratio_to_embree"]:
            continue
        cells = []
        for kind in RAY_KINDS:
            ratio = r["ratio_to_embree"].get(kind)
            cells.append(f"{fmt(ratio)}× ({_met(ratio, TARGET_EMBREE[kind])})" if ratio else "–")
        lines.append(f"| {trav} | " + " | ".join(cells) + " |")
    lines.append("")
    return lines


def _floor_lines(records: list) -> list:
    base = _baseline(records)
    cells = [r for r in records if r["labels"]["packet"] == LARGE and floor_seconds(r) is not None]
    if base is None or floor_seconds(base) is None or not cells:
        return []
    b_trace, b_floor = trace_seconds(base), floor_seconds(base)
    p = base["labels"]["packet"]
    lines = ["### Where the time goes: the per-ray floor", "",
             "*Floor*: the same batches through the same frustum builders and packet adapter with the BVH walk "
             "taken out (`engine/bench_floor.py`: answer arrays, ray load and shear, frustum pass, hit store), "
             "which every traversal pays alike. *Walk* = trace − floor. *Bound*: the speed-up over the "
             f"{p}×{p} baseline if the {LARGE}×{LARGE} walk cost nothing (baseline trace / {LARGE}×{LARGE} floor).", "",
             "| traversal | culling | packet | trace ms | floor ms | floor share | walk ms | speed-up | walk speed-up "
             "| bound |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
             f"| {base['labels']['traversal']} | {_culling(base)} | {p} | {b_trace * 1e3:,.1f} | {b_floor * 1e3:,.1f} | "
             f"{b_floor / b_trace * 100:.0f}% | {(b_trace - b_floor) * 1e3:,.1f} | 1.00× | 1.00× | – |"]
    for r in cells:
        trace, floor = trace_seconds(r), floor_seconds(r)
        walk = trace - floor
        lines.append(f"| {r['labels']['traversal']} | {_culling(r)} | {LARGE} | {trace * 1e3:,.1f} | {floor * 1e3:,.1f} | "
                     f"{floor / trace * 100:.0f}% | {walk * 1e3:,.1f} | {b_trace / trace:.2f}× | "
                     f"{fmt((b_trace - b_floor) / walk if walk > 0 else None)}× | {b_trace / floor:.2f}× |")
    lines.append("")
    return lines


def _cost_lines(records: list) -> list:
    lines = ["### The walk's cost per operation", "",
             "Per ray kind, a non-negative least-squares fit over the cells: walk core seconds ((trace − floor) × "
             "threads) ≈ a·packets + b·node visits + c·SIMD box tests + d·SIMD triangle tests (counts from the "
             "counting render; a SIMD test is one 2×2 SIMD ray against one box or triangle).", "",
             "| ray kind | cells | ns / packet | ns / node visit | ns / SIMD box test | ns / SIMD triangle test "
             "| median error |", "|---|---:|---:|---:|---:|---:|---:|"]
    fitted = False
    for kind in RAY_KINDS:
        model = cost_model(records, kind)
        if model is None:
            continue
        fitted = True
        lines.append(f"| {kind} | {model['cells']} | " + " | ".join(f"{v:.2f}" for v in model["ns"])
                     + f" | {model['median_error'] * 100:.1f}% |")
    lines.append("")
    return lines if fitted else []


def _plot(records: list, travs: list, path: Path) -> Path:
    plt = pyplot()
    kinds = [k for k in RAY_KINDS if any(r["rays"][k] for r in records)]
    fig, axes = plt.subplots(1, len(kinds), figsize=(3.4 * len(kinds), 3.2), squeeze=False)
    packets = sorted({r["labels"]["packet"] for r in records})
    for ax, kind in zip(axes[0], kinds):
        for i, trav in enumerate(travs):
            for culling, style in (("on", "-"), ("off", "--")):
                rs = sorted((r for r in records if r["labels"]["traversal"] == trav and _culling(r) == culling
                             and _rate(r, kind)), key=lambda r: r["labels"]["packet"])
                if rs:
                    ax.plot([r["labels"]["packet"] for r in rs], [_rate(r, kind) for r in rs], "o" + style,
                            color=f"C{i % 10}", ms=3, lw=1.2, label=f"{trav} ({'culling' if culling == 'on' else 'none'})")
        embree = {}
        for r in records:
            if _embree_rate(r, kind):
                embree.setdefault(r["labels"]["packet"], []).append(_embree_rate(r, kind))
        if embree:
            xs = sorted(embree)
            ax.plot(xs, [float(np.median(embree[p])) for p in xs], "x:", color="0.4", label="Embree")
        ax.set_xscale("log", base=2)
        ax.set_xticks(packets, [f"{p}×{p}" for p in packets], fontsize=7)
        ax.minorticks_off()
        ax.set_ylim(bottom=0)
        ax.tick_params(labelsize=7)
        ax.set_title(f"{kind} rays", fontsize=9)
        ax.set_xlabel("packet size", fontsize=8)
    axes[0][0].set_ylabel("Mrays/s (median)", fontsize=8)
    handles = {}
    for ax in axes.flat:
        for h, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, h)
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=min(5, len(handles)), fontsize=7,
               bbox_to_anchor=(0.5, -0.12))
    lab = records[0]["labels"]
    fig.suptitle(f"{lab['scene']} {lab['recursion']} {lab['resolution']}: Mrays/s per ray kind", fontsize=10)
    fig.tight_layout()
    return save(fig, path)


def packet_cells(records: list) -> dict:
    """{(scene, recursion, resolution): records} of the cells whose every ray kind uses one of
    the packet traversals (the study's subject; ``single``, ``rayspace`` and Embree cells are left
    out), in matrix order."""
    groups = {}
    for r in records:
        if all(name in PACKET_TRAVERSALS for name in r["cell"]["traversal"].values()):
            lab = r["labels"]
            groups.setdefault((lab["scene"], lab["recursion"], lab["resolution"]), []).append(r)
    return groups


def packets(records: list, out: Path) -> list:
    """packets.md and packets.png (see the module doc), a section and a figure per scene,
    recursion and size (packets-2.png ... after the first); nothing when no record fits."""
    groups = packet_cells(records)
    if not groups:
        return []
    lines = ["# Large packets: Mrays/s per ray kind, traversal × packet size × culling", "",
             f"Machine: {machine_line(records)}.", "",
             "Mrays/s = rays of the kind per frame / median replay time of their batches (frustum build + "
             "traversal, shading excluded). Culling *on* uses the cell's frustum builders (pinhole, pointlight, "
             "general), *off* none. Embree traces the very same batches in the same run with the same threads.", ""]
    figures = []
    for i, ((scene, recursion, size), rs) in enumerate(groups.items()):
        packet_sizes = sorted({r["labels"]["packet"] for r in rs})
        travs = ordered(r["labels"]["traversal"] for r in rs)
        lines += [f"## {scene}, {recursion}, {size}", ""]
        lines += _rate_tables(rs, packet_sizes, travs)
        lines += _target_lines(rs, travs)
        lines += _floor_lines(rs)
        lines += _cost_lines(rs)
        figures.append(_plot(rs, travs, out / ("packets.png" if i == 0 else f"packets-{i + 1}.png")))
    md = out / "packets.md"
    write_text(md, "\n".join(lines) + "\n")
    return [md, *figures]
