"""Figures and tables from benchmark records (``engine.bench.results``): one function per kind.

A matrix picks its kinds with ``plot = [...]``; ``summary`` is always written. Every function
takes (records, out folder) and returns the files it wrote (none when no record fits it).
Times are medians over the repeats; "trace" time is our frustum build + traversal on the
recorded batches (shading excluded), the same work Embree is timed on.

    summary  summary.md: one row per cell (rays, frame and trace time, Mrays/s, ratios to Embree
             and, when measured, Open3D)
    mrays    mrays.png: Mrays/s per cell, ours beside Embree (and Open3D when measured)
    fig5     fig5.png: trace time per frame vs packet size, scenes x recursion grid, a line per
             traversal (Overbeck et al. 2008, Figure 5)
    fig6     fig6-<scene>.png: ray-AABB and ray-triangle tests per ray by BVH depth, a bar per
             traversal; fig6-totals.png: the totals (Figure 6)
    fig7     fig7.png: as fig5 with culling on (solid) and off (dashed); fig7.md: the benefit (Figure 7)
    table2   table2.md + table2.png: whole-frame and trace-only FPS of 2x2 SIMD vs 16x16 packets with
             and without culling, their ratios, the culling benefit, Embree (and Open3D when
             measured) on the same rays, where each frame goes (Table 2)
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
from engine.bench.open3d_yardstick import OPEN3D_MISMATCH_TOLERANCE
from engine.bench.results import host_slowdown
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

def _open3d_rate(r: dict):
    """Open3D's Mrays/s over all kinds as shown: "†" when some of its answers disagreed with the
    reference (rates kept within a tolerance, see engine.bench.open3d_yardstick.open3d_rates)."""
    rate = (r.get("open3d_mrays_per_s") or {}).get("all")
    flagged = any(row["mismatches"] for row in ((r.get("checks") or {}).get("open3d") or {}).values())
    return fmt(rate) + (" †" if flagged and rate is not None else "")


def summary(records: list, out: Path) -> list:
    lines = ["# Benchmark summary", ""]
    if not records:
        lines.append("No finished cells yet.")
    else:
        open3d = any(r.get("open3d_mrays_per_s") for r in records)
        lines += [f"Machine: {machine_line(records)}.", "",
                  "Times are medians over the repeats; trace = frustum build + traversal on the recorded batches "
                  "(all ray kinds, shading excluded); the yardsticks trace the very same batches with the same "
                  "thread count: Embree (embreex, robust mode, driven from a thread pool"
                  + ("), Open3D's RaycastingScene (its own Embree build)." if open3d else ")."), ""]
        if open3d:
            lines += [f"† Open3D disagreed with the reference answers on a few rays (its rate is kept up to "
                      f"{OPEN3D_MISMATCH_TOLERANCE:.1%} of a kind's rays; the counts are in results.jsonl, "
                      f"checks.open3d).", ""]
        lines += ["CPU share = our CPU time / (wall time x threads) while replaying: near 1 on an idle machine, "
                  "lower when other work competed for the cores (treat such rows with care). Host slow-down = "
                  "how many times slower than the run's fastest probes the host ran just before or after the "
                  "cell (compute, memory latency, bandwidth: engine.bench.host_speed), 1.00 at the run's "
                  "fastest moment; a row well above 1 was measured while the cores ran slower, which the CPU "
                  "share does not show.", "",
                  "| scene | recursion | size | traversal | frustum | packet | rays | frame ms | trace ms | Mrays/s "
                  "| Embree Mrays/s | ours / Embree |" + (" Open3D Mrays/s | ours / Open3D |" if open3d else "")
                  + " CPU share | host slow-down |",
                  "|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|" + ("---:|---:|" if open3d else "")
                  + "---:|---:|"]
        for r, slow in zip(records, host_slowdown(records)):
            lab = r["labels"]
            ratio = (r["ratio_to_embree"] or {}).get("all")
            versus = (f" {_open3d_rate(r)} | {fmt((r.get('ratio_to_open3d') or {}).get('all'))} |"
                      if open3d else "")
            lines.append(f"| {lab['scene']} | {lab['recursion']} | {lab['resolution']} | {lab['traversal']} | "
                         f"{lab['frustum']} | {lab['packet']} | {r['rays']['all']:,} | "
                         f"{r['seconds']['frame']['median'] * 1e3:,.1f} | {trace_seconds(r) * 1e3:,.1f} | "
                         f"{fmt(r['mrays_per_s']['all'])} | {fmt((r['embree_mrays_per_s'] or {}).get('all'))} | "
                         f"{fmt(ratio)} |{versus} {fmt(r.get('load', {}).get('cpu_share_replay'))} | {fmt(slow)} |")
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
    series = [("ours", [r["mrays_per_s"]["all"] or 0 for r in records], "C0"),
              ("Embree (same rays)", [(r["embree_mrays_per_s"] or {}).get("all") or 0 for r in records], "0.6"),
              ("Open3D (same rays)", [(r.get("open3d_mrays_per_s") or {}).get("all") or 0 for r in records], "0.35")]
    series = [s for s in series if s[0] == "ours" or any(s[1])]
    height = 0.8 / len(series)
    fig, ax = plt.subplots(figsize=(8, 0.2 * (len(series) + 1) * len(records) + 1.2))
    y = range(len(records))
    for j, (label, rates, colour) in enumerate(series):
        ax.barh([i + (j - (len(series) - 1) / 2) * height for i in y], rates, height=height, label=label, color=colour)
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
    handles = {}
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

#: The variants of Table 2: (key, label); "auto" (16×16 packets walked by the ``auto`` traversal,
#: with the paper's frusta: beyond the paper) only where the matrix has it.
TABLE2_VARIANTS = (("small", "2×2 SIMD"), ("plain", "16×16, no culling"), ("culled", "16×16, culling"),
                   ("auto", "16×16 `auto`, culling"))


def _prefer(records: list, **labels):
    """The first record whose labels match ``labels``, else the first record (None if none)."""
    match = [r for r in records if all(r["labels"][k] == v for k, v in labels.items())]
    return (match or records or [None])[0]


def _ratio(a, b):
    return a / b if a and b else None


def _times(value) -> str:
    return "–" if value is None else f"{value:.2f}×"


def table2_rows(records: list) -> list:
    """One dict per (scene, recursion, size) that has a baseline below 16×16 and a 16×16 record:
    the records of the variants (small = the baseline, ``simd`` 2×2 when present;
    plain / culled = 16×16 without / with frusta, the paper's system when present; auto = 16×16
    by the ``auto`` traversal with frusta; a variant not measured is None) and their whole-frame
    and trace-only FPS, Embree's and Open3D's trace FPS on the culled cell's rays (None where not
    measured)."""
    groups = {}
    for r in records:
        groups.setdefault((r["labels"]["scene"], r["labels"]["recursion"], r["labels"]["resolution"]), []).append(r)
    rows = []
    for (scene, rec, size), rs in groups.items():
        below = sorted((r for r in rs if r["labels"]["packet"] < 16), key=lambda r: r["labels"]["packet"])
        large = [r for r in rs if r["labels"]["packet"] == 16]
        # The baseline: simd 2x2 without frusta (the first 2x2 simd record, frusta or not, was
        # taken: a culled baseline, named "simd 2x2" all the same, inflated every ratio).
        small = _prefer([r for r in below if r["labels"]["traversal"] == "simd"] or below, packet=2, frustum="none")
        culled = _prefer([r for r in large if r["labels"]["frustum"] != "none"], traversal="paper")
        plain = _prefer([r for r in large if r["labels"]["frustum"] == "none"], traversal="paper")
        if small is None or (culled is None and plain is None):
            continue
        adaptive = next((r for r in large if r["labels"]["traversal"] == "auto" and r["labels"]["frustum"] != "none"),
                        None)
        cells = {"small": small, "plain": plain, "culled": culled, "auto": adaptive}
        fps = {key: (r.get("fps") or {}) if r is not None else {} for key, r in cells.items()}
        frame = {key: fps[key].get("frame") for key in cells}
        trace = {key: (1 / trace_seconds(r) if r is not None and trace_seconds(r) > 0 else None)
                 for key, r in cells.items()}
        yard = culled or plain
        embree = fps["culled" if culled else "plain"].get("embree_trace")
        if embree is None and embree_seconds(yard):
            embree = 1 / embree_seconds(yard)
        baseline = f"{small['labels']['traversal']} {small['labels']['packet']}×{small['labels']['packet']}" + \
            ("" if small["labels"]["frustum"] == "none" else f" with frusta {small['labels']['frustum']}")
        rows.append({"scene": scene, "recursion": rec, "size": size, "records": cells,
                     "triangles": yard["scene"]["triangles"], "lights": yard["scene"].get("lights"),
                     "rays": yard["rays"]["all"], "frame": frame, "trace": trace, "embree": embree,
                     "open3d": fps["culled" if culled else "plain"].get("open3d_trace"),
                     "baseline": baseline})
    return rows


def paired_section(out: Path) -> list:
    """Markdown lines of the run's frames paired by repetition (``paired.json``, written by the
    matrix's ``[paired]`` table: ``engine.bench.paired_frames.run_paired``), or none."""
    import json

    path = out / "paired.json"
    if not path.is_file():
        return []
    data = json.loads(path.read_text())
    lines = ["", "## Per frame, paired by repetition", "",
             f"The cells above are measured minutes apart, and this host's speed moves between them, so a ratio "
             f"of two cells mixes two host speeds. Here each repetition renders one frame of every variant, in "
             f"alternating order ({data['repeat']} repetitions), and each variant's speed-up over the first is "
             f"taken within the repetition: the median and its 95% interval (the sign test's; "
             f"`engine.bench.paired_frames`). `paired.md` has the times.", "",
             "| scene | configuration | size | variant | frame speed-up [95%] | trace speed-up [95%] |",
             "|---|---|---|---|---|---|"]
    for group in data["groups"]:
        for ratio in group["ratios"]:
            cells = []
            for what in ("frame", "trace"):
                median, low, high = ratio[what]
                cells.append(f"{1 / median:.2f}× [{1 / high:.2f}, {1 / low:.2f}]")
            lines.append(f"| {group['scene']} | {group['recursion']} | {group['size']} | {ratio['label']} over "
                         f"{group['variants'][0]['label']} | " + " | ".join(cells) + " |")
    return lines


