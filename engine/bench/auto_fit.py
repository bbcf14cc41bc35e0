"""The ``auto`` traversal's thresholds, fitted from measurements (``tools/fit_auto.py``), and
``auto`` measured against Ranged and Partition on the same rays.

A reduced version of Overbeck et al.'s Figure 5 grid: scenes x packet sizes x ray kinds at one
or more resolutions (a row per scene and resolution: ``row_label``). Per (scene, resolution,
packet size):

1. **Rays.** One render per recursion preset records every batch the Whitted loop casts
   (``engine.bench.runner.BatchRecorder``): primary and shadow rays from ``shadows`` (the
   scene's first point light only, to keep the run short), reflection rays from
   ``reflection2``, refraction rays from ``refraction2``.
2. **Measures.** Every packet's (live, footprint, valid) by the chooser's own kernel
   (``engine.packet.choose.measure_packets``) and the batch's paper frusta.
3. **Cells.** The packets of one (scene, packet size, ray kind) are binned by footprint
   (quantile edges over all packets of the run), live fraction (``LIVE_EDGES``) and frustum
   validity; each non-empty bin becomes a sub-batch of its packets (repeated up to at least
   ``MIN_CELL_PACKETS``, the time divided by the copies), which Masked, Ranged and Partition
   walk in turn, interleaved, ``repeat`` times on one thread (a packet's walk does not depend
   on the other packets of its batch). Best of the repeats per strategy.
4. **Fit.** The chooser's rule (``engine.packet.choose``) applied to a bin is one strategy
   for all its packets when its thresholds sit on bin edges, so the fitted thresholds are edges
   (and the frustum-less strategy), found by an exhaustive search over every combination
   (``fit_limits``) for the smallest summed cell time (``objective="total"``, the shipped
   fit's), or for issue 17's criterion row by row (``"worst-row"``): the smallest worst ratio,
   over the rows (scene, resolution, packet size, ray kind), of the rule's summed cell time to
   the better of all-Ranged and all-Partition on that row, ties to the smaller total. The
   summed time is ruled by the scene with the longest walks (spd-rings' reflection rays take
   half of it), so thresholds that cost the kitchen's shadow rays 7% hardly move it
   (``docs/auto-fit-1024.md``); the worst-row fit weighs every row alike
   (``docs/auto-fit-two-sizes.md``: it did not help, as no footprint threshold suits every row).
5. **Measure.** Every batch of the frame replayed through the renderer's ``Tracer`` (frustum
   build + query, as a render times it) with ``ranged``, ``partition``, ``auto`` (the fitted
   thresholds) and ``auto`` with every split batch chosen packet by packet, interleaved,
   ``measure_repeat`` times on ``threads`` threads (0: all); median trace time per frame and
   kind. Both autos' answers are checked equal to Partition's.

Writes the thresholds file (``engine/packet/auto_thresholds.json`` by default), a markdown
report and, beside it, a figure of the measurement (``figure``: the report's name with .png),
each atomically.
"""
from __future__ import annotations

import datetime
import time
from dataclasses import replace
from pathlib import Path

import numba
import numpy as np

from engine.bench.machine import machine_info
from engine.bench.matrix import Cell, PluginSpec, SceneSpec
from engine.bench.cell_scenes import SceneCache, cell_scene
from engine.bench.paired_stats import paired_ratio, verdict
from engine.bench.runner import BatchRecorder, answer_arrays
from engine.core.atomic import write_json, write_text
from engine.core.threads import numba_threads
from engine.core.types import RAY_KINDS, Frusta, Packets, RayBatch, empty_hits
from engine.packet.choose import LIMIT_NAMES, measure_packets
from engine.packet.plugin import walk_batch
from engine.packet.strategies import CHOSEN_NAMES, STRATEGIES
from engine.render.config import PAPER_FRUSTUM
from engine.render.plugins import make_traversal
from engine.render.tracer import Tally

