"""``rayspace``: the ray-space hierarchy of Roger, Assarsson and Holzschuch (2007).

Instead of a hierarchy over the scene, a hierarchy over the rays of one batch, rebuilt for
every batch: nothing depends on the scene's layout, so moving geometry costs nothing to
rebuild. Ignores the BVH and the frusta it is given.

How it works
    1. Build (``engine.rayspace.cone_sphere``): the batch's live rays are indexed by a pixel on a
       screen: camera rays by their own pixel on the ``packets.width x packets.height`` screen,
       shadow and secondary rays by default at the pixel the light or direction grid gives them
       (options below; "pixel" keeps their ancestral pixels, as the paper does); each ray is an
       exact cone-sphere (radius 0, spread 0, reach bounded by tmax), each 2x2 pixel block holds
       all its rays, and every coarser level of the mip-map holds four nodes of the level below,
       up to one root.
    2. Traversal (``engine.rayspace.pair_stream``): a stream of (node, triangle) pairs starts with every
       triangle at the root; per level each pair's children are tested against the
       triangle's bounding sphere (``engine.rayspace.triangle_spheres``) and the survivors are compacted
       with a parallel prefix sum. The test is conservative: a pair is dropped only when no
       ray under the node can touch the triangle.
    3. Final tests: the candidate triangles of each ray get the shared watertight test and the
       shared tie rule, so the hits are the kernel's own answer over all triangles, bit for
       bit, and so ``single``'s and every packet traversal's (tests/test_offset.py checks all
       of them against a brute-force pass on the Whitted loop's rays).

Shadow rays
    A ``shadow`` batch whose rays all aim at one point (a point light) is indexed reversed, as
    segments that leave the light: the leaves then have (rounding-)zero spatial extent and
    only the cones differ. The reversal changes the indexing only. A reversed leaf covers
    exactly the original segment: from the light it starts after the gap that tmax leaves
    before the light and stops at the original tmin offset, not at the surface point behind
    it. The exact tests then use the original rays with their own [tmin, tmax], so the answer
    is the original ray's, bit for bit; testing the reversed ray instead would reach the
    surface it leaves at the far end, where the tmin offset has no reversed counterpart.
    Rays of a batch that aim at different lights are not reversed.
    Reversed rays are placed on a grid over their directions from the light
    (``engine.rayspace.light_grid``) instead of at their pixels, unless ``shadow_grid =
    "pixel"``: their nodes' cones are then as narrow as the rays allow; the same answers.

Options (``[options.rayspace]`` in a config, or keyword arguments of the class)
    pair_budget = 4194304   most (node, triangle) pairs one stream may hold (1 .. 2^31-1).
                            A level that would overflow splits the triangles into batches
                            traced one after another, merged by closest hit. A budget too
                            small for one triangle's pairs raises ConfigError with the need.
    shadow_grid = "light"   how rays that share a light are grouped: "light", by direction
                            from the light; "pixel", by ancestral pixel (the paper's layout).
    secondary_grid = "direction"   how reflection and refraction rays are grouped:
                            "direction", by screen tile and then direction
                            (``engine.rayspace.direction_grid``: the kitchen's frame 0.69x,
                            cosine-n's reflections 0.45-0.89x, simpler scenes' frames
                            1.03-1.06x); "pixel", by ancestral pixel (the paper's layout).
                            Camera rays are always grouped by pixel.

Statistics (``stats.extra["rayspace"]``, summed over calls; lists are indexed by level,
0 = rays, last = root): ``cone_sphere_tests``, ``pairs_before`` (child slots before
compaction), ``pairs_after``, ``candidates`` and ``candidates_per_ray`` (final triangle
tests per live ray), ``rays``, ``batches``, ``retries`` (batches abandoned for overflow;
their work is in the counts and times), ``peak_pairs``, ``reversed_batches``, and
``seconds`` per phase (triangle_spheres, build, traversal, compaction, sort, final).
Triangle tests also go to ``stats.counters[:, 1, 0]``.

When it pays (measured: one thread, bunny as the reflector, hits identical to ``single``)
    The final tests match a BVH's: 5.2-6.3 candidate triangles per ray on the bunny (the
    paper reports 2.5-4.5), 20-33 in the Cornell box, whose big walls have big spheres. The
    cost is the traversal: a triangle is paired with every node whose cone can reach it, and
    reflection cones off a curved, finely tessellated surface open wide (median spread 10
    degrees at 2x2 pixels, 49 at 8x8), so cone-sphere tests grow with the triangle count:
    at 512^2, 24 per ray for 948 triangles, 1,190 for 69,451, and the time against
    ``single`` from 3x to 27x. Reversed shadow rays stay tight (10-70 tests per ray): 2-3x
    ``single``. Growth with resolution is sub-linear, as the paper says: 16x the rays
    (256^2 -> 1024^2) cost 3.5x the time for bunny reflections, 4.2x for its shadows,
    against 12x for ``single``. It beats no BVH traversal here, even with a per-frame BVH
    rebuild (42 ms for 69,451 triangles) added to theirs; closest are shadow rays at
    1024^2: 194 ms against 136 ms for rebuild plus ``single``.
"""
from __future__ import annotations

