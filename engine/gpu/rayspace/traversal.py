"""``DeviceRaySpace``: the two queries of the ray-space traversal over a device ray queue."""
from __future__ import annotations

import numpy as np

from engine.core.errors import ConfigError
from engine.gpu.device import BLOCK, blocks, require_cuda
from engine.gpu.rayspace import final
from engine.gpu.rayspace.hierarchy import build
from engine.gpu.rayspace.ray_grids import direction_grid_pixels, light_grid_pixels
from engine.rayspace.direction_grid import checked_secondary_grid
from engine.rayspace.light_grid import checked_shadow_grid
from engine.gpu.rayspace.scratch import Scratch
from engine.gpu.rayspace.stream import WORK_SLOTS, WORK_TESTS, Stream
from engine.gpu.scan import Scanner

cuda = require_cuda()

MAX_PAIR_BUDGET = 2**31 - 1   # stream positions are i32 (the scan's type)
# The batching policy of the CPU plugin (traversals/rayspace.py): a first batch of at most
# budget / PROBE_SHARE triangles; later batches aimed at BATCH_FILL of the budget from the last
# batch's peak; after an overflow, deeper levels are expected to need OVERFLOW_GROWTH times more.
PROBE_SHARE = 256
BATCH_FILL = 0.8
OVERFLOW_GROWTH = 4
SUMMED = ("calls", "rays", "triangles", "reversed_batches", "candidates", "batches", "retries")
PER_LEVEL = ("cone_sphere_tests", "pairs_before", "pairs_after")


def new_record(levels: int) -> dict:
    """Statistics with the keys of the CPU plugin's ``stats.extra["rayspace"]`` (lists by level,
    0 = rays, last = root), without its per-phase seconds (the device runs asynchronously)."""
    return {"calls": 0, "rays": 0, "triangles": 0, "levels": levels, "reversed_batches": 0,
            "cone_sphere_tests": [0] * (levels + 1), "pairs_before": [0] * (levels + 1),
            "pairs_after": [0] * (levels + 1), "candidates": 0, "candidates_per_ray": 0.0,
            "batches": 0, "retries": 0, "peak_pairs": 0}


def add_record(total: dict, record: dict) -> None:
    """Add one call's record to a running total (sums, lists elementwise, levels and peak by max)."""
    for key in SUMMED:
        total[key] += record[key]
    total["levels"] = max(total["levels"], record["levels"])
    total["peak_pairs"] = max(total["peak_pairs"], record["peak_pairs"])
    for key in PER_LEVEL:
        mine = total[key]
        mine.extend([0] * (len(record[key]) - len(mine)))
        for level, value in enumerate(record[key]):
            mine[level] += value
    total["candidates_per_ray"] = total["candidates"] / total["rays"] if total["rays"] else 0.0


def _batch_size(budget: int, triangles: int, pairs: int) -> int:
    return max(1, int(BATCH_FILL * budget * triangles / max(pairs, 1)))