SCENES = ("erw6", "bart-museum", "bart-kitchen", "spd-rings")
PACKETS = (8, 16)
SIZE = 256
#: Fit objectives (``fit_limits``): the summed cell time, or the worst row's ratio to its better
#: strategy.
OBJECTIVES = ("total", "worst-row")
#: Ray kind -> the recursion preset whose render supplies its batches.
SOURCE = {"primary": "shadows", "shadow": "shadows", "reflection": "reflection2", "refraction": "refraction2"}
#: Footprint bins: this many quantiles of the run's packets.
FOOTPRINT_BINS = 16
#: Live-fraction bin edges (a bin is [edge, next edge)).
LIVE_EDGES = (0.0, 0.25, 0.5, 0.75, 0.9, 1.0)
#: A cell of fewer packets is timed on copies of them, this many packets or more, and its time
#: divided by the copies: a walk call costs about 17 us before its first packet (erw6, one
#: thread), as much as a few packets' walks, and in the cells of one to a dozen packets that
#: fixed cost hid which strategy walked the packets faster.
MIN_CELL_PACKETS = 64
#: A footprint threshold above every packet's footprint.
EVERY = 1e9
#: The auto variants a measurement replays (``measure``).
AUTOS = ("auto", "auto/packet", "auto/trials")


# -- rays ----------------------------------------------------------------------------------

def record_frame(scene_cache, scene_name, packet, size, threads=0):
    """(renderer, [(kind, query, rays, packets)]) of one frame of ``scene_name``: the batches of
    every kind, each from the render of its preset (``SOURCE``)."""
    from engine.render.whitted import WhittedRenderer

    batches, renderer = [], None
    for preset in dict.fromkeys(SOURCE.values()):
        cell = Cell(SceneSpec(scene_name, label=scene_name), PluginSpec("partition", ("partition",) * 4),
                    PluginSpec("paper", tuple(PAPER_FRUSTUM[k] for k in RAY_KINDS)), packet, preset, size, size,
                    threads=threads, embree=False)
        scene = cell_scene(scene_cache.get(cell.scene), cell)
        scene = replace(scene, lights=list(scene.lights[:1]))
        recorder = BatchRecorder()
        renderer = WhittedRenderer(scene, cell.config(), observer=recorder, bvh=getattr(renderer, "bvh", None))
        renderer.render()
        kinds = [k for k, p in SOURCE.items() if p == preset]
        batches += [batch for batch in recorder.batches if batch[0] in kinds]
    return renderer, batches


def measures(renderer, kind, rays, packets):
    """(live f64[K], footprint f64[K], Frusta) of a batch's packets."""
    offsets = np.ascontiguousarray(packets.offsets, np.int32)
    n = offsets.shape[0] - 1
    live, footprint = np.zeros(n), np.zeros(n)
    measure_packets(renderer.bvh.bmin, renderer.bvh.bmax, rays.org, rays.dir, rays.tmin, rays.tmax, offsets,
                    live, footprint)
    return live, footprint, renderer.tracer.frusta_for(kind, rays, packets)


def sub_batch(parts):
    """One batch of the chosen packets of several batches of one kind: parts is
    [(rays, packets, frusta, packet indices)]; returns (rays, packets, frusta)."""
    fields = {f: [] for f in RayBatch._fields[:-1]}
    offsets, planes, valid, total = [0], [], [], 0
    for rays, packets, frusta, chosen in parts:
        for k in chosen:
            start, stop = int(packets.offsets[k]), int(packets.offsets[k + 1])
            for f in fields:
                fields[f].append(getattr(rays, f)[start:stop])
            total += stop - start
            offsets.append(total)
            planes.append(frusta.planes[k])
            valid.append(frusta.valid[k])
    rays = RayBatch(*(np.ascontiguousarray(np.concatenate(fields[f])) for f in fields), parts[0][0].kind)
    first = parts[0][1]
    return (rays, Packets(np.array(offsets, np.int32), first.size, first.width, first.height),
            Frusta(np.ascontiguousarray(planes, np.float32), np.ascontiguousarray(valid, np.bool_)))


def time_strategies(renderer, rays, packets, frusta, any_hit, repeat):
    """Best-of-``repeat`` seconds of Masked, Ranged and Partition walking a batch, interleaved:
    f64[3] indexed by strategy number."""
    n = rays.org.shape[0]
    hits = empty_hits(n)
    best = np.full(len(CHOSEN_NAMES), np.inf)
    for rep in range(repeat + 1):  # the first round warms the caches and is not kept
        order = range(len(CHOSEN_NAMES)) if rep % 2 else reversed(range(len(CHOSEN_NAMES)))
        for s in order:
            start = time.perf_counter()
            walk_batch(STRATEGIES[CHOSEN_NAMES[s]], renderer.bvh, renderer.tris, rays, packets, frusta, any_hit,
                       hits.t, hits.prim, hits.u, hits.v)
            if rep:
                best[s] = min(best[s], time.perf_counter() - start)
    return best


# -- the fit -------------------------------------------------------------------------------

