"""The plugin side shared by the packet traversals and frustum builders: contracts in, kernel
call, answers out.

Each packet traversal (``traversals/simd.py`` and friends) is a subclass naming its strategy
(``engine.packet.strategies``); ``walk_batch`` checks the batch and calls the one packet walk
``engine.packet.walk.walk_packets`` (``walk_packets_auto`` for AUTO) with it, optionally
counting (``Stats``) or recording the walk of a one-packet batch (``engine.packet.record``, for ``packetrt show``).

Each frustum builder (``frusta/pinhole.py`` and friends) is a subclass naming its builder
(``engine.packet.frustum_builders``), whose one kernel fills ``planes`` f32[K,4,4] and
``valid`` bool[K] for the packets, given the scene box f32[2,3].
"""
from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from engine.core.types import Frusta, Hits, check_answer_arrays, thread_counters
from engine.packet.auto_limits import fitted_limits, limits_array
from engine.packet.choose import N_LIMITS
from engine.packet.frustum_builders import build_frusta
from engine.packet.kernels import child_order_keys
from engine.packet.strategies import AUTO
from engine.packet.walk import walk_packets, walk_packets_auto

#: A shadow-order trial (``PacketTraversal._trial``, ``engine.render.shadow_order``) walks its
#: packets in this many interleaved groups, and needs at least TRIAL_PACKETS of them.
TRIAL_GROUPS = 4
TRIAL_PACKETS = 16


@njit(cache=True, parallel=True)
def live_rays_of(tmin, tmax, offsets, chosen):
    """How many rays with tmin <= tmax (f32[R]) lie in the packets k (offsets i32[K+1]) with
    chosen[k] >= 0 (i8[K])."""
    n = 0
    for k in prange(offsets.shape[0] - 1):
        live = 0  # counted apart: numba drops a reduction updated inside the inner loop
        if chosen[k] >= 0:
            for i in range(offsets[k], offsets[k + 1]):
                live += tmin[i] <= tmax[i]
        n += live
    return n


#: Packet decks per thread: packet k goes to deck k % n_chunks, so neighbouring (similarly
#: expensive) tiles land on different threads and the threads finish together.
DECKS_PER_THREAD = 4


#: The last few BVHs' child-order keys, as (bmin, first, keys, flipped keys): computing them walks every node
#: (0.6 ms on the 110k-triangle kitchen), which the kitchen's 54 shadow batches a frame would
#: otherwise pay each time. Identity of the arrays is the key: a refit makes new arrays.
_ORDER_CACHE: list = []
_ORDER_CACHE_SIZE = 4


def cached_child_order(bvh, from_end: bool = False) -> np.ndarray:
    """``child_order_keys`` of ``bvh`` (i8[N]), computed once per BVH. ``from_end``: the keys
    with the upper/lower bit flipped (``key ^ 1``), which makes the walk take the far child
    first, so that a packet meets the ends of its segments first (see ``walk_batch``)."""
    for bmin, first, keys, flipped in _ORDER_CACHE:
        if bmin is bvh.bmin and first is bvh.first:
            return flipped if from_end else keys
    keys = child_order_keys(bvh.bmin, bvh.bmax, bvh.first, bvh.count)
    flipped = keys ^ np.int8(1)
    _ORDER_CACHE.insert(0, (bvh.bmin, bvh.first, keys, flipped))
    del _ORDER_CACHE[_ORDER_CACHE_SIZE:]
    return flipped if from_end else keys


def deck_count(n_packets: int) -> int:
    """How many interleaved decks of packets to deal to the threads."""
    return min(n_packets, DECKS_PER_THREAD * numba.get_num_threads())


