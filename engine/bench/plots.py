"""Figures and tables from benchmark records (``engine.bench.results``): one function per kind.

A matrix picks its kinds with ``plot = [...]``; ``summary`` is always written. Every function
takes (records, out folder) and returns the files it wrote (none when no record fits it).
Times are medians over the repeats; "trace" time is our frustum build + traversal on the
recorded batches (shading excluded), the same work Embree is timed on.

    summary  summary.md: one row per cell (rays, frame and trace time, Mrays/s, ratio to Embree)
    mrays    mrays.png: Mrays/s per cell, ours beside Embree
    fig5     fig5.png: trace time per frame vs packet size, scenes x recursion grid, a line per
             traversal (Overbeck et al. 2008, Figure 5)
    fig6     fig6-<scene>.png: ray-AABB and ray-triangle tests per ray by BVH depth, a bar per
             traversal; fig6-totals.png: the totals (Figure 6)
    fig7     fig7.png: as fig5 with culling on (solid) and off (dashed); fig7.md: the benefit (Figure 7)
    table2   table2.md + table2.png: 2x2 SIMD vs 16x16 packets, culling benefit, Embree (Table 2)
    packets  packets.md + packets.png: Mrays/s per ray kind for traversal x packet size x culling,
             Embree, the issue's targets and a cost model (``engine.bench.packets_report``)
    roger    roger.png + roger.md: secondary-ray time and candidates per ray vs reflector
             triangles (tag "lod"), image size (tag "resolution") and cosine-n's n (tag "cosine")
             (Roger et al. 2007)

matplotlib is imported (Agg backend) only when a figure is drawn.
"""
from __future__ import annotations

from pathlib import Path

from engine.bench import packets_report
from engine.bench.figures import fmt, machine_line, ordered, pyplot, save, trace_seconds
from engine.core.atomic import write_text
from engine.core.types import RAY_KINDS

SECONDARY = ("shadow", "reflection", "refraction")


# -- record helpers ---------------------------------------------------------------------------

def embree_seconds(r: dict, kinds=RAY_KINDS):
    e = r["seconds"]["embree"]
    return None if e is None else sum(e[k]["median"] for k in kinds)


def main_kind(recursion: str) -> str:
    """The ray kind a recursion preset is about (what Figure 6 shows for it)."""
    for kind in ("shadow", "reflection", "refraction"):
        if recursion.startswith(kind[:6]):
            return kind
    return "primary"


def _series_label(r: dict, with_frustum: bool) -> str:
    lab = r["labels"]
    return f"{lab['traversal']} / {lab['frustum']}" if with_frustum else lab["traversal"]


# -- summary ----------------------------------------------------------------------------------