import time

import numpy as np
from numba import get_thread_id, njit, prange

from engine.rayspace.cone_sphere import absolute_slack, build_hierarchy, reversed_segment
from engine.rayspace.direction_grid import checked_secondary_grid, direction_grid_pixels
from engine.rayspace.light_grid import checked_shadow_grid, light_grid_pixels
from engine.core.errors import ConfigError
from engine.core.triangle import F32_INF, closer, intersect_triangle, ray_shear
from engine.rayspace.pair_stream import expand, group_by_slot, root_stream
from engine.core.registry import register_traversal
from engine.rayspace.triangle_spheres import triangle_spheres
from engine.core.types import COUNTER_RAY_TRI, check_answer_arrays, empty_hits, thread_counters

CHUNK = 256               # slots per prange task of the final tests
MAX_PAIR_BUDGET = 2**31 - 1   # stream indices are i32
# Reverse a shadow batch only when every ray passes within this fraction of the longest
# segment of one point; the leftover distance becomes the leaf radius, so this is about
# efficiency, never correctness.
APEX_TOLERANCE = 1e-4
BATCH_FILL = 0.8          # aim each triangle batch at this fraction of the pair budget
OVERFLOW_GROWTH = 4       # after an overflow, expect the levels below to need this many times more
PROBE_SHARE = 256         # the first batch has at most budget / PROBE_SHARE triangles
PHASES = ("triangle_spheres", "build", "traversal", "compaction", "sort", "final")
SECONDARY_KINDS = ("reflection", "refraction")  # placed by ``secondary_grid``


