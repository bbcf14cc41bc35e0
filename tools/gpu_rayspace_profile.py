"""Where a device ``rayspace`` frame's time goes: every rayspace kernel launch timed alone.

On a GPU machine (after ``. tools/gpu_device_setup.sh``):

    python3 tools/gpu_rayspace_profile.py                          # kitchen-paper at 1024x1024
    python3 tools/gpu_rayspace_profile.py --scene cornell-box --recursion render-defaults --frames 9
    python3 tools/gpu_rayspace_profile.py --shadow-grid pixel       # shadow rays at their pixels (the paper)

Renders the scene's recursion preset with ``GpuWhittedRenderer`` and the ``rayspace`` traversal:
compile apart, then ``--frames`` frames (their times and median), then one more frame in which
every launch of the rayspace kernels (hierarchy build, the stream's ``_expand`` per level, the
final tests, the scans) waits for the GPU before and after, summed per kernel (``_expand`` per
level). The frame's own wall time with those waits is printed beside it: the sums are the
kernels' times plus a launch each, not a share of the unprofiled frame.
Session 17's profile of the kitchen is in the README's GPU section.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: The rayspace kernels (module attribute names) that are launched from Python.
KERNELS = {"_expand", "_root_pairs", "nearest_t", "nearest_prim", "merge_batch", "any_hit", "reset_answers",
           "reset_flags", "_count_blocks", "_fill_slots", "_order_blocks", "_leaves", "_inner", "_spheres",
           "_node_scale", "fill_array", "_scan_blocks", "_scan_sums", "_add_offsets", "_bounds", "_count_keys",
           "_fill_cells", "_place_ranked"}


class TimedKernel:
    """Stands in for a kernel: ``kernel[grid, block](*args)`` waits for the GPU before and after
    and adds the time to ``totals[name]`` (``_expand`` keyed by its level, args[2])."""

    def __init__(self, name, kernel, totals, cuda):
        self.name, self.kernel, self.totals, self.cuda = name, kernel, totals, cuda

    def __getitem__(self, config):
        launch = self.kernel[config]

        def run(*args):
            key = f"{self.name}@{args[2]}" if self.name == "_expand" else self.name
            self.cuda.synchronize()
            start = time.perf_counter()
            launch(*args)
            self.cuda.synchronize()
            row = self.totals[key]
            row[0] += time.perf_counter() - start
            row[1] += 1
        return run


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="bart-kitchen")
    parser.add_argument("--recursion", default="kitchen-paper")
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--compare-prepared", action="store_true",
                        help="also render --frames frames alternating with the rayspace launches prepared "
                             "(engine.gpu.launch.LaunchCache) and through numba's dispatcher, and print both medians")
    parser.add_argument("--pair-budget", type=int, default=268435456)
    parser.add_argument("--shadow-grid", default="light", help="options.rayspace.shadow_grid: light or pixel")
    parser.add_argument("--secondary-grid", default="direction",
                        help="options.rayspace.secondary_grid: direction or pixel")
    args = parser.parse_args(argv)

    from numba import cuda

    from engine.bench.dynamic import cell_config
    from engine.gpu import scan
    from engine.gpu.frame import GpuWhittedRenderer
    from engine.gpu.rayspace import final, hierarchy, ray_grids, stream
    from scenes.catalog import scene_from_config

    config = cell_config({"resolution": args.size}, {"name": args.scene, "recursion": args.recursion},
                         {"label": "rayspace", "traversal": "rayspace",
                          "options": {"rayspace": {"pair_budget": args.pair_budget,
                                                  "shadow_grid": args.shadow_grid,
                                                  "secondary_grid": args.secondary_grid}}}, "gpu_rayspace_profile")
    renderer = GpuWhittedRenderer(scene_from_config(config.scene, config.override), config)
    print(f"compile {renderer.warm_up():.1f} s", flush=True)
    times = [renderer.render().seconds["total"] for _ in range(args.frames)]
    print("frames ms", [round(t * 1e3, 1) for t in times], "median", round(statistics.median(times) * 1e3, 1))
    caches = {id(c): c for c in (getattr(getattr(t, "scratch", None), "launch", None)
                                 for t in renderer.traversal.values()) if c is not None}
    for cache in caches.values():  # the traversal's prepared launches (engine.gpu.launch.LaunchCache)
        print(f"prepared launches: {cache.hits} replayed, {cache.misses} prepared, {len(cache.entries)} held")
    if args.compare_prepared and caches:
        paired = {True: [], False: []}
        for _ in range(args.frames):
            for enabled in (True, False):
                for cache in caches.values():
                    cache.enabled = enabled
                paired[enabled].append(renderer.render().seconds["total"])
        for cache in caches.values():
            cache.enabled = True
        print("alternating frames ms: prepared", [round(t * 1e3, 1) for t in paired[True]], "median",
              round(statistics.median(paired[True]) * 1e3, 1), "| dispatcher", [round(t * 1e3, 1) for t in paired[False]],
              "median", round(statistics.median(paired[False]) * 1e3, 1))

    totals = defaultdict(lambda: [0.0, 0])
    for module in (stream, final, hierarchy, ray_grids, scan):
        for name in KERNELS & set(vars(module)):
            setattr(module, name, TimedKernel(name, getattr(module, name), totals, cuda))
    cuda.synchronize()
    start = time.perf_counter()
    result = renderer.render()
    cuda.synchronize()
    print(f"profiled frame {(time.perf_counter() - start) * 1e3:.1f} ms (every launch waited for)")
    for key, (seconds, launches) in sorted(totals.items(), key=lambda kv: -kv[1][0]):
        print(f"  {key:16s} {seconds * 1e3:8.2f} ms  {launches} launches")
    print(f"kernels {sum(s for s, _ in totals.values()) * 1e3:.1f} ms")
    record = result.extra.get("rayspace", {}).get("primary")
    if record:  # the traversal's running totals: every call since the renderer was made
        print(f"over all {record['calls']} calls so far (warm-up and every frame above), by level, 0 = rays:")
        print("  cone-sphere tests", record["cone_sphere_tests"])
        print("  pairs after", record["pairs_after"], "candidates per ray", round(record["candidates_per_ray"], 1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