def bin_of(footprint, live, f_edges):
    """(footprint bin, live bin) of each packet: footprint bin i holds f_edges[i-1] < f <=
    f_edges[i] (bin len(f_edges): above the last), live bin j holds LIVE_EDGES[j] <= live <
    LIVE_EDGES[j+1] (the last: live == 1)."""
    fb = np.searchsorted(f_edges, footprint, side="left")
    lb = np.clip(np.searchsorted(LIVE_EDGES, live, side="right") - 1, 0, len(LIVE_EDGES) - 1)
    return fb, lb


def rule_choice(fb, lb, valid, r_idx, m_idx, l_idx, invalid):
    """The chooser's rule on bins with thresholds on edges: RANGED_MAX = f_edges[r_idx] (-1:
    below every packet), MASKED_MAX = f_edges[m_idx], MIN_LIVE = LIVE_EDGES[l_idx]; invalid:
    the frustum-less strategy. Returns the strategy number per cell."""
    masked, ranged, partition = (STRATEGIES[n] for n in CHOSEN_NAMES)
    out = np.full(fb.shape, partition)
    live_ok = lb >= l_idx
    out[live_ok & (fb <= r_idx)] = ranged
    out[live_ok & (fb <= m_idx)] = masked
    out[~valid] = invalid
    return out


def row_baseline(cells) -> tuple:
    """(row of each cell i64[C], rows, f64[rows] the better of all-Ranged and all-Partition's
    summed seconds on each row) of ``cells["group"]`` (one row when absent)."""
    seconds = cells["seconds"]
    groups = cells.get("group")
    if groups is None:
        index = np.zeros(len(seconds), np.int64)
    else:
        names = {g: i for i, g in enumerate(dict.fromkeys(groups))}
        index = np.array([names[g] for g in groups], np.int64)
    n_rows = int(index.max()) + 1 if len(index) else 0
    ranged, partition = (np.bincount(index, seconds[:, STRATEGIES[x]], n_rows) for x in ("ranged", "partition"))
    return index, n_rows, np.maximum(np.minimum(ranged, partition), 1e-300)


def row_ratios(cells, choice, baseline=None):
    """f64[G] per row (``cells["group"]``; one row when absent): the summed cell seconds when
    cell c is walked by choice[c], over the better of all-Ranged and all-Partition on the row.
    ``baseline``: ``row_baseline(cells)``, when the caller asks for many choices."""
    index, n_rows, better = baseline or row_baseline(cells)
    return np.bincount(index, cells["seconds"][np.arange(len(index)), choice], n_rows) / better


def fit_limits(cells, f_edges, objective: str = "total"):
    """The thresholds that minimise ``objective`` (``OBJECTIVES``): "total", the summed cell
    times, or "worst-row", the largest ``row_ratios`` (ties to the smaller summed time). cells:
    dict of arrays fb, lb (bins), valid (bool), seconds f64[C,3] (per strategy number) and the
    row of each cell, group (a list; absent: one row). Returns (limits {name: value}, total
    seconds, the index choice)."""
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {', '.join(OBJECTIVES)}, got {objective!r}")
    fb, lb, valid, seconds = cells["fb"], cells["lb"], cells["valid"], cells["seconds"]
    rows = np.arange(len(fb))
    baseline = row_baseline(cells) if objective == "worst-row" else None
    best = ((np.inf, np.inf), None)
    n_f = len(f_edges)
    for invalid in range(len(CHOSEN_NAMES)):
        for l_idx in range(len(LIVE_EDGES)):
            for r_idx in range(-1, n_f + 1):  # n_f: every footprint
                for m_idx in range(-1, r_idx + 1):
                    choice = rule_choice(fb, lb, valid, r_idx, m_idx, l_idx, invalid)
                    total = seconds[rows, choice].sum()
                    # Ratios compared to 1e-9: cell sums in another order differ in the last bits.
                    key = (round(float(row_ratios(cells, choice, baseline).max()), 9) if baseline else 0.0, total)
                    if key[0] < best[0][0] or (key[0] == best[0][0] and total < best[0][1] - 1e-12):
                        best = (key, (r_idx, m_idx, l_idx, invalid))
    (_, total), (r_idx, m_idx, l_idx, invalid) = best
    def edge(i):  # -1: below every packet; n_f: above every packet (JSON has no infinity)
        return -1.0 if i < 0 else (EVERY if i >= n_f else float(f_edges[i]))

    limits = {"ranged_max_footprint": edge(r_idx), "masked_max_footprint": edge(m_idx),
              "min_live": float(LIVE_EDGES[l_idx]), "invalid_frustum": CHOSEN_NAMES[invalid]}
    assert set(limits) == set(LIMIT_NAMES)
    return limits, float(total), (r_idx, m_idx, l_idx, invalid)