def walk_batch(strategy, bvh, tris, rays, packets, frusta, any_hit, out_t, out_prim, out_u, out_v,
               counters=None, record=None, kernel=None, limits=None, choices=None, from_end=False, chosen=None,
               visits=None, per_packet=False, book=None, min_share=0.0):
    """Walk every packet of ``rays`` (in ``packets``) through ``bvh`` by ``strategy``, with its
    frustum from ``frusta`` (None: no culling), writing the best (any_hit: first) hits into
    out_t, out_prim, out_u, out_v (f32/i32[R]). counters: i64[threads,3,D] or None; record: a
    PacketRecord for a batch of one packet, or None. ``kernel``: instead of the walk, a kernel
    of the walk's arguments without strategy, AUTO's arrays and record (``engine.bench.floor``).
    AUTO only: limits f64[N_LIMITS] the chooser's thresholds (None: the fitted ones,
    ``engine.packet.auto_limits``); choices i8[K] receives each packet's strategy (None: not kept);
    per_packet: choose each packet of a batch whose sample is split, instead of giving the whole
    batch the sample's majority (``engine.packet.walk.choose_batch``).
    from_end: take the far child first at every node (the packet's rays met from their ends
    first). Closest hits do not depend on the order; an any-hit walk may stop at another of a
    ray's blockers, and sooner or later than in the usual order (``engine.render.shadow_order``).
    chosen: None (every packet), or i8[K] and only packets k with chosen[k] == strategy are
    walked (with AUTO: packets k with chosen[k] >= 0, each by the strategy it chooses).
    visits: i64[threads] that receives the nodes visited (added to), or None.
    min_share: AUTO only, a batch chosen packet by packet whose smaller strategies' packets hold
    under this share of it is walked whole by the strategy most got (``choose_batch``).
    book: AUTO only, an ``engine.packet.auto_trial.TrialBook`` whose verdicts (and, when none is
    held for this batch, timed trials) correct the per-packet choice, or None."""
    check_answer_arrays(rays.org.shape[0], out_t, out_prim, out_u, out_v)
    offsets = np.ascontiguousarray(packets.offsets, np.int32)
    n_packets = offsets.shape[0] - 1
    if offsets[-1] != rays.org.shape[0] or np.any(np.diff(offsets) % 4):
        raise ValueError("packets must cover the batch in whole 2x2 SIMD rays "
                         f"(offsets end at {int(offsets[-1])}, batch has {rays.org.shape[0]} rays)")
    if record is not None and n_packets != 1:
        raise ValueError(f"a walk is recorded one packet at a time, not {n_packets}")
    if frusta is None:
        planes = np.zeros((n_packets, 4, 4), np.float32)
        valid = np.zeros(n_packets, np.bool_)
    else:
        planes = np.ascontiguousarray(frusta.planes, np.float32)
        valid = np.ascontiguousarray(frusta.valid, np.bool_)
        if planes.shape != (n_packets, 4, 4) or valid.shape != (n_packets,):
            raise ValueError(f"frusta for {planes.shape[0]} packets given to a batch of {n_packets}")
    args = (bvh.bmin, bvh.bmax, bvh.first, bvh.count, bvh.prim, tris.v0, tris.v1, tris.v2,
            rays.org, rays.inv_dir, rays.dir, rays.tmin, rays.tmax, offsets, planes, valid,
            cached_child_order(bvh, from_end), deck_count(n_packets), any_hit, out_t, out_prim, out_u, out_v,
            counters)
    if kernel is not None:
        kernel(*args)
        return
    if strategy != AUTO:
        walk_packets(strategy, *args, record, chosen, visits)
        return
    limits = limits_array(fitted_limits()) if limits is None else np.ascontiguousarray(limits, np.float64)
    if limits.shape != (N_LIMITS,):
        raise ValueError(f"auto limits must be f64[{N_LIMITS}], got shape {limits.shape}")
    if choices is None:
        choices = np.empty(n_packets, np.int8)
    elif choices.shape != (n_packets,) or choices.dtype != np.int8:
        raise ValueError(f"auto choices must be i8[{n_packets}], got {choices.dtype}{list(choices.shape)}")
    signature = None if book is None else book.signature_of(rays, packets)
    walk_packets_auto(*args, limits, choices, record, visits, chosen, per_packet, book, signature, min_share)