@njit(cache=True, parallel=True)
def _final_tests(slot_ray, start, cand, v0, v1, v2, org, dirs, tmin, tmax, any_hit,
                 best_t, best_prim, best_u, best_v, counters):
    """Watertight tests of each slot's candidates, merged into the running best hit.

    slot_ray: i32[S]; start: i64[S+1]; cand: i32[P] (see ``group_by_slot``). best_*: f32/i32[R]
    hold the result of earlier triangle batches and are updated in place; for any_hit a ray
    that is already occluded is skipped and a ray stops at its first hit.
    counters: i64[threads,3,D] or None (triangle tests go to depth 0).
    """
    n_slots = slot_ray.shape[0]
    for chunk in prange((n_slots + CHUNK - 1) // CHUNK):
        thread = get_thread_id()
        for s in range(chunk * CHUNK, min(n_slots, (chunk + 1) * CHUNK)):
            if start[s] == start[s + 1]:
                continue
            r = slot_ray[s]
            bt, bp, bu, bv = best_t[r], best_prim[r], best_u[r], best_v[r]
            if any_hit and bp >= 0:
                continue
            t_lo = tmin[r]
            t_hi = min(tmax[r], bt)  # a tie with an earlier batch's hit is still accepted
            kx, ky, kz, sx, sy, sz = ray_shear(dirs[r, 0], dirs[r, 1], dirs[r, 2])
            okx, oky, okz = org[r, kx], org[r, ky], org[r, kz]
            for i in range(start[s], start[s + 1]):
                tri = cand[i]
                if counters is not None:
                    counters[thread, COUNTER_RAY_TRI, 0] += 1
                t, u, v = intersect_triangle(okx, oky, okz, kx, ky, kz, sx, sy, sz, t_lo, t_hi,
                                             v0, v1, v2, tri)
                if t < F32_INF and closer(t, tri, bt, bp):
                    bt, bp, bu, bv = t, tri, u, v
                    if any_hit:
                        break
                    t_hi = t
            best_t[r], best_prim[r], best_u[r], best_v[r] = bt, bp, bu, bv


def live_lanes(rays) -> np.ndarray:
    """bool[R]: lanes with a pixel and a non-empty [tmin, tmax]."""
    return (rays.pixel >= 0) & (rays.tmin <= rays.tmax)


@njit(cache=True)
def _line_sums(org, dirs, tmin, tmax, live):
    """Normal equations of the point nearest to every live ray's line, sum over rays of
    (I - u u^T)(p - o) = 0 with u = d / |d|: returns (m f64[3,3], b f64[3]), or a zero m when
    a live ray has a zero direction or an unbounded segment (no shared endpoint then)."""
    m = np.zeros((3, 3))
    b = np.zeros(3)
    u = np.empty(3)
    for r in range(org.shape[0]):
        if not live[r]:
            continue
        length = 0.0
        for i in range(3):
            length += np.float64(dirs[r, i]) ** 2
        length = np.sqrt(length)
        if not (length > 0 and np.isfinite(tmax[r]) and np.isfinite(tmin[r])):
            return np.zeros((3, 3)), b
        along = 0.0
        for i in range(3):
            u[i] = dirs[r, i] / length
            along += u[i] * org[r, i]
        for i in range(3):
            b[i] += org[r, i] - u[i] * along
            m[i, i] += 1.0
            for j in range(3):
                m[i, j] -= u[i] * u[j]
    return m, b


@njit(cache=True)
def _apex_spread(org, dirs, tmin, tmax, live, ax, ay, az):
    """(largest gap, largest reach) of the live rays reversed from the point a."""
    gap_max = 0.0
    reach_max = 0.0
    for r in range(org.shape[0]):
        if live[r]:
            gap, reach = reversed_segment(org, dirs, tmin, tmax, r, ax, ay, az)
            gap_max = max(gap_max, gap)
            reach_max = max(reach_max, reach)
    return gap_max, reach_max


def shared_apex(rays, live: np.ndarray):
    """The point every live ray aims at (f64[3]), or None when they do not share one.

    The candidate is the least-squares nearest point to all ray lines; it is accepted when
    the leaf radii the reversed build would get are all tiny against the segment lengths.
    """
    if not live.any():
        return None
    m, b = _line_sums(rays.org, rays.dir, rays.tmin, rays.tmax, live)
    if not m.any():
        return None
    p = np.linalg.lstsq(m, b, rcond=None)[0]
    p = p.astype(np.float32).astype(np.float64)  # the build stores the apex as float32
    gap, reach = _apex_spread(rays.org, rays.dir, rays.tmin, rays.tmax, live, p[0], p[1], p[2])
    return p if gap <= APEX_TOLERANCE * reach else None


def _new_record(levels: int) -> dict:
    return {"calls": 0, "rays": 0, "triangles": 0, "levels": levels, "reversed_batches": 0,
            "cone_sphere_tests": [0] * (levels + 1), "pairs_before": [0] * (levels + 1),
            "pairs_after": [0] * (levels + 1), "candidates": 0, "candidates_per_ray": 0.0,
            "batches": 0, "retries": 0, "peak_pairs": 0, "seconds": dict.fromkeys(PHASES, 0.0)}


def _accumulate(stats, record: dict) -> None:
    """Add one call's record to stats.extra["rayspace"] (lists elementwise, peak by max)."""
    total = stats.extra.setdefault("rayspace", _new_record(0))
    for key in ("calls", "rays", "triangles", "reversed_batches", "candidates", "batches", "retries"):
        total[key] += record[key]
    total["levels"] = max(total["levels"], record["levels"])
    total["peak_pairs"] = max(total["peak_pairs"], record["peak_pairs"])
    for key in ("cone_sphere_tests", "pairs_before", "pairs_after"):
        mine = total[key]
        mine.extend([0] * (len(record[key]) - len(mine)))
        for level, value in enumerate(record[key]):
            mine[level] += value
    for phase, seconds in record["seconds"].items():
        total["seconds"][phase] += seconds
    total["candidates_per_ray"] = total["candidates"] / total["rays"] if total["rays"] else 0.0


def _descend(h, first, last, centre, radius, abs_tol, budget, record, seconds):
    """Stream triangles first .. last-1 from the root down to the rays.

    Returns (slots i32[P], tris i32[P], None, peak) with the final (slot, triangle) pairs and
    the largest stream on the way, or (None, None, (level, pairs needed), peak) as soon as a
    level would exceed ``budget``. The work done is added to ``record`` and ``seconds``.
    """
    nodes, tris = root_stream(first, last)
    peak = last - first
    record["pairs_before"][h.levels] += last - first
    record["pairs_after"][h.levels] += last - first
    for level in range(h.levels, 0, -1):
        out_nodes, out_tris, step = expand(h, level, nodes, tris, centre, radius, abs_tol, budget)
        record["cone_sphere_tests"][level - 1] += step.tests
        record["pairs_before"][level - 1] += step.slots
        seconds["traversal"] += step.count_seconds
        seconds["compaction"] += step.compact_seconds
        if out_nodes is None:
            return None, None, (level - 1, step.survivors), peak
        record["pairs_after"][level - 1] += step.survivors
        peak = max(peak, step.survivors)
        nodes, tris = out_nodes, out_tris
    return nodes, tris, None, peak


def _budget_needed(h, first, last, centre, radius, abs_tol, chunk: int = 4096) -> int:
    """The smallest pair budget under which every triangle first .. last-1 passes alone: the
    most (node, triangle) pairs any one of them makes at any level, counted through every level
    (an overflow's own count stops at the level that overflowed, and deeper levels usually need
    more). Triangles go ``chunk`` at a time, so the count needs no more memory than a trace.
    Answers MAX_PAIR_BUDGET when even that is not enough."""
    most = 1
    for start in range(first, last, chunk):
        stop = min(last, start + chunk)
        nodes, tris = root_stream(start, stop)
        for level in range(h.levels, 0, -1):
            nodes, tris, step = expand(h, level, nodes, tris, centre, radius, abs_tol, MAX_PAIR_BUDGET)
            if nodes is None:
                return MAX_PAIR_BUDGET
            if tris.size:
                most = max(most, int(np.bincount(tris - start).max()))
    return most


def _batch_size(budget: int, triangles: int, pairs: int) -> int:
    """Triangles per batch that would fill BATCH_FILL of the budget, had ``triangles``
    triangles needed ``pairs`` pairs at their fullest level (neighbouring triangles in a mesh
    need similar numbers, so the last batch predicts the next)."""
    return max(1, int(BATCH_FILL * budget * triangles / max(pairs, 1)))


@register_traversal("rayspace")
class RaySpaceTraversal:
    """Ray-space cone-sphere hierarchy over the batch's rays (Roger et al. 2007); no scene hierarchy."""

    OPTIONS = {"pair_budget": 1 << 22, "shadow_grid": "light", "secondary_grid": "direction"}
    #: The hierarchy is over the rays: a moving scene has no structure of ours to keep current.
    uses_bvh = False
    #: Frusta are not read: the tracer builds none for this traversal.
    uses_frusta = False

    def __init__(self, pair_budget=OPTIONS["pair_budget"], shadow_grid=OPTIONS["shadow_grid"],
                 secondary_grid=OPTIONS["secondary_grid"]):
        """Options as in the module doc; a bad value is a ConfigError."""
        if isinstance(pair_budget, bool) or not isinstance(pair_budget, (int, np.integer)) \
                or not 1 <= pair_budget <= MAX_PAIR_BUDGET:
            raise ConfigError(f"options.rayspace: pair_budget must be an integer in 1..{MAX_PAIR_BUDGET}, "
                              f"got {pair_budget!r}")
        self.pair_budget = int(pair_budget)
        self.shadow_grid = checked_shadow_grid(shadow_grid)
        self.secondary_grid = checked_secondary_grid(secondary_grid)

    # -- the two queries ---------------------------------------------------------------
    def intersect(self, bvh, tris, rays, packets, frusta, hits, stats):
        self._trace(tris, rays, packets, False, hits.t, hits.prim, hits.u, hits.v, stats)

    def occluded(self, bvh, tris, rays, packets, frusta, occluded, stats):
        any_hit = empty_hits(rays.org.shape[0])  # scratch: which triangle stopped each ray
        self._trace(tris, rays, packets, True, any_hit.t, any_hit.prim, any_hit.u, any_hit.v, stats)
        occluded[:] = any_hit.prim >= 0

    # -- the work ----------------------------------------------------------------------
    def _trace(self, tris, rays, packets, any_hit, out_t, out_prim, out_u, out_v, stats):
        n_rays = rays.org.shape[0]
        check_answer_arrays(n_rays, out_t, out_prim, out_u, out_v)
        out_t[:] = np.inf
        out_prim[:] = -1
        out_u[:] = 0
        out_v[:] = 0
        n_tris = tris.v0.shape[0]
        live = live_lanes(rays)
        if n_tris == 0 or not live.any():
            return
        clock = time.perf_counter()
        centre, radius = triangle_spheres(tris.v0, tris.v1, tris.v2)
        seconds = dict.fromkeys(PHASES, 0.0)
        seconds["triangle_spheres"] = time.perf_counter() - clock

        clock = time.perf_counter()
        apex = shared_apex(rays, live) if rays.kind == "shadow" else None
        pixel, width, height = rays.pixel, packets.width, packets.height
        if apex is not None and self.shadow_grid == "light":
            pixel, width = light_grid_pixels(rays.dir, rays.tmin, rays.tmax, rays.pixel, width, height)
            height = width
        elif apex is None and rays.kind in SECONDARY_KINDS and self.secondary_grid == "direction":
            pixel, width = direction_grid_pixels(rays.dir, rays.tmin, rays.tmax, rays.pixel, width, height)
            height = width
        h = build_hierarchy(rays.org, rays.dir, rays.tmin, rays.tmax, pixel, width, height, apex)
        seconds["build"] = time.perf_counter() - clock
        abs_tol = absolute_slack(h, centre, radius)

        record = _new_record(h.levels)
        record.update(calls=1, rays=int(live.sum()), triangles=n_tris, reversed_batches=int(apex is not None))
        budget = self.pair_budget
        # A first batch small enough to pass unless a triangle meets hundreds of nodes per
        # level; its peak then sizes the batches that follow.
        first, size = 0, min(n_tris, max(1, budget // PROBE_SHARE))
        while first < n_tris:
            last = min(n_tris, first + size)
            slots, cand_tris, overflow, peak = _descend(h, first, last, centre, radius, abs_tol, budget,
                                                        record, seconds)
            if overflow is not None:
                level, needed = overflow
                if last - first == 1:
                    enough = _budget_needed(h, first, n_tris, centre, radius, abs_tol)
                    raise ConfigError(
                        f"options.rayspace: pair_budget = {budget} is too small: triangle {first} alone "
                        f"needs {needed} (node, triangle) pairs at level {level} of the ray hierarchy "
                        f"({record['rays']} rays); set pair_budget to at least {enough} (the most any "
                        f"triangle left needs at any level for these rays)")
                record["retries"] += 1
                # ``needed`` counts only down to the overflowing level; deeper levels usually
                # need more, and a retry wastes far more than a batch too small costs.
                size = min((last - first) // 2, _batch_size(budget, last - first, OVERFLOW_GROWTH * needed))
                continue
            record["peak_pairs"] = max(record["peak_pairs"], peak)
            clock = time.perf_counter()
            start, cand = group_by_slot(slots, cand_tris, h.slot_ray.shape[0])
            seconds["sort"] += time.perf_counter() - clock
            clock = time.perf_counter()
            _final_tests(h.slot_ray, start, cand, tris.v0, tris.v1, tris.v2, rays.org, rays.dir,
                         rays.tmin, rays.tmax, any_hit, out_t, out_prim, out_u, out_v,
                         thread_counters(stats))
            seconds["final"] += time.perf_counter() - clock
            record["candidates"] += int(cand.shape[0])
            record["batches"] += 1
            size = _batch_size(budget, last - first, peak)
            first = last
        record["seconds"] = seconds
        if stats is not None:
            _accumulate(stats, record)
