"""Whole frames of several render configurations, interleaved in one process and paired by
repetition: the ratio of two configurations' frame times as this host can measure it.

A matrix cell (``engine.bench.runner``) times its frames by itself, and the cells of Table 2 run
minutes apart: on this shared 2-core host the speed moves by 1.3-1.8x from minute to minute
(``engine.bench.host_speed``), so a per-frame ratio of two cells mixes two host speeds (session
30: the kitchen's 2x2 SIMD cell ran at a host slow-down of 1.72, its 16x16 cell at 1.35). Here
every repetition renders one frame of each variant back to back, in an order that alternates, and
the ratio is taken within the repetition (``engine.bench.paired_stats.paired_ratio``: the median of
the per-repetition ratios and the sign test's 95% interval), so a drift shared by the variants
cancels.

Each variant is a ``Cell`` (scene, traversal, frustum, packet size, recursion preset, size,
threads), rendered by its own ``WhittedRenderer`` after one untimed warm-up frame (compilation).
``tools/paired_frames.py`` runs it from the command line; a matrix's ``[paired]`` table runs it
after the matrix's cells (``run_paired``).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from engine.bench.paired_stats import paired_ratio, verdict
from engine.bench.matrix import Cell, Matrix, merged_options
from engine.bench.cell_scenes import SceneCache, cell_scene
from engine.core.atomic import write_json, write_text
from engine.core.threads import numba_threads


def paired_frames(cells: list, repeat: int, log=print) -> dict:
    """{"variants": [{"label", "frame": [s per repetition], "trace": [...], "shade": [...]}],
    "ratios": [{"label", "frame": (median, low, high), "trace": (...)}]} for ``cells`` (Cell, all
    at the first cell's thread count): each later variant's time over the first one's, paired by
    repetition (above 1: the later variant is slower)."""
    from engine.render.whitted import WhittedRenderer

    if len(cells) < 2 or repeat < 1:
        raise ValueError("paired_frames needs at least two variants and one repetition")
    scenes = SceneCache()
    with numba_threads(cells[0].threads):
        renderers = []
        for cell in cells:
            renderer = WhittedRenderer(cell_scene(scenes.get(cell.scene), cell), cell.config())
            start = time.perf_counter()
            renderer.render()  # compiles (or loads) this variant's kernels; not timed
            log(f"{describe(cell)}: warm-up frame {time.perf_counter() - start:.1f} s")
            renderers.append(renderer)
        runs = [{"frame": [], "trace": [], "shade": []} for _ in cells]
        for rep in range(repeat):
            order = range(len(cells)) if rep % 2 == 0 else reversed(range(len(cells)))
            for v in order:
                seconds = renderers[v].render().seconds
                runs[v]["frame"].append(seconds["total"])
                runs[v]["trace"].append(sum(seconds["trace"].values()))
                runs[v]["shade"].append(seconds["shade"])
    variants = [{"label": describe(cell), **run} for cell, run in zip(cells, runs)]
    ratios = [{"label": v["label"], **{what: paired_ratio(v[what], variants[0][what]) for what in ("frame", "trace")}}
              for v in variants[1:]]
    return {"variants": variants, "ratios": ratios}


def describe(cell: Cell) -> str:
    """A variant's label: traversal/frustum packet size."""
    return f"{cell.traversal.label}/{cell.frustum.label} {cell.packet}x{cell.packet}"


def markdown(result: dict, title: str) -> str:
    """The medians of every variant and the paired ratios as a markdown report."""
    lines = [f"# {title}", "",
             "| variant | frame ms | FPS | trace ms | shading ms |", "|---|---:|---:|---:|---:|"]
    for v in result["variants"]:
        frame = float(np.median(v["frame"]))
        lines.append(f"| {v['label']} | {1e3 * frame:.1f} | {1 / frame:.2f} | {1e3 * np.median(v['trace']):.1f} | "
                     f"{1e3 * np.median(v['shade']):.1f} |")
    first = result["variants"][0]["label"]
    lines += ["", f"Each variant's time over {first}'s in the same repetition: the median ratio and its "
              "95% interval (the sign test's order statistics); below 1 the variant is faster.", "",
              "| variant | frame, paired [95%] | | trace, paired [95%] | |", "|---|---|---|---|---|"]
    for r in result["ratios"]:
        cells = []
        for what in ("frame", "trace"):
            median, low, high = r[what]
            speed = verdict(low, high)
            cells += [f"{median:.3f} [{low:.3f}, {high:.3f}] = {1 / median:.2f}x the first's speed",
                      {"faster": "faster", "slower": "slower", "same": "the same within the noise"}[speed]]
        lines.append(f"| {r['label']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


#: The files ``run_paired`` writes into a run's folder.
PAIRED_FILES = ("paired.json", "paired.md")


def run_paired(matrix: Matrix, out: Path) -> list:
    """The matrix's ``[paired]`` variants rendered frame by frame against the first
    (``paired_frames``) for every (scene, recursion, size) of its cells, in their
    order, at the matrix's thread count; writes paired.json ({"repeat", "groups": [{"scene",
    "recursion", "size", "variants", "ratios"}]}) and paired.md into ``out``. Returns their paths."""
    groups = dict.fromkeys((c.scene, c.recursion, c.width, c.height) for c in matrix.cells)
    results, texts = [], []
    for scene, recursion, width, height in groups:
        cells = [Cell(scene, traversal, frustum, packet, recursion, width, height, threads=matrix.threads,
                      embree=False, options=merged_options(matrix.options, traversal.options))
                 for traversal, frustum, packet in matrix.paired]  # not the first cell's: its entry's options
        title = f"{scene.label} {recursion} {width}x{height}"
        print(f"packetrt bench: paired frames, {title}: {', '.join(describe(c) for c in cells)}", file=sys.stderr)
        result = paired_frames(cells, matrix.paired_repeat, log=lambda m: None)
        results.append({"scene": scene.label, "recursion": recursion, "size": f"{width}x{height}", **result})
        texts.append(markdown(result, title).replace("# ", "## ", 1))
    write_json(out / PAIRED_FILES[0], {"repeat": matrix.paired_repeat, "groups": results})
    write_text(out / PAIRED_FILES[1], f"# {matrix.name}: frames paired by repetition ({matrix.paired_repeat} "
                                      f"repetitions, {matrix.threads or 'all'} threads)\n\n" + "\n".join(texts))
    return [out / name for name in PAIRED_FILES]