def summary(records: list, out: Path) -> list:
    lines = ["# Benchmark summary", ""]
    if not records:
        lines.append("No finished cells yet.")
    else:
        lines += [f"Machine: {machine_line(records)}.", "",
                  "Times are medians over the repeats; trace = frustum build + traversal on the recorded batches "
                  "(all ray kinds, shading excluded); Embree traces the very same batches.", "",
                  "CPU share = our CPU time / (wall time x threads) while replaying: near 1 on an idle machine, "
                  "lower when other work competed for the cores (treat such rows with care).", "",
                  "| scene | recursion | size | traversal | frustum | packet | rays | frame ms | trace ms | Mrays/s "
                  "| Embree Mrays/s | ours / Embree | CPU share |",
                  "|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in records:
            lab = r["labels"]
            ratio = (r["ratio_to_embree"] or {}).get("all")
            lines.append(f"| {lab['scene']} | {lab['recursion']} | {lab['resolution']} | {lab['traversal']} | "
                         f"{lab['frustum']} | {lab['packet']} | {r['rays']['all']:,} | "
                         f"{r['seconds']['frame']['median'] * 1e3:,.1f} | {trace_seconds(r) * 1e3:,.1f} | "
                         f"{fmt(r['mrays_per_s']['all'])} | {fmt((r['embree_mrays_per_s'] or {}).get('all'))} | "
                         f"{fmt(ratio)} | {fmt(r.get('load', {}).get('cpu_share_replay'))} |")
    path = out / "summary.md"
    write_text(path, "\n".join(lines) + "\n")
    return [path]


# -- mrays --------------------------------------------------------------------------------------

def mrays(records: list, out: Path) -> list:
    if not records:
        return []
    plt = pyplot()
    names = [f"{r['labels']['scene']} {r['labels']['recursion']} {r['labels']['traversal']}/"
             f"{r['labels']['frustum']} {r['labels']['packet']}²" for r in records]
    ours_rate = [r["mrays_per_s"]["all"] or 0 for r in records]
    embree_rate = [(r["embree_mrays_per_s"] or {}).get("all") or 0 for r in records]
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(records) + 1.2))
    y = range(len(records))
    ax.barh([i + 0.2 for i in y], ours_rate, height=0.4, label="ours")
    if any(embree_rate):
        ax.barh([i - 0.2 for i in y], embree_rate, height=0.4, label="Embree (same rays)", color="0.6")
    ax.set_yticks(list(y), names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("Mrays/s, all ray kinds (median)")
    ax.legend(fontsize=8)
    ax.set_title(f"{records[0]['matrix']}: throughput per cell", fontsize=10)
    return [save(fig, out / "mrays.png")]


# -- fig5 / fig7: time per frame vs packet size ----------------------------------------------

def _packet_grid(records: list, out: Path, name: str, culling_styles: bool) -> list:
    rows = ordered(r["labels"]["scene"] for r in records)
    cols = ordered(r["labels"]["recursion"] for r in records)
    if not rows:
        return []
    plt = pyplot()
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(3.4 * len(cols), 2.7 * len(rows)), squeeze=False)
    travs = ordered(r["labels"]["traversal"] for r in records)
    colours = {t: f"C{i % 10}" for i, t in enumerate(travs)}
    with_frustum = not culling_styles and len({r["labels"]["frustum"] for r in records}) > 1
    for i, scene in enumerate(rows):
        for j, rec in enumerate(cols):
            ax = axes[i][j]
            cell = [r for r in records if r["labels"]["scene"] == scene and r["labels"]["recursion"] == rec]
            series = {}
            for r in cell:
                series.setdefault((r["labels"]["traversal"], r["labels"]["frustum"]), []).append(r)
            for (trav, frus), rs in series.items():
                rs = sorted(rs, key=lambda r: r["labels"]["packet"])
                x = [r["labels"]["packet"] for r in rs]
                med = [trace_seconds(r) * 1e3 for r in rs]
                lo = [m - trace_seconds(r, stat="min") * 1e3 for m, r in zip(med, rs)]
                hi = [trace_seconds(r, stat="max") * 1e3 - m for m, r in zip(med, rs)]
                style = "--" if culling_styles and frus == "none" else "-"
                label = (f"{trav} ({'no culling' if frus == 'none' else 'culling'})" if culling_styles
                         else _series_label(rs[0], with_frustum))
                ax.errorbar(x, med, yerr=[lo, hi], fmt="o" + style, ms=3, lw=1.2, capsize=2,
                            color=colours[trav], label=label)
            by_packet = {}
            for r in cell:
                e = embree_seconds(r)
                if e is not None:
                    by_packet.setdefault(r["labels"]["packet"], []).append(e * 1e3)
            if by_packet:
                xs = sorted(by_packet)
                ax.plot(xs, [sorted(by_packet[p])[len(by_packet[p]) // 2] for p in xs], "x:", color="0.4",
                        lw=1.2, ms=5, label="Embree")
            ax.set_xscale("log", base=2)
            packets = sorted({r["labels"]["packet"] for r in cell}) or [16]
            ax.set_xticks(packets, [f"{p}×{p}" for p in packets], fontsize=7)
            ax.minorticks_off()
            ax.set_ylim(bottom=0)
            ax.tick_params(labelsize=7)
            if cell:
                rays = cell[0]["rays"]["all"]
                ax.set_title(f"{scene} — {rec}\n{cell[0]['scene']['triangles']:,} tris, {rays:,} rays, "
                             f"{cell[0]['labels']['resolution']}", fontsize=8)
            if j == 0:
                ax.set_ylabel("trace ms / frame", fontsize=8)
            if i == len(rows) - 1:
                ax.set_xlabel("packet size", fontsize=8)
    handles, labels = {}, {}
    for ax in axes.flat:
        for h, l in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(l, h)
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=min(6, len(handles)), fontsize=8,
               bbox_to_anchor=(0.5, -0.01 - 0.02 * (len(handles) > 6)))
    title = ("Frustum culling on (solid) and off (dashed)" if culling_styles
             else "Time per frame vs packet size")
    fig.suptitle(f"{title}: trace time per frame (frustum build + traversal, shading excluded), median with "
                 f"min–max", fontsize=10)
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    return [save(fig, out / f"{name}.png")]


def fig5(records: list, out: Path) -> list:
    return _packet_grid(records, out, "fig5", culling_styles=False)


def fig7(records: list, out: Path) -> list:
    files = _packet_grid(records, out, "fig7", culling_styles=True)
    rows = ["# Frustum culling benefit (Figure 7)", "",
            "Trace time per frame without culling divided by with culling (median ms); > 1 means culling helps.", "",
            "| scene | recursion | traversal | packet | no culling ms | culling ms | benefit |",
            "|---|---|---|---:|---:|---:|---:|"]
    pairs = {}
    for r in records:
        lab = r["labels"]
        on = "off" if lab["frustum"] == "none" else "on"
        pairs.setdefault((lab["scene"], lab["recursion"], lab["traversal"], lab["packet"]), {})[on] = r
    found = False
    for (scene, rec, trav, packet), both in pairs.items():
        if "on" in both and "off" in both:
            found = True
            off, on = trace_seconds(both["off"]), trace_seconds(both["on"])
            rows.append(f"| {scene} | {rec} | {trav} | {packet} | {off * 1e3:,.1f} | {on * 1e3:,.1f} | "
                        f"{off / on:.2f} |")
    if found:
        path = out / "fig7.md"
        write_text(path, "\n".join(rows) + "\n")
        files.append(path)
    return files


# -- fig6: tests per BVH depth ----------------------------------------------------------------

def fig6(records: list, out: Path) -> list:
    records = [r for r in records if r.get("counters_by_depth")]
    if not records:
        return []
    plt = pyplot()
    files = []
    packets = sorted({r["labels"]["packet"] for r in records})
    packet = 16 if 16 in packets else packets[-1]
    records = [r for r in records if r["labels"]["packet"] == packet]
    travs = ordered(r["labels"]["traversal"] for r in records)
    counters = ("ray_aabb", "ray_tri")
    titles = {"ray_aabb": "ray–AABB tests per ray", "ray_tri": "ray–triangle tests per ray"}
    totals = []
    for scene in ordered(r["labels"]["scene"] for r in records):
        mine = [r for r in records if r["labels"]["scene"] == scene]
        recs = ordered(r["labels"]["recursion"] for r in mine)
        fig, axes = plt.subplots(len(counters), len(recs), figsize=(4.2 * len(recs), 5.4), squeeze=False)
        for j, rec in enumerate(recs):
            kind = main_kind(rec)
            width = 0.8 / max(len(travs), 1)
            for t, trav in enumerate(travs):
                match = [r for r in mine if r["labels"]["recursion"] == rec and r["labels"]["traversal"] == trav]
                if not match:
                    continue
                r = match[0]
                rays = max(r["rays"][kind], 1)
                for i, name in enumerate(counters):
                    depth = r["counters_by_depth"].get(name, {}).get(kind, [])
                    per_ray = [v / rays for v in depth]
                    axes[i][j].bar([d + (t - (len(travs) - 1) / 2) * width for d in range(len(per_ray))], per_ray,
                                   width=width, color=f"C{t}", label=trav)
                    totals.append((scene, rec, kind, trav, name, r["counters"].get(name, {}).get(kind, 0) / rays))
            for i, name in enumerate(counters):
                ax = axes[i][j]
                ax.set_title(f"{rec}: {kind} rays — {titles[name]}", fontsize=8)
                ax.set_xlabel("BVH depth", fontsize=8)
                ax.tick_params(labelsize=7)
        axes[0][0].legend(fontsize=8)
        fig.suptitle(f"{scene}: tests per BVH depth, {packet}×{packet} packets "
                     f"({mine[0]['labels']['resolution']})", fontsize=10)
        fig.tight_layout()
        safe = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in scene)
        files.append(save(fig, out / f"fig6-{safe}.png"))
    if totals:
        groups = ordered((s, rec, k) for s, rec, k, *_ in totals)
        fig, axes = plt.subplots(1, 2, figsize=(max(7.0, 1.3 * len(groups) + 3), 3.6))
        width = 0.8 / max(len(travs), 1)
        for i, name in enumerate(counters):
            ax = axes[i]
            for t, trav in enumerate(travs):
                values = {(s, rec, k): v for s, rec, k, tr, n, v in totals if tr == trav and n == name}
                ax.bar([g + (t - (len(travs) - 1) / 2) * width for g in range(len(groups))],
                       [values.get(key, 0) for key in groups], width=width, color=f"C{t}", label=trav)
            ax.set_xticks(range(len(groups)), [f"{s}\n{k}" for s, rec, k in groups], fontsize=7)
            ax.set_title(titles[name], fontsize=9)
            ax.tick_params(labelsize=7)
        axes[0].legend(fontsize=8)
        fig.suptitle(f"Tests per ray, {packet}×{packet} packets", fontsize=10)
        fig.tight_layout()
        files.append(save(fig, out / "fig6-totals.png"))
    return files


