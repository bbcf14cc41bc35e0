"""The one place a batch of rays is traced.

``Tracer.trace(kind, query, rays, packets, tally)`` builds the kind's frusta (none for a traversal
that declares ``uses_frusta = False``: ``single``, ``wide``, ``embree``, ``rayspace``), allocates the
answer arrays, calls the kind's traversal plugin, and adds the seconds (frustum build and query
together: culling is part of what a traversal strategy costs), the live rays and, when the tally
counts, the traversal counters to ``tally``. Everything that casts rays through a plugin goes
through it: the Whitted loop, the ``RayTracer`` API, the audit's reference answers, the
benchmark runner's replays (ours, the per-ray floor, Embree) and ``packetrt show``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numba
import numpy as np
from numba import njit, prange

from engine.core.types import RAY_KINDS, RayBatch, empty_hits, new_stats


@njit(cache=True, parallel=True)
def live_rays(tmin, tmax):
    """How many rays have tmin <= tmax (f32[R] each): the live ones, padding lanes excluded. A
    kernel rather than numpy's count of a comparison, which wrote a bool[R] temporary for
    every batch (the frame's 2.8 M rays on the kitchen)."""
    n = 0
    for i in prange(tmin.shape[0]):
        if tmin[i] <= tmax[i]:
            n += 1
    return n


@dataclass
class Tally:
    """What a run of traces cost, per ray kind: seconds, live rays and (counting) Stats."""

    count: bool = False
    seconds: dict = field(default_factory=lambda: dict.fromkeys(RAY_KINDS, 0.0))
    rays: dict = field(default_factory=lambda: dict.fromkeys(RAY_KINDS, 0))
    stats: dict = field(default_factory=dict)  # kind -> Stats, one per kind, when counting

    def stats_for(self, kind: str):
        """The kind's Stats to accumulate into (None when not counting)."""
        if not self.count:
            return None
        return self.stats.setdefault(kind, new_stats(numba.get_num_threads()))


class Tracer:
    """Traces batches over one BVH and triangle set with one traversal and frustum builder per kind.

    bvh, tris: as in ``engine.core.types``; bounds: the scene box f32[2,3] (frustum builders
    clip to it); traversal: {ray kind: plugin instance}; frustum: {ray kind: frustum builder,
    or None for traversals that take no frusta (``single``, ``embree``)}.
    """

    def __init__(self, bvh, tris, bounds, traversal: dict, frustum: dict):
        self.bvh, self.tris, self.bounds = bvh, tris, bounds
        self.traversal, self.frustum = traversal, frustum

    def prepare(self) -> dict:
        """Let plugins with their own acceleration structure (Embree) build it now, outside any
        timing: {plugin name: build seconds}."""
        seconds = {}
        for plugin in {id(p): p for p in self.traversal.values()}.values():
            if hasattr(plugin, "prepare"):
                seconds[plugin.name] = plugin.prepare(self.tris)
        return seconds

    def trace(self, kind: str, query: str, rays: RayBatch, packets, tally: Tally | None = None, answer=None,
              from_end: bool = False, trial=None):
        """Hits (query "intersect") or bool[R] occlusion flags (query "occluded") of ``rays``
        (R rays in ``packets``), in batch order. ``answer``: arrays of that shape to answer
        into (reset here to all misses, unless the traversal declares ``writes_every_answer``:
        the packet walks store every ray's answer, and the serial reset of a frame's primary
        answers alone is 16 MB of writes), instead of new ones.

        Occlusion through a traversal that ``orders_any_hit`` (the packet walks) also takes
        ``from_end`` (walk the far child first: the rays' ends met first) and ``trial`` (a dict
        that receives the node visits and live rays of a walk from both ends, packet group by
        group: see ``engine.render.shadow_order``). Other traversals ignore both and leave ``trial``
        empty."""
        traversal = self.traversal[kind]
        stats = tally.stats_for(kind) if tally is not None else None
        n = rays.org.shape[0]
        start = time.perf_counter()
        # A traversal that ignores frusta (``uses_frusta = False``) is not charged for building them.
        frusta = self.frusta_for(kind, rays, packets) if getattr(traversal, "uses_frusta", True) else None
        if query == "intersect":
            if answer is None:
                answer = empty_hits(n)
            elif not getattr(traversal, "writes_every_answer", False):
                answer.t.fill(np.inf), answer.prim.fill(-1), answer.u.fill(0), answer.v.fill(0)
            traversal.intersect(self.bvh, self.tris, rays, packets, frusta, answer, stats)
        elif query == "occluded":
            if answer is None:
                answer = np.zeros(n, np.bool_)
            else:
                answer.fill(False)
            if self.orders_any_hit(kind):
                traversal.occluded(self.bvh, self.tris, rays, packets, frusta, answer, stats, from_end, trial)
            else:
                traversal.occluded(self.bvh, self.tris, rays, packets, frusta, answer, stats)
        else:
            raise ValueError(f"query must be 'intersect' or 'occluded', got {query!r}")
        if tally is not None:
            tally.seconds[kind] += time.perf_counter() - start
            tally.rays[kind] += live_rays(rays.tmin, rays.tmax)
        return answer

    def orders_any_hit(self, kind: str) -> bool:
        """Whether the kind's traversal takes ``from_end`` and ``trial`` (see ``trace``)."""
        return getattr(self.traversal[kind], "orders_any_hit", False)

    def frusta_for(self, kind: str, rays: RayBatch, packets):
        """The kind's frusta of ``rays`` (one per packet), or None when its traversal takes none."""
        frustum = self.frustum[kind]
        return None if frustum is None else frustum.build(rays, packets, self.bounds)

    def record_walk(self, kind: str, rays: RayBatch, packets, any_hit: bool, record, from_end: bool = False):
        """The walk of a batch of one packet through the kind's traversal, recorded node by node
        into ``record`` (``engine.packet.record``) by the traversal's own kernel, for ``packetrt
        show``: (Hits of the packet's rays -- the first hit found when ``any_hit`` -- and the
        Frusta it was culled with). A traversal that cannot record (no ``walk_recorded``:
        ``single``, Embree, the ray-space hierarchy) is a ValueError. ``from_end``: walked far
        child first, as ``trace`` walks a shadow batch from the light."""
        traversal = self.traversal[kind]
        if not hasattr(traversal, "walk_recorded"):
            raise ValueError(f"traversal {getattr(traversal, 'name', traversal)!r} cannot record a packet walk")
        frusta = self.frusta_for(kind, rays, packets)
        answers = empty_hits(rays.org.shape[0])
        if from_end and self.orders_any_hit(kind):
            traversal.walk_recorded(self.bvh, self.tris, rays, packets, frusta, any_hit, answers, record, from_end=True)
        else:
            traversal.walk_recorded(self.bvh, self.tris, rays, packets, frusta, any_hit, answers, record)
        return answers, frusta

    def with_traversal(self, traversal: dict, frustum: dict | None = None) -> "Tracer":
        """The same BVH and triangles traced with other plugins."""
        return Tracer(self.bvh, self.tris, self.bounds, traversal, frustum or self.frustum)