# -- the run -------------------------------------------------------------------------------

def row_label(scene: str, size: int, sizes) -> str:
    """The scene column of a row: the scene's name, with its resolution when a run has several
    (``sizes``)."""
    return scene if len(sizes) == 1 else f"{scene} {size}x{size}"


def collect(scenes, packets, sizes, repeat, log, threads=0):
    """Record the frames (one per scene, resolution in ``sizes`` and packet size), measure and
    time the cells. Returns (frames {(row label, packet): (renderer, batches)}, the footprint
    bin edges, the cell table, whose groups are (row label, packet, kind): ``row_label``)."""
    scene_cache = SceneCache()
    frames, groups = {}, {}
    for size in sizes:
        for name in scenes:
            label = row_label(name, size, sizes)
            for n in packets:
                start = time.perf_counter()
                renderer, batches = record_frame(scene_cache, name, n, size, threads)
                frames[(label, n)] = (renderer, batches)
                for kind, query, rays, pk in batches:
                    live, footprint, frusta = measures(renderer, kind, rays, pk)
                    groups.setdefault((label, n, kind), []).append((query, rays, pk, frusta, live, footprint))
                log(f"{label} {n}x{n}: {len(batches)} batches recorded in {time.perf_counter() - start:.1f} s")
    all_f = np.concatenate([b[5][b[4] > 0] for parts in groups.values() for b in parts])
    f_edges = np.unique(np.quantile(all_f, np.linspace(0, 1, FOOTPRINT_BINS + 1)[1:-1]))
    table = {"group": [], "fb": [], "lb": [], "valid": [], "packets": [], "seconds": []}
    with numba_threads(1):  # a cell's time is the sum of its packets' walks
        for (name, n, kind), parts in groups.items():
            start = time.perf_counter()
            renderer = frames[(name, n)][0]
            per_part = [(bin_of(p[5], p[4], f_edges), p[3].valid) for p in parts]
            keys = sorted({(int(a), int(b), bool(v)) for (fb, lb), valid in per_part
                           for a, b, v in zip(fb, lb, valid)})
            for fbin, lbin, ok in keys:
                chosen = [(p[1], p[2], p[3], np.flatnonzero((fb == fbin) & (lb == lbin) & (valid == ok)))
                          for p, ((fb, lb), valid) in zip(parts, per_part)]
                chosen = [c for c in chosen if len(c[3])]
                n_packets = sum(len(c[3]) for c in chosen)
                copies = -(-MIN_CELL_PACKETS // n_packets)
                rays, pk, frusta = sub_batch(chosen * copies)
                seconds = time_strategies(renderer, rays, pk, frusta, parts[0][0] == "occluded", repeat) / copies
                table["group"].append((name, n, kind))
                table["fb"].append(fbin)
                table["lb"].append(lbin)
                table["valid"].append(ok)
                table["packets"].append(n_packets)
                table["seconds"].append(seconds)
            log(f"  {name} {n}x{n} {kind}: {len(keys)} cells timed in {time.perf_counter() - start:.1f} s")
    cells = {k: (np.array(v) if k != "group" else v) for k, v in table.items()}
    return frames, f_edges, cells


def measure(frames, limits, repeat, log):
    """{(scene, packet, kind): {traversal: median seconds per frame, "paired": {auto: (median,
    low, high)}}} of replaying each frame's batches with ranged, partition, auto (``limits``),
    "auto/packet" (the same limits, every batch whose sample is split chosen packet by packet:
    ``split_min_packets = 0``) and "auto/trials" (the same limits with timed trials on the batches
    it splits: ``engine.packet.auto_trial``), interleaved, where "paired" is each auto's ``paired_ratio``
    against the better of ranged and partition; and {(scene, packet, kind): auto's packets per
    strategy, with auto/trials' trials}. Every auto's answers must equal Partition's. The first,
    untimed repetition is where auto/trials makes its trials (a renderer's first frame)."""
    names = ("ranged", "partition") + AUTOS
    options = {"auto": limits, "auto/packet": {**limits, "split_min_packets": 0},
               "auto/trials": {**limits, "trials": True}}
    out, counts = {}, {}
    for (name, n), (renderer, batches) in frames.items():
        plugins = {t: make_traversal(t.split("/")[0], options.get(t)) for t in names}
        tracers = {t: renderer.tracer.with_traversal(dict.fromkeys(RAY_KINDS, p))
                   for t, p in plugins.items()}
        runs = {t: [] for t in names}
        answers = {}
        # Each traversal's timed replays answer into arrays of its own, made once (as a frame's
        # renderer keeps its answers): new arrays inside the timing biased the pairs by their
        # page faults (``engine.bench.runner.answer_arrays``).
        kept = {t: answer_arrays(batches) for t in names}
        for rep in range(repeat + 1):
            order = names if rep % 2 else names[::-1]
            for t in order:
                tally = Tally()
                into = kept[t] if rep else [None] * len(batches)
                got = [tracers[t].trace(kind, query, rays, pk, tally, answer)
                       for (kind, query, rays, pk), answer in zip(batches, into)]
                if rep:
                    runs[t].append(dict(tally.seconds))
                else:
                    answers[t] = got
        for auto in AUTOS:
            for a, b, (kind, query, _, _) in zip(answers[auto], answers["partition"], batches):
                same = np.array_equal(a, b) if query == "occluded" else all(
                    np.array_equal(x, y) for x, y in zip(a, b))
                if not same:
                    raise AssertionError(f"{auto}'s answers differ from partition's on {name} {kind}")
        for kind in {k for k, *_ in batches}:
            row = {t: float(np.median([r[kind] for r in runs[t]])) for t in names}
            per_rep = {t: np.array([r[kind] for r in runs[t]]) for t in names}
            best = "ranged" if row["ranged"] <= row["partition"] else "partition"
            # Each auto against the better strategy's time in the same repetition.
            row["paired"] = {t: paired_ratio(per_rep[t], per_rep[best]) for t in AUTOS}
            out[(name, n, kind)] = row
        tally, tried = Tally(count=True), Tally(count=True)  # counting replays: auto's choices, the trials
        for kind, query, rays, pk in batches:
            tracers["auto"].trace(kind, query, rays, pk, tally)
            tracers["auto/trials"].trace(kind, query, rays, pk, tried)
        for kind, stats in tally.stats.items():
            counts[(name, n, kind)] = {**stats.extra["auto"]["packets"],
                                       "trials": tried.stats[kind].extra["auto"].get("trials", [])}
        log(f"measured {name} {n}x{n}")
    return out, counts


# -- outputs ---------------------------------------------------------------------------------

def totals_by(cells, choice):
    """Summed seconds per ray kind when each cell is walked by choice[c] (a strategy number)."""
    out = {}
    for c, (scene, n, kind) in enumerate(cells["group"]):
        out[kind] = out.get(kind, 0.0) + float(cells["seconds"][c, choice[c]])
    return out


def report(args, limits, fitted_total, cells, f_edges, timing, counts, seconds, plot=None) -> str:
    """The markdown report of a fit and its measurement; ``plot``: the figure of the
    measurement (``figure``) beside the report, shown in it."""
    s = cells["seconds"]
    m, r, p = (STRATEGIES[x] for x in CHOSEN_NAMES)
    n_cells = len(cells["group"])
    fb, lb, valid = cells["fb"], cells["lb"], cells["valid"]
    idx = _index_of(limits, f_edges)
    fitted = rule_choice(fb, lb, valid, *idx)
    rows = [("all Ranged", np.full(n_cells, r)), ("all Partition", np.full(n_cells, p)),
            ("all Masked", np.full(n_cells, m)),
            ("paper (Ranged primary, Partition others)",
             np.array([r if g[2] == "primary" else p for g in cells["group"]])),
            ("auto, fitted rule", fitted), ("per-cell best (lower bound)", np.argmin(s, axis=1))]
    lines = [f"# `auto` traversal: threshold fit and measurement ({args['date']})", "",
             "Reduced fit, not the full Figure 5 matrix: scenes " + ", ".join(args["scenes"]) +
             ", " + ", ".join(f"{z}x{z}" for z in args["sizes"]) + ", packets "
             + ", ".join(f"{n}x{n}" for n in args["packets"]) +
             ", every ray kind (primary + shadows of the first light, 2-bounce mirror reflections, 2-deep glass "
             "refraction), paper frusta. Cell timings on one thread, best of "
             f"{args['repeat']}; frame timings on {args['threads']} threads, median of {args['measure_repeat']}.",
             "", f"Command: `{args['command']}` ({seconds:.0f} s on {args['machine']}).", "",
             "## Fitted thresholds" if args.get("fitted", True) else
             "## Thresholds (given with `--limits`, measured, not refitted)", "", "| limit | value |", "|---|---|"]
    lines += [f"| `{k}` | {v:.6g} |" if isinstance(v, float) else f"| `{k}` | {v} |" for k, v in limits.items()]
    lines += ["", f"Footprint bin edges (quantiles of {FOOTPRINT_BINS} bins): "
              + ", ".join(f"{e:.4g}" for e in f_edges) + f"; live edges: {', '.join(map(str, LIVE_EDGES))}.",
              "", "## Cell times summed (ms, one thread): what the fit minimised", "",
              *([f"Objective: `{args['objective']}` (`engine.bench.auto_fit.fit_limits`). `worst row` is the "
                 "largest ratio, over the rows (scene, packet, ray kind), of a rule's summed cell time to the "
                 "better of all-Ranged and all-Partition on that row.", ""] if args.get("objective") else []),
              "| rule | " + " | ".join(RAY_KINDS) + " | total | worst row |",
              "|---|" + "---|" * (len(RAY_KINDS) + 2)]
    for label, choice in rows:
        t = totals_by(cells, choice)
        lines.append(f"| {label} | " + " | ".join(f"{1e3 * t.get(k, 0):.1f}" for k in RAY_KINDS)
                     + f" | {1e3 * sum(t.values()):.1f} | {row_ratios(cells, choice).max():.3f} |")
    lines += ["", "## Frame trace time: auto against the better of Ranged and Partition", "",
              "Median trace time per frame (frustum build + traversal, ms) per ray kind; `auto/best` is auto "
              "over the faster of Ranged and Partition for that row (above 1: auto is slower). `paired` is the "
              "median of the per-repetition ratios of auto to the better strategy measured in the same "
              "repetition, with its 95% interval (distribution-free: the sign test's order statistics); "
              "`verdict` says whether that interval lies below 1 (auto faster than both), above 1 (slower) "
              "or around it (the same within the run's noise). `choices` are "
              "auto's packets walked by Masked / Ranged / Partition. `auto by packet` is auto with "
              "`split_min_packets = 0` (every batch whose sample is split chosen packet by packet). "
              "`with trials` is auto with timed trials on the batches it splits (`trials = true`, "
              "`engine.packet.auto_trial`), with its paired ratio and verdict.", "",
              *([f"![auto over the better of Ranged and Partition per row]({plot.name})", ""] if plot else []),
              "| scene | packet | kind | ranged | partition | auto | auto/best | paired [95%] | verdict | "
              "choices M/R/P | auto by packet | by packet/best | with trials | trials paired [95%] | trials verdict |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    verdicts = {"faster": 0, "same": 0, "slower": 0}
    trial_verdicts = {"faster": 0, "same": 0, "slower": 0}
    # Rows auto walked entirely by the better strategy: the very kernel of that strategy's row, so
    # only auto's choosing cost and the run's noise separate them (a verdict there is not a choice).
    one_kernel = {"faster": 0, "same": 0, "slower": 0}
    sums = {t: 0.0 for t in ("ranged", "partition", "auto", "auto/packet", "auto/trials", "best")}
    for (scene, n, kind) in sorted(timing, key=lambda k: (k[0], k[1], RAY_KINDS.index(k[2]))):
        t = timing[(scene, n, kind)]
        best = min(t["ranged"], t["partition"])
        c = counts.get((scene, n, kind), {})
        sums["ranged"] += t["ranged"]
        sums["partition"] += t["partition"]
        sums["auto"] += t["auto"]
        by_packet = t.get("auto/packet", np.nan)
        sums["auto/packet"] += by_packet
        sums["best"] += best
        tried = t.get("auto/trials", np.nan)
        sums["auto/trials"] += tried
        paired_cell, row_verdict = _paired_cells(t.get("paired", {}).get("auto"), verdicts)
        better = "ranged" if t["ranged"] <= t["partition"] else "partition"
        walked = [x for x in CHOSEN_NAMES if c.get(x, 0)]
        if walked == [better] and row_verdict in one_kernel:
            one_kernel[row_verdict] += 1
        tried_cell, tried_verdict = _paired_cells(t.get("paired", {}).get("auto/trials"), trial_verdicts)
        lines.append(f"| {scene} | {n} | {kind} | {1e3 * t['ranged']:.2f} | {1e3 * t['partition']:.2f} | "
                     f"{1e3 * t['auto']:.2f} | {t['auto'] / best:.3f} | {paired_cell} | {row_verdict} | "
                     + "/".join(str(c.get(x, 0)) for x in CHOSEN_NAMES)
                     + f" | {1e3 * by_packet:.2f} | {by_packet / best:.3f} | {1e3 * tried:.2f} | {tried_cell} | "
                     f"{tried_verdict} |")
    lines += [f"| **all** | | | {1e3 * sums['ranged']:.1f} | {1e3 * sums['partition']:.1f} | "
              f"{1e3 * sums['auto']:.1f} | {sums['auto'] / sums['best']:.3f} (vs per-row best) | | | | "
              f"{1e3 * sums['auto/packet']:.1f} | {sums['auto/packet'] / sums['best']:.3f} | "
              f"{1e3 * sums['auto/trials']:.1f} | {sums['auto/trials'] / sums['best']:.3f} | |", ""]
    for label, counted in (("auto", verdicts), ("auto with trials", trial_verdicts)):
        if sum(counted.values()):
            lines += [f"Paired verdicts over {sum(counted.values())} rows, {label}: faster than both in "
                      f"{counted['faster']}, the same as the better within the noise in {counted['same']}, "
                      f"slower than the better in {counted['slower']}.", ""]
    if sum(one_kernel.values()):
        lines += [f"Of auto's rows, {sum(one_kernel.values())} were walked entirely by the better strategy, with "
                  f"that strategy's own kernel (only auto's choosing cost and the noise tell them apart; at 95% "
                  f"intervals about one row in twenty reads faster or slower by chance): faster in "
                  f"{one_kernel['faster']}, the same in {one_kernel['same']}, slower in {one_kernel['slower']}.", ""]
    tried = [(key, trial) for key in sorted(counts, key=lambda k: (k[0], k[1], RAY_KINDS.index(k[2])))
             for trial in counts[key].get("trials", [])]
    if tried:
        lines += ["## auto's trials", "",
                  "Each group of a batch the rule split packet by packet, as auto with trials' first "
                  "(untimed) repetition tried it (`engine.packet.auto_trial`): its own strategy's and the other's time on about an "
                  "eighth of the group's packets each (packets in brackets), whether it is the batch's larger "
                  "group, and the strategy that walked the rest from then on.", "",
                  "| scene | packet | kind | batch packets | group | larger | own ms | other ms | walked by |",
                  "|---|---|---|---|---|---|---|---|---|"]
        lines += [f"| {scene} | {n} | {kind} | {t['packets']} | {t['group']} | {'yes' if t.get('larger') else 'no'} | "
                  f"{1e3 * t['own_seconds']:.2f} ({t.get('own_packets', '?')}) | "
                  f"{1e3 * t['other_seconds']:.2f} ({t.get('other_packets', '?')}) | {t['walked_by']} |"
                  for (scene, n, kind), t in tried]
        lines.append("")
    return "\n".join(lines) + "\n"


def _paired_cells(paired, counted) -> tuple:
    """(the table's paired cell, the verdict) of a (median, low, high) paired ratio, counting the
    verdict into ``counted``; ("–", "–") where the timing kept no repetitions (an older caller)."""
    if paired is None:
        return "–", "–"
    row_verdict = verdict(paired[1], paired[2])
    counted[row_verdict] += 1
    return f"{paired[0]:.3f} [{paired[1]:.3f}, {paired[2]:.3f}]", row_verdict


def figure(timing, counts, path):
    """``path`` (PNG): per (scene, packet, ray kind) row of ``timing`` ({(scene, n, kind):
    {traversal: seconds}}), Ranged, Partition and auto over the better of Ranged and Partition,
    on one axis around 1; a green auto bar is a row where auto beat both, a red one where it lost;
    where the rows carry ``paired`` ratios (``measure``), a dot and whisker per row give auto's
    paired median and 95% interval. Returns the path."""
    from engine.bench.figures import pyplot, save

    plt = pyplot()
    keys = sorted(timing, key=lambda k: (k[0], k[1], RAY_KINDS.index(k[2])))
    best = [min(timing[k]["ranged"], timing[k]["partition"]) for k in keys]
    ratio = {t: [timing[k][t] / b for k, b in zip(keys, best)] for t in ("ranged", "partition", "auto")}
    ys = np.arange(len(keys))
    fig, ax = plt.subplots(figsize=(7.5, 0.24 * len(keys) + 1.4))
    colours = ["tab:green" if r < 1.0 else "tab:red" for r in ratio["auto"]]
    ax.barh(ys, [r - 1.0 for r in ratio["auto"]], left=1.0, height=0.6, color=colours, label="auto")
    paired = [timing[k].get("paired", {}).get("auto") for k in keys]
    if all(p is not None for p in paired):  # the paired ratios' 95% intervals (``paired_ratio``)
        ax.errorbar([p[0] for p in paired], ys, xerr=[[p[0] - p[1] for p in paired], [p[2] - p[0] for p in paired]],
                    fmt="o", color="0.15", markersize=2.5, elinewidth=0.9, capsize=2,
                    label="auto, paired per repetition (95%)")
    ax.plot(ratio["ranged"], ys, "|", color="tab:blue", markersize=9, mew=2, label="Ranged")
    ax.plot(ratio["partition"], ys, "|", color="tab:orange", markersize=9, mew=2, label="Partition")
    ax.axvline(1.0, color="0.3", lw=0.8)
    labels = []
    for k in keys:
        chosen = counts.get(k, {})
        labels.append(f"{k[0]} {k[1]}x{k[1]} {k[2]}  (R {chosen.get('ranged', 0)} / P {chosen.get('partition', 0)})")
    ax.set_yticks(ys, labels, fontsize=7)
    ax.invert_yaxis()
    high = max(max(v) for v in ratio.values())
    ax.set_xlim(min(0.9, min(ratio["auto"]) - 0.02), min(high + 0.05, 2.0))
    ax.set_xlabel("trace time per frame over the better of Ranged and Partition (below 1: auto beat both)",
                  fontsize=8)
    ax.tick_params(axis="x", labelsize=7)
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title("auto against Ranged and Partition, row by row (packets auto walked by each in brackets)",
                 fontsize=9)
    fig.tight_layout()
    return save(fig, path)


def _index_of(limits, f_edges):
    def edge_index(v):
        return -1 if v < 0 else int(np.searchsorted(f_edges, v))
    return (edge_index(limits["ranged_max_footprint"]), edge_index(limits["masked_max_footprint"]),
            LIVE_EDGES.index(limits["min_live"]), CHOSEN_NAMES.index(limits["invalid_frustum"]))


def run(scenes=SCENES, packets=PACKETS, sizes=(SIZE,), repeat=5, measure_repeat=5, thresholds_out=None,
        report_out=None, command="", log=print, threads=0, limits=None, objective="total") -> dict:
    """Collect (at each resolution of ``sizes``), fit by ``objective`` (``fit_limits``), write
    the thresholds, measure (on ``threads`` threads, 0: all), write the report. ``limits``:
    thresholds to measure instead of fitting ({name: value}, as in the thresholds file; none is
    written then). Returns the limits."""
    with numba_threads(threads):  # for this run only; the caller's count comes back
        return _run(scenes, packets, tuple(sizes), repeat, measure_repeat, thresholds_out, report_out, command,
                    log, threads, limits, objective)


def _run(scenes, packets, sizes, repeat, measure_repeat, thresholds_out, report_out, command, log, threads,
         given=None, objective="total"):
    start = time.perf_counter()
    frames, f_edges, cells = collect(scenes, packets, sizes, repeat, log, threads)
    if given is None:
        limits, total, _ = fit_limits(cells, f_edges, objective)
        log(f"fitted {limits} (summed cell time {1e3 * total:.1f} ms)")
    else:
        limits = dict(given)
        total = sum(totals_by(cells, rule_choice(cells["fb"], cells["lb"], cells["valid"],
                                                 *_index_of(limits, f_edges))).values())
        thresholds_out = None  # measured, not fitted: the thresholds file stays as it is
        log(f"measuring the given thresholds {limits} (summed cell time {1e3 * total:.1f} ms)")
    fit_seconds = time.perf_counter() - start
    info = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "scenes": list(scenes), "packets": list(packets), "sizes": list(sizes), "repeat": repeat,
            "objective": objective if given is None else None,
            "measure_repeat": measure_repeat, "threads": numba.get_num_threads(), "command": command,
            "fitted": given is None,
            "machine": machine_info().get("cpu", "this machine")}
    if thresholds_out:
        write_json(thresholds_out, {"limits": limits, "fit": {**info, "seconds": round(fit_seconds, 1),
                                                              "cells": len(cells["group"]),
                                                              "footprint_edges": list(f_edges),
                                                              "live_edges": list(LIVE_EDGES)}},
                   "thresholds")
    timing, counts = measure(frames, limits, measure_repeat, log) if measure_repeat else ({}, {})
    if report_out:
        plot = Path(report_out).with_suffix(".png") if timing else None
        if plot is not None:
            figure(timing, counts, plot)
        write_text(report_out, report(info, limits, total, cells, f_edges, timing, counts,
                                      time.perf_counter() - start, plot))
    return limits