# -- table2 -------------------------------------------------------------------------------------

def table2(records: list, out: Path) -> list:
    groups = {}
    for r in records:
        groups.setdefault((r["labels"]["scene"], r["labels"]["recursion"], r["labels"]["resolution"]), []).append(r)
    rows = []
    for (scene, rec, size), rs in groups.items():
        small = min(rs, key=lambda r: r["labels"]["packet"])
        large = [r for r in rs if r["labels"]["packet"] == 16]
        culled = next((r for r in large if r["labels"]["frustum"] != "none"), None)
        plain = next((r for r in large if r["labels"]["frustum"] == "none"), None)
        if small["labels"]["packet"] >= 16 or culled is None:
            continue
        fps = {name: (1 / trace_seconds(r) if r is not None else None)
               for name, r in (("small", small), ("plain", plain), ("culled", culled))}
        e = embree_seconds(culled)
        rows.append({"scene": scene, "recursion": rec, "size": size, "triangles": culled["scene"]["triangles"],
                     "rays": culled["rays"]["all"], **fps, "embree": 1 / e if e else None,
                     "frame": culled["fps"]["frame"], "small_label": f"{small['labels']['traversal']} "
                     f"{small['labels']['packet']}×{small['labels']['packet']}"})
    if not rows:
        return []
    lines = ["# Table 2: 2×2 SIMD rays vs 16×16 packets", "",
             f"Machine: {machine_line(records)}.", "",
             "FPS = 1 / (trace time per frame): frustum build + traversal of every ray of the frame, median over the "
             "repeats, shading excluded (the Python shading is the same for all columns: see the last column for "
             "whole frames). Embree traces the same rays.", "",
             "| scene | configuration | size | triangles | rays / frame | 2×2 SIMD FPS | 16×16 FPS, no culling | "
             "16×16 FPS | 16×16 / 2×2 | culling benefit | Embree FPS | 16×16 / Embree | whole-frame FPS (16×16) |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        speedup = row["culled"] / row["small"]
        benefit = row["culled"] / row["plain"] if row["plain"] else None
        versus = row["culled"] / row["embree"] if row["embree"] else None
        lines.append(f"| {row['scene']} | {row['recursion']} | {row['size']} | {row['triangles']:,} | "
                     f"{row['rays']:,} | {fmt(row['small'])} | {fmt(row['plain'])} | {fmt(row['culled'])} | "
                     f"{speedup:.2f}× | {fmt(benefit)}× | {fmt(row['embree'])} | {fmt(versus)}× | "
                     f"{fmt(row['frame'])} |")
    md = out / "table2.md"
    write_text(md, "\n".join(lines) + "\n")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(2.2 * len(rows) + 2, 3.6))
    bars = (("small", "2×2 SIMD"), ("plain", "16×16, no culling"), ("culled", "16×16, culling"), ("embree", "Embree"))
    width = 0.2
    for b, (key, label) in enumerate(bars):
        ax.bar([i + (b - 1.5) * width for i in range(len(rows))], [row[key] or 0 for row in rows], width=width,
               label=label, color="0.6" if key == "embree" else f"C{b}")
    ax.set_xticks(range(len(rows)), [f"{row['scene']}\n{row['recursion']}" for row in rows], fontsize=8)
    ax.set_ylabel("FPS (trace only)", fontsize=8)
    ax.legend(fontsize=8)
    ax.set_title(f"Table 2 at {rows[0]['size']}: frames per second of ray tracing", fontsize=10)
    return [md, save(fig, out / "table2.png")]