def table2(records: list, out: Path) -> list:
    rows = table2_rows(records)
    if not rows:
        return []
    open3d = any(row["open3d"] for row in rows)
    adaptive = any(row["records"]["auto"] is not None for row in rows)
    lines = ["# Table 2: 2×2 SIMD rays vs 16×16 packets (Overbeck et al. 2008)", "",
             f"Machine: {machine_line(records)}.", "",
             "**Frame FPS** = 1 / median time of a timed render: camera rays, every traversal, shading and the "
             "image (JIT compilation excluded), what the paper's Table 2 reports. **Trace FPS** = 1 / the same "
             "frame's trace time: frustum build + traversal of every recorded ray batch, replayed, shading "
             "excluded. Embree" + (" and Open3D trace" if open3d else " traces") + " the very same batches. "
             "2×2 SIMD = `simd` in 2×2 packets without frusta; 16×16 = the paper's system (Ranged primary, "
             "Partition secondary) in 16×16 packets, without and with frustum culling. 16×16 / 2×2 compares "
             "16×16 with culling to 2×2 SIMD (the paper: 3.2–6.1× per frame, 8 cores); culling benefit = with "
             "culling over without." + (" Beyond the paper, 16×16 `auto` = the `auto` traversal (a strategy "
             "chosen from measured packets) in 16×16 packets with the paper's frusta, over 2×2 SIMD per frame "
             "and per trace." if adaptive else ""), "",
             "| scene | configuration | size | triangles | lights | rays / frame "
             "| frame FPS 2×2 SIMD | frame FPS 16×16, no culling | frame FPS 16×16 | frame 16×16 / 2×2 "
             "| trace FPS 2×2 SIMD | trace FPS 16×16, no culling | trace FPS 16×16 | trace 16×16 / 2×2 "
             "| culling benefit, frame / trace | Embree trace FPS | 16×16 / Embree, trace |"
             + (" Open3D trace FPS | 16×16 / Open3D, trace |" if open3d else "")
             + (" frame FPS 16×16 `auto` | frame `auto` / 2×2 | trace `auto` / 2×2 |" if adaptive else ""),
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
             + ("---:|---:|" if open3d else "") + ("---:|---:|---:|" if adaptive else "")]
    for row in rows:
        frame, trace = row["frame"], row["trace"]
        config = row["recursion"] + ("" if row["baseline"] == "simd 2×2" else f" (baseline: {row['baseline']})")
        line = (f"| {row['scene']} | {config} | {row['size']} | {row['triangles']:,} | {fmt(row['lights'], 0)} | "
                f"{row['rays']:,} | {fmt(frame['small'])} | {fmt(frame['plain'])} | {fmt(frame['culled'])} | "
                f"{_times(_ratio(frame['culled'], frame['small']))} | {fmt(trace['small'])} | "
                f"{fmt(trace['plain'])} | {fmt(trace['culled'])} | {_times(_ratio(trace['culled'], trace['small']))} | "
                f"{_times(_ratio(frame['culled'], frame['plain']))} / {_times(_ratio(trace['culled'], trace['plain']))} | "
                f"{fmt(row['embree'])} | {_times(_ratio(trace['culled'], row['embree']))} |")
        if open3d:
            line += f" {fmt(row['open3d'])} | {_times(_ratio(trace['culled'], row['open3d']))} |"
        if adaptive:
            line += (f" {fmt(frame['auto'])} | {_times(_ratio(frame['auto'], frame['small']))} | "
                     f"{_times(_ratio(trace['auto'], trace['small']))} |")
        lines.append(line)
    lines += ["", "## Where a frame goes", "",
              "Medians over the timed renders, ms per frame: trace = the traversal time the render itself measured "
              "(every ray kind, frustum build included), shading = the renderer's shading time, outside trace = "
              "the share of the frame that is not traversal.", "",
              "| scene | configuration | variant | frame ms | trace ms | shading ms | outside trace |",
              "|---|---|---|---:|---:|---:|---:|"]
    for row in rows:
        for key, label in TABLE2_VARIANTS:
            r = row["records"][key]
            if r is None:
                continue
            seconds = r["seconds"]
            total = seconds["frame"]["median"]
            traced = sum(seconds["trace"][k]["median"] for k in RAY_KINDS)
            shade = (seconds.get("shade") or {}).get("median")
            outside = 1 - traced / total if total > 0 else None
            lines.append(f"| {row['scene']} | {row['recursion']} | {label} | {total * 1e3:,.1f} | {traced * 1e3:,.1f} | "
                         f"{fmt(None if shade is None else shade * 1e3, 1)} | "
                         f"{'–' if outside is None else f'{outside:.0%}'} |")
    lines += paired_section(out)
    md = out / "table2.md"
    write_text(md, "\n".join(lines) + "\n")
    return [md, _table2_figure(rows, out / "table2.png", open3d, adaptive)]