class DeviceRaySpace:
    """Roger et al.'s ray-space hierarchy, built on the device for every call (one generation's
    queue) and traversed with (node, triangle) streams compacted by prefix sums.

    tris: the scene's ``DeviceTriangles`` (v0, v1, v2 f32[T,3] are read; spheres are recomputed
    from them on every call, so an animated scene needs nothing refitted); host_tris: the same
    ``engine.core.types.Triangles`` on the host (only its count is checked). pair_budget: the
    most (node, triangle) pairs one level's stream may hold, as the CPU plugin's option; a level
    that would exceed it splits the triangles into batches, and a single triangle that exceeds
    it raises ConfigError with the number it needs. shadow_grid: "light" (rays given a
    ``light`` grouped by their direction from it, ``engine.rayspace.light_grid``) or "pixel"
    (by ancestral pixel, the paper's layout), as the CPU plugin's option; secondary_grid:
    "direction" (closest-hit calls with ``secondary=True`` grouped by screen tile and direction,
    ``engine.rayspace.direction_grid``) or "pixel".

    ``stats``: the running totals over calls (keys of ``new_record``); ``last``: the last call's.
    """

    name = "rayspace"
    uses_bvh = False

    def __init__(self, tris, host_tris, pair_budget: int = 4194304, shadow_grid: str = "light",
                 secondary_grid: str = "direction"):
        if isinstance(pair_budget, bool) or not isinstance(pair_budget, (int, np.integer)) \
                or not 1 <= pair_budget <= MAX_PAIR_BUDGET:
            raise ConfigError(f"options.rayspace: pair_budget must be an integer in 1..{MAX_PAIR_BUDGET}, "
                              f"got {pair_budget!r}")
        if host_tris is not None and host_tris.v0.shape[0] != tris.count:
            raise ValueError(f"device triangles ({tris.count}) and host triangles ({host_tris.v0.shape[0]}) "
                             "are not the same scene")
        self.tris = tris
        self.pair_budget = int(pair_budget)
        self.shadow_grid = checked_shadow_grid(shadow_grid)
        self.secondary_grid = checked_secondary_grid(secondary_grid)
        self.scratch = Scratch(hint=f"lower [options.rayspace] pair_budget (now {int(pair_budget):,} pairs; "
                                    "both pair buffers hold it) or render smaller")
        self.scanner = Scanner(self.scratch.launch)
        self.stream = Stream(self.scratch)
        self.stats = new_record(0)
        self.last = new_record(0)

    # -- the two queries ---------------------------------------------------------------
    def closest(self, org, dirs, tmin, tmax, pixel, n, width, height, t_out, prim_out, u_out, v_out,
                light=None, secondary=False) -> None:
        """Closest hits of rays 0 .. n-1 of a device queue.

        org, dirs: f32[C,3]; tmin, tmax: f32[C]; pixel: i32[C] ancestral pixel y * width + x on
        the width x height screen (several rays may share one; -1 or tmax < tmin = dead);
        C >= n. Writes t_out f32, prim_out i32, u_out, v_out f32 (length >= n): the hit of the
        shared watertight test over all triangles with the smallest t, ties to the smaller
        index (inf, -1, 0, 0 on a miss), bit for bit the CPU's answer. light: as ``occluded``.
        secondary: the rays are reflections and refractions (grouped by ``secondary_grid``).
        """
        n = int(n)
        launch = self.scratch.launch
        best_t = self.scratch.get("best_t", n, np.float32)
        best_prim = self.scratch.get("best_prim", n, np.int32)
        if n:
            launch(final.reset_answers, blocks(n), BLOCK, n, t_out, prim_out, u_out, v_out, best_t, best_prim)
        tris = self.tris

        def finish(slots, cand, count):
            pair_t = self.scratch.get("pair_t", count, np.float32)
            args = (slots, cand, count, self._h.slot_ray)
            launch(final.nearest_t, blocks(count), BLOCK, *args, org, dirs, tmin, tmax, tris.v0, tris.v1, tris.v2,
                   pair_t, best_t)
            launch(final.nearest_prim, blocks(count), BLOCK, *args, pair_t, best_t, best_prim)
            launch(final.merge_batch, blocks(n), BLOCK, n, org, dirs, tmin, tmax, tris.v0, tris.v1, tris.v2, best_t,
                   best_prim, t_out, prim_out, u_out, v_out)

        self._trace(org, dirs, tmin, tmax, pixel, n, width, height, light, finish, secondary)

    def occluded(self, org, dirs, tmin, tmax, pixel, n, width, height, out, light=None) -> None:
        """Any hit of rays 0 .. n-1 (arguments as ``closest``): out[r] = 1 (or True) when some
        triangle is hit within [tmin, tmax], else 0; out: u8 or bool, length >= n.

        light: the point light every ray aims at (3 floats), or None. Given, the hierarchy is
        built over the segments reversed to leave the light (the paper's shadow rays): tight
        leaves, the same answers; with ``shadow_grid = "light"`` the rays are also grouped by
        their direction from it. Any point is correct; only culling depends on it.
        """
        n = int(n)
        launch = self.scratch.launch
        if n:
            launch(final.reset_flags, blocks(n), BLOCK, n, out)
        tris = self.tris

        def finish(slots, cand, count):
            launch(final.any_hit, blocks(count), BLOCK, slots, cand, count, self._h.slot_ray, org, dirs, tmin, tmax,
                   tris.v0, tris.v1, tris.v2, out)

        self._trace(org, dirs, tmin, tmax, pixel, n, width, height, light, finish)

    def forget_launches(self) -> None:
        """Drop the prepared launches (``scratch.launch``), and with them every array they hold:
        the caller is about to free the queues it passed in."""
        self.scratch.launch.clear()

    # -- the work ----------------------------------------------------------------------
    def _trace(self, org, dirs, tmin, tmax, pixel, n, width, height, light, finish, secondary=False) -> None:
        """Build, then stream triangle batches down and hand each final (slot, triangle) stream
        to ``finish(slots, tris, count)``; the statistics go to ``last`` and ``stats``."""
        if int(width) < 1 or int(height) < 1:
            raise ValueError(f"screen {width}x{height} must be at least 1x1")
        n_tris = self.tris.count
        if n == 0 or n_tris == 0:
            self.last = new_record(0)
            return
        if light is not None and self.shadow_grid == "light":
            pixel, width = light_grid_pixels(self.scratch, self.scanner, dirs, tmin, tmax, pixel, n, int(width),
                                             int(height))
            height = width
        elif light is None and secondary and self.secondary_grid == "direction":
            pixel, width = direction_grid_pixels(self.scratch, self.scanner, dirs, tmin, tmax, pixel, n, int(width),
                                                 int(height))
            height = width
        h = build(self.scratch, self.scanner, self.tris, org, dirs, tmin, tmax, pixel, n, int(width), int(height),
                  light)
        self._h = h
        record = new_record(h.levels)
        record.update(calls=1, rays=h.n_slots, triangles=n_tris, reversed_batches=int(light is not None))
        if h.n_slots == 0:
            self._finish_record(record, None)
            return
        work = self.scratch.get("work", h.levels + 1, np.int64, 3)
        work.copy_to_device(np.zeros((h.levels + 1, 3), np.int64))
        budget = self.pair_budget
        first, size = 0, min(n_tris, max(1, budget // PROBE_SHARE))
        while first < n_tris:
            last = min(n_tris, first + size)
            record["pairs_before"][h.levels] += last - first
            slots, cand, count, overflow, peak = self.stream.descend(h, first, last, budget, work,
                                                                      record["pairs_after"])
            if overflow is not None:
                level, needed = overflow
                if last - first == 1:
                    raise ConfigError(
                        f"options.rayspace: pair_budget = {budget} is too small: triangle {first} alone needs "
                        f"{needed} (node, triangle) pairs at level {level} of the ray hierarchy ({h.n_slots} "
                        f"rays); raise pair_budget to at least {needed} (deeper levels may need more)")
                record["retries"] += 1
                size = min((last - first) // 2, _batch_size(budget, last - first, OVERFLOW_GROWTH * needed))
                continue
            record["peak_pairs"] = max(record["peak_pairs"], peak)
            if count:
                finish(slots, cand, count)
            record["candidates"] += count
            record["batches"] += 1
            size = _batch_size(budget, last - first, peak)
            first = last
        self._finish_record(record, work)

    def _finish_record(self, record: dict, work) -> None:
        if work is not None:
            done = work.copy_to_host()
            for level in range(record["levels"]):
                record["pairs_before"][level] += int(done[level, WORK_SLOTS])
                record["cone_sphere_tests"][level] += int(done[level, WORK_TESTS])
        record["candidates_per_ray"] = record["candidates"] / record["rays"] if record["rays"] else 0.0
        self.last = record
        add_record(self.stats, record)