class PacketTraversal:
    """Adapter from the traversal plugin interface to the packet walk (set ``strategy``; the
    benchmark's walk-less floor sets ``kernel`` instead, see ``walk_batch``)."""

    strategy = None
    kernel = None
    #: The walk (and the floor kernel) stores every ray's answer, misses included, so the Tracer
    #: need not reset reused answer arrays first.
    writes_every_answer = True
    #: The occlusion query's scratch answers (see ``_any_hit_scratch``), per instance.
    _scratch = None

    def intersect(self, bvh, tris, rays, packets, frusta, hits, stats):
        """Closest hit of every ray into ``hits`` (arrays of length R)."""
        self._run(bvh, tris, rays, packets, frusta, False, hits.t, hits.prim, hits.u, hits.v, stats)

    #: ``occluded`` takes ``from_end`` and ``trial`` (``engine.render.tracer.Tracer.trace``).
    orders_any_hit = True

    def occluded(self, bvh, tris, rays, packets, frusta, occluded, stats, from_end=False, trial=None):
        """occluded[r] = True when ray r hits anything in [tmin, tmax]. from_end: walk the far
        child first (see ``walk_batch``). trial: None, or a dict that receives {"surface":
        (nodes visited, live rays), "light": (nodes visited, live rays)} from a walk of the
        packets in four interleaved groups from alternate ends (``engine.render.shadow_order``;
        left empty when the batch has fewer than TRIAL_PACKETS packets: then from_end decides)."""
        any_hit = self._any_hit_scratch(rays.org.shape[0])  # which triangle stopped each ray
        n_packets = len(packets.offsets) - 1
        if trial is None or self.kernel is not None or n_packets < TRIAL_PACKETS:
            self._run(bvh, tris, rays, packets, frusta, True, any_hit.t, any_hit.prim, any_hit.u, any_hit.v, stats,
                      from_end)
        else:
            trial.update(self._trial(bvh, tris, rays, packets, frusta, any_hit, stats))
        np.greater_equal(any_hit.prim, 0, out=occluded)

    def _trial(self, bvh, tris, rays, packets, frusta, any_hit, stats) -> dict:
        """The any-hit walk of every packet, group g = k % 4 of packets k from the light end for
        g = 1, 2 and from the surface for g = 0, 3; nodes visited and live rays per end."""
        group = np.arange(len(packets.offsets) - 1) % TRIAL_GROUPS
        offsets = np.ascontiguousarray(packets.offsets, np.int32)
        nodes = {False: 0, True: 0}
        live = {False: 0, True: 0}
        for g, from_end in enumerate((False, True, True, False)):
            chosen = np.where(group == g, self.strategy, -1).astype(np.int8)
            visits = np.zeros(numba.config.NUMBA_NUM_THREADS, np.int64)
            self._walk_group(bvh, tris, rays, packets, frusta, any_hit, stats, from_end, chosen, visits)
            nodes[from_end] += int(visits.sum())
            live[from_end] += live_rays_of(rays.tmin, rays.tmax, offsets, chosen)
        return {"surface": (nodes[False], live[False]), "light": (nodes[True], live[True])}

    def _walk_group(self, bvh, tris, rays, packets, frusta, any_hit, stats, from_end, chosen, visits):
        """One trial group's any-hit walk: the packets k with chosen[k] >= 0."""
        walk_batch(self.strategy, bvh, tris, rays, packets, frusta, True, any_hit.t, any_hit.prim, any_hit.u,
                   any_hit.v, thread_counters(stats), from_end=from_end, chosen=chosen,
                   visits=visits)

    def _any_hit_scratch(self, n):
        """Hits arrays for n rays, kept by this instance from query to query: the walk writes
        every ray's answer, and fresh arrays of a frame's shadow rays (21 MB on the kitchen)
        cost a serial fill and a page fault per 4 KiB each time."""
        if self._scratch is None or self._scratch.t.shape[0] < n:
            self._scratch = Hits(np.empty(n, np.float32), np.empty(n, np.int32), np.empty(n, np.float32),
                                 np.empty(n, np.float32))
        return Hits(*(a[:n] for a in self._scratch))

    def walk_recorded(self, bvh, tris, rays, packets, frusta, any_hit, hits, record, from_end=False):
        """The walk of a batch of one packet, recorded into ``record`` (a PacketRecord) by the
        same kernel: answers (closest, or first when ``any_hit``) into ``hits``; ``from_end`` as
        in ``walk_batch`` (a shadow batch the render walked from the light)."""
        walk_batch(self.strategy, bvh, tris, rays, packets, frusta, any_hit, hits.t, hits.prim, hits.u, hits.v,
                   record=record, from_end=from_end)

    def _run(self, bvh, tris, rays, packets, frusta, any_hit, out_t, out_prim, out_u, out_v, stats,
             from_end=False):
        walk_batch(self.strategy, bvh, tris, rays, packets, frusta, any_hit, out_t, out_prim, out_u, out_v,
                   thread_counters(stats), kernel=type(self).kernel, from_end=from_end)


class PacketFrustum:
    """Adapter from the frustum plugin interface to the frustum kernel (set ``builder``)."""

    builder = None

    def build(self, rays, packets, scene_bounds):
        """One frustum per packet: Frusta(planes f32[K,4,4], valid bool[K])."""
        n_packets = len(packets.offsets) - 1
        planes = np.zeros((n_packets, 4, 4), np.float32)
        valid = np.zeros(n_packets, np.bool_)
        if n_packets:
            build_frusta(self.builder, rays.org, rays.dir, rays.tmin, rays.tmax,
                         np.ascontiguousarray(packets.offsets, np.int32),
                         np.ascontiguousarray(scene_bounds, np.float32), deck_count(n_packets), planes, valid)
        return Frusta(planes, valid)