# -- roger ----------------------------------------------------------------------------------------

def _roger_x(r: dict, tag: str):
    if tag == "lod":
        return r["scene"]["triangles"]
    if tag == "resolution":
        return r["cell"]["width"] * r["cell"]["height"]
    return r["cell"]["scene"]["params"].get("n", 4)


def roger(records: list, out: Path) -> list:
    studies = (("lod", "triangles"), ("resolution", "pixels"), ("cosine", "cosine-n's n"))
    present = [(tag, xl) for tag, xl in studies if any(tag in r.get("tags", []) for r in records)]
    if not present:
        return []
    plt = pyplot()
    fig, axes = plt.subplots(2, len(present), figsize=(4.4 * len(present), 7), squeeze=False)
    lines = ["# Ray-space hierarchy analyses (Roger et al. 2007)", "", f"Machine: {machine_line(records)}.", "",
             "Secondary-ray trace time per frame (shadow + reflection + refraction, median ms) and the ray-space "
             "hierarchy's final triangle tests per ray.", "",
             "| study | scene | size | traversal | x | secondary rays | trace ms | Embree ms | candidates / ray |",
             "|---|---|---|---|---:|---:|---:|---:|---:|"]
    for j, (tag, xlabel) in enumerate(present):
        mine = [r for r in records if tag in r.get("tags", [])]
        travs = ordered(r["labels"]["traversal"] for r in mine)
        ax_t, ax_c = axes[0][j], axes[1][j]
        embree_points = {}
        for t, trav in enumerate(travs):
            rs = sorted((r for r in mine if r["labels"]["traversal"] == trav), key=lambda r: _roger_x(r, tag))
            xs = [_roger_x(r, tag) for r in rs]
            ax_t.plot(xs, [trace_seconds(r, SECONDARY) * 1e3 for r in rs], "o-", ms=3, color=f"C{t}", label=trav)
            for r in rs:
                e = embree_seconds(r, SECONDARY)
                if e is not None:
                    embree_points.setdefault(_roger_x(r, tag), e * 1e3)
                cand = {k: r.get("extra", {}).get(k, {}).get("rayspace", {}).get("candidates_per_ray")
                        for k in SECONDARY}
                shown = "; ".join(f"{k} {v:.1f}" for k, v in cand.items() if v)
                lines.append(f"| {tag} | {r['labels']['scene']} | {r['labels']['resolution']} | {trav} | "
                             f"{_roger_x(r, tag):,} | {sum(r['rays'][k] for k in SECONDARY):,} | "
                             f"{trace_seconds(r, SECONDARY) * 1e3:,.1f} | "
                             f"{fmt(None if e is None else e * 1e3, 1)} | {shown or '–'} |")
            for k, style in (("reflection", "o-"), ("shadow", "s--")):
                pts = [(x, r.get("extra", {}).get(k, {}).get("rayspace", {}).get("candidates_per_ray"))
                       for x, r in zip(xs, rs)]
                pts = [(x, v) for x, v in pts if v]
                if pts:
                    ax_c.plot(*zip(*pts), style, ms=3, color=f"C{t}", label=f"{trav}: {k}")
        if embree_points:
            xs = sorted(embree_points)
            ax_t.plot(xs, [embree_points[x] for x in xs], "x:", color="0.4", label="Embree")
        for ax in (ax_t, ax_c):
            ax.set_xlabel(xlabel, fontsize=8)
            ax.tick_params(labelsize=7)
            if tag != "cosine":
                ax.set_xscale("log")
        ax_t.set_yscale("log")
        ax_t.set_ylabel("secondary trace ms / frame", fontsize=8)
        ax_c.set_ylabel("candidate triangles per ray (rayspace)", fontsize=8)
        ax_t.set_title(f"time vs {xlabel} ({mine[0]['labels']['scene'].split('(')[0]})", fontsize=9)
        ax_t.legend(fontsize=7)
        if ax_c.has_data():
            ax_c.legend(fontsize=7)
        ax_c.set_ylim(bottom=0)
    fig.suptitle("Ray-space hierarchy (Roger et al. 2007): costs of secondary rays", fontsize=10)
    fig.tight_layout()
    md = out / "roger.md"
    write_text(md, "\n".join(lines) + "\n")
    return [md, save(fig, out / "roger.png")]


#: Figure kinds a matrix may ask for (``plot = [...]``).
PLOTS = {"summary": summary, "mrays": mrays, "fig5": fig5, "fig6": fig6, "fig7": fig7, "table2": table2,
         "roger": roger, "packets": packets_report.packets}


def render_plots(records: list, out: Path, kinds) -> list:
    """Write ``summary`` and every kind in ``kinds``; returns the files written."""
    files = []
    for kind in ordered(["summary", *kinds]):
        files += PLOTS[kind](records, out)
    return files