def _table2_figure(rows: list, path: Path, open3d: bool, adaptive: bool) -> Path:
    """Two panels of grouped bars per row (log FPS): whole frames, and trace only with the
    yardsticks; the 16×16-with-culling bar is labelled with its ratio to 2×2 SIMD."""
    plt = pyplot()
    from matplotlib.ticker import FuncFormatter, NullFormatter

    nan = float("nan")
    fig, axes = plt.subplots(1, 2, figsize=(max(9.0, 2.6 * len(rows) + 3), 4.0))
    panels = ((axes[0], "frame", "whole-frame FPS (shading included)", ()),
              (axes[1], "trace", "trace-only FPS (frustum build + traversal)",
               (("embree", "Embree (same rays)", "0.6"),) + ((("open3d", "Open3D (same rays)", "0.35"),) if open3d
                                                               else ())))
    for ax, key, title, yardsticks in panels:
        series = [(label, f"C{i}", [row[key][variant] or nan for row in rows])
                  for i, (variant, label) in enumerate(TABLE2_VARIANTS) if variant != "auto" or adaptive]
        series += [(label, colour, [row[name] or nan for row in rows]) for name, label, colour in yardsticks]
        width = 0.8 / len(series)
        for s, (label, colour, values) in enumerate(series):
            xs = [i + (s - (len(series) - 1) / 2) * width for i in range(len(rows))]
            ax.bar(xs, values, width=width, label=label, color=colour)
            if s == 2:  # 16×16 with culling: its ratio to 2×2 SIMD
                for x, row in zip(xs, rows):
                    ratio = _ratio(row[key]["culled"], row[key]["small"])
                    if ratio:
                        ax.annotate(f"{ratio:.1f}×", (x, row[key]["culled"]), ha="center", va="bottom", fontsize=7,
                                    xytext=(0, 2), textcoords="offset points")
        ax.set_yscale("log")
        low, high = ax.get_ylim()   # ticks at 1, 2, 5 × 10^k, written plainly (0.5, 20), not 5×10⁻¹
        ax.set_yticks([t for t in (m * 10.0 ** e for e in range(-4, 7) for m in (1, 2, 5)) if low <= t <= high])
        ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_xticks(range(len(rows)), [f"{row['scene']}\n{row['recursion']}" for row in rows], fontsize=7)
        ax.set_ylabel("frames per second (log)", fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7)
    fig.suptitle(f"Table 2 at {rows[0]['size']}: 2×2 SIMD rays vs 16×16 packets (labels: 16×16 with culling "
                 f"over 2×2)", fontsize=10)
    fig.tight_layout()
    return save(fig, path)


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
