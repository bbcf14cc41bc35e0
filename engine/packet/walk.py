"""The packet walk: the one skeleton behind every packet traversal (Overbeck, Ramamoorthi and
Mark 2008, Section 3), and its kernels (``walk_packets``).

Each strategy's kernel deals the packets to the threads in interleaved decks; for each packet
it loads the rays into packet-local rows (``engine.packet.kernels.load_packet``) and its
frustum, walks the BVH depth first and stores the best hits. The walk pops a node, counts it,
lets the strategy visit it (``engine.packet.steps.node_step``: getFirstHit, partRays, the
frustum test) and, when the visit ENTERED, either intersects the leaf's frustum-surviving
triangles with the SIMD rays and lanes the strategy lists (``leaf_rays`` / ``leaf_ray``), or
pushes the children far first, so that the near one -- from the packet's direction signs -- is
popped first. SIMD walks each SIMD ray of a packet alone (``walkers``). A walk ends when its
stack is empty or every lane is dead (an occlusion query kills a lane at its first hit).

``walk_packets`` walks a batch by one strategy through that strategy's compiled, disk-cached
kernel (``walk_masked``, ``walk_ranged``, ``walk_partition``, ``walk_simd``; numba compiles two
of each: the plain walk, and the instrumented one with both counters and a record, see
``instrumented``). Each inlines ``walk_packet_range`` with its strategy a constant, so numba
prunes the other strategies' steps from it: with the strategy a run-time number instead, the
branches cost up to 5% on primary and shadow rays; and a config compiles only the strategies it
uses. AUTO (``walk_packets_auto``) chooses first (``choose_batch``: one strategy for the whole
batch from a sample of its packets, each asked ``engine.packet.choose.choose_packet``; or, in a
batch whose sample is split, the rule for every packet), then runs the kernel of each strategy
chosen, walking only its packets.

The packet body unpacks its grouped arguments once per range of packets, not once per packet:
the 2x2 SIMD baseline has 262,144 packets in a 1024^2 batch, and unpacking per packet made its
primary trace 25% slower (erw6, one thread: 148 against 118 ms before ``walk_packet_range``
existed; now 123-134 ms, the rest not found). The kernels also hand the parallel body single
arrays, not tuples of them.
"""
from __future__ import annotations

import numpy as np
import numba
from numba import get_thread_id, njit, prange

from engine.core.types import COUNTER_NODES, COUNTER_RAY_AABB, COUNTER_RAY_TRI, MAX_BVH_DEPTH
from engine.packet.frustum_cull import load_frustum
from engine.packet.kernels import (STACK_SIZE, intersect_lanes, intersect_lanes_x2, largest_leaf, leaf_triangles,
                                   load_packet, longest_packet, node_box, packet_scratch, store_hits)
from engine.packet.record import new_record, record_visit
from engine.packet.steps import leaf_ray, leaf_rays, node_step, visit_record, walk_start, walkers
from engine.packet.auto_trial import apply_verdicts, tried_walk, walk_by_strategy
from engine.packet.choose import batch_choice, choose_packet, scene_scales
from engine.packet.strategies import ENTERED, MASKED, N_STRATEGIES, PARTITION, RANGED, SIMD


def walk_packets(strategy, bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax,
                 offsets, planes, valid, order, n_chunks, any_hit, out_t, out_prim, out_u, out_v,
                 counters, record, chosen=None, visits=None):
    """Closest (any_hit False) or first (any_hit True) hits of every ray, walked by ``strategy``
    (``engine.packet.strategies``, not AUTO: see ``walk_packets_auto``) through its kernel in
    ``STRATEGY_KERNELS``.

    BVH bmin, bmax f32[N,3], first, count i32[N], prim i32[P]; triangle corners v0, v1, v2
    f32[T,3]; rays org, inv, dirs f32[R,3], tmin, tmax f32[R] in packets offsets i32[K+1] (whole
    2x2 SIMD rays); frusta planes f32[K,4,4], valid bool[K]; order i8[N] the child-order keys
    (``engine.packet.kernels.child_order_keys``); n_chunks the packet decks; answers out_t,
    out_prim, out_u, out_v f32/i32[R]. counters: i64[threads,3,D] (nodes, ray-box and
    ray-triangle tests per depth, added to) or None. record: an ``engine.packet.record``
    PacketRecord for a batch of one packet, or None. chosen: None (every packet), or i8[K] and
    only the packets k with chosen[k] == strategy are walked. visits: i64[threads] that each
    worker adds its node visits to (every walk counts them: one addition a node, nothing
    measurable), or None.
    """
    counters, record = instrumented(counters, record)
    if visits is None:
        visits = np.zeros(numba.config.NUMBA_NUM_THREADS, np.int64)
    STRATEGY_KERNELS[strategy]((bmin, bmax, first, count, prim, v0, v1, v2, order),
                               (org, inv, dirs, tmin, tmax, offsets, planes, valid, n_chunks, any_hit),
                               (out_t, out_prim, out_u, out_v, visits), counters, record,
                               EVERY_PACKET if chosen is None else chosen)


def instrumented(counters, record):
    """(counters, record) as a walk takes them: both None (the plain walk) or both given, a
    missing one replaced by a throwaway (zeroed counters, or a record without room, which keeps
    nothing). So numba compiles each strategy's kernel twice, plain and instrumented, rather
    than once per combination (four): about 12 s each on a cold cache."""
    if counters is None and record is None:
        return None, None
    if counters is None:
        counters = np.zeros((numba.config.NUMBA_NUM_THREADS, 3, MAX_BVH_DEPTH), np.int64)
    if record is None:
        record = new_record(0)
    return counters, record


# One kernel per strategy, each the skeleton with its strategy a constant, so that numba prunes
# the other strategies' steps from it and a config compiles only the strategies it uses. The
# four bodies are the same lines on purpose: the parallel loop is written in the kernel itself,
# not in an inlined helper, because every level of inlining copies the whole walk's IR once more
# (numba's inliner deep-copies it): a strategy's kernel compiled in 15 s through a helper and
# in 11.7 s without (one signature, the default scene, cold cache). The groups are unpacked and
# made again inside the loop, so that the parallel body receives single arrays, not tuples.
# scene (bmin, bmax, first, count, prim, v0, v1, v2, order), batch (org, inv, dirs, tmin, tmax,
# offsets, planes, valid, n_chunks, any_hit), answers (out_t, out_prim, out_u, out_v, visits): the
# arguments of ``walk_packets``; counters and record stay arguments of their own, so numba drops
# their code where they are None; chosen: i8[K], or empty for every packet. No kernel holds an
# AUTO branch: each would then compile AUTO's three copies (a cold default render compiled for
# 245 s with it, 68 s without).
@njit(cache=True, parallel=True)
def walk_masked(scene, batch, answers, counters, record, chosen):
    bmin, bmax, first, count, prim, v0, v1, v2, order = scene
    org, inv, dirs, tmin, tmax, offsets, planes, valid, n_chunks, any_hit = batch
    out_t, out_prim, out_u, out_v, visits = answers
    max_rays = longest_packet(offsets)
    max_leaf = largest_leaf(count)
    for chunk in prange(n_chunks):
        walk_packet_range(MASKED, (bmin, bmax, first, count, prim, v0, v1, v2, order),
                          (org, inv, dirs, tmin, tmax, offsets, planes, valid, n_chunks, any_hit),
                          worker_scratch(max_rays, max_leaf), chunk, offsets.shape[0] - 1, n_chunks,
                          (out_t, out_prim, out_u, out_v, visits), counters, record, chosen)


@njit(cache=True, parallel=True)
def walk_ranged(scene, batch, answers, counters, record, chosen):
    bmin, bmax, first, count, prim, v0, v1, v2, order = scene
    org, inv, dirs, tmin, tmax, offsets, planes, valid, n_chunks, any_hit = batch
    out_t, out_prim, out_u, out_v, visits = answers
    max_rays = longest_packet(offsets)
    max_leaf = largest_leaf(count)
    for chunk in prange(n_chunks):
        walk_packet_range(RANGED, (bmin, bmax, first, count, prim, v0, v1, v2, order),
                          (org, inv, dirs, tmin, tmax, offsets, planes, valid, n_chunks, any_hit),
                          worker_scratch(max_rays, max_leaf), chunk, offsets.shape[0] - 1, n_chunks,
                          (out_t, out_prim, out_u, out_v, visits), counters, record, chosen)


@njit(cache=True, parallel=True)
def walk_partition(scene, batch, answers, counters, record, chosen):
    bmin, bmax, first, count, prim, v0, v1, v2, order = scene
    org, inv, dirs, tmin, tmax, offsets, planes, valid, n_chunks, any_hit = batch
    out_t, out_prim, out_u, out_v, visits = answers
    max_rays = longest_packet(offsets)
    max_leaf = largest_leaf(count)
    for chunk in prange(n_chunks):
        walk_packet_range(PARTITION, (bmin, bmax, first, count, prim, v0, v1, v2, order),
                          (org, inv, dirs, tmin, tmax, offsets, planes, valid, n_chunks, any_hit),
                          worker_scratch(max_rays, max_leaf), chunk, offsets.shape[0] - 1, n_chunks,
                          (out_t, out_prim, out_u, out_v, visits), counters, record, chosen)


@njit(cache=True, parallel=True)
def walk_simd(scene, batch, answers, counters, record, chosen):
    bmin, bmax, first, count, prim, v0, v1, v2, order = scene
    org, inv, dirs, tmin, tmax, offsets, planes, valid, n_chunks, any_hit = batch
    out_t, out_prim, out_u, out_v, visits = answers
    max_rays = longest_packet(offsets)
    max_leaf = largest_leaf(count)
    for chunk in prange(n_chunks):
        walk_packet_range(SIMD, (bmin, bmax, first, count, prim, v0, v1, v2, order),
                          (org, inv, dirs, tmin, tmax, offsets, planes, valid, n_chunks, any_hit),
                          worker_scratch(max_rays, max_leaf), chunk, offsets.shape[0] - 1, n_chunks,
                          (out_t, out_prim, out_u, out_v, visits), counters, record, chosen)


STRATEGY_KERNELS = {MASKED: walk_masked, RANGED: walk_ranged, PARTITION: walk_partition, SIMD: walk_simd}
#: ``chosen`` for a walk of every packet: empty, so that plain walks and AUTO's passes share one
#: compiled kernel per strategy.
EVERY_PACKET = np.empty(0, np.int8)


def walk_packets_auto(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax,
                      offsets, planes, valid, order, n_chunks, any_hit, out_t, out_prim, out_u, out_v,
                      counters, limits, choices, record, visits=None, only=None, per_packet=False, book=None,
                      signature=None, min_share=0.0):
    """``walk_packets`` by AUTO: each packet walked by the strategy ``choose_batch`` gives it
    under limits f64[N_LIMITS] (packet by packet when the sample is split and ``per_packet``, unless
    the smaller strategies' packets hold under ``min_share`` of the batch);
    choices i8[K] receives each packet's strategy. only: None (every packet), or i8[K] and only
    packets k with only[k] >= 0 are walked (their choices; the others' choices are -1).

    The batch is chosen first (``choose_batch``); then the kernel of each strategy some packet
    got walks the packets given to it, so AUTO compiles no walk of its own. A batch given whole
    to one strategy is walked by its kernel without the per-packet filter. Choosing and walking
    packet by packet unpacked the walk's arguments once per packet (see the module doc).

    book: an ``engine.packet.auto_trial.TrialBook`` (with the batch's ``signature``), or None. A
    batch chosen packet by packet then has its groups tried, timed, or walked by the verdicts the
    book holds for its signature (``engine.packet.auto_trial.tried_walk``); a counting or
    recording walk only applies verdicts already held."""
    _, whole = choose_batch(bmin, bmax, org, dirs, tmin, tmax, offsets, valid, limits, choices, only,
                            per_packet, min_share)
    if whole >= 0 and only is None:
        walk_packets(whole, bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax, offsets,
                     planes, valid, order, n_chunks, any_hit, out_t, out_prim, out_u, out_v, counters, record,
                     None, visits)
        return

    def walk(strategy, chosen):
        walk_packets(strategy, bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax, offsets,
                     planes, valid, order, n_chunks, any_hit, out_t, out_prim, out_u, out_v, counters, record, chosen,
                     visits)

    if book is not None and only is None and whole < 0:
        if counters is None and record is None:
            tried_walk(walk, choices, book, signature)
            return
        apply_verdicts(choices, book.verdicts(signature) or {})
    walk_by_strategy(walk, choices)


def choose_batch(bmin, bmax, org, dirs, tmin, tmax, offsets, valid, limits, choices, only=None, per_packet=False,
                 min_share=0.0):
    """Fill choices i8[K] with the strategy AUTO walks each packet of a batch with (rays org,
    dirs f32[R,3], tmin, tmax f32[R] in packets offsets i32[K+1], frusta valid bool[K]) under
    limits f64[N_LIMITS], in a scene of BVH boxes bmin, bmax f32[N,3]; only: None, or i8[K] and
    packets k with only[k] < 0 get -1. Returns (i64[N_STRATEGIES] packets per strategy, the
    strategy the whole batch was given, or -1 when it was chosen packet by packet).

    ``engine.packet.choose.batch_choice`` asks the rule for a sample of the packets; a sample
    that agrees gives the whole batch its strategy. A split one gives the whole batch the
    strategy most sampled packets got (a tie to the lower strategy number), or, when
    ``per_packet``, has every packet chosen by the rule (``choose_packets``, in parallel). A split
    whose smaller strategies hold under ``min_share`` -- of the sample (then no per-packet pass
    is made), or of the packets -- gives the whole batch the strategy most got (splitting has a
    cost of its own: see the ``auto`` plugin's ``split_min_share``). See ``engine.packet.choose``."""
    whole, given = batch_choice(bmin, bmax, org, dirs, tmin, tmax, offsets, valid, limits,
                                EVERY_PACKET if only is None else only, per_packet, choices, min_share)
    if whole >= 0:
        counts = np.zeros(N_STRATEGIES, np.int64)
        counts[whole] = given
        return counts, whole
    counts = choose_packets(bmin, bmax, org, dirs, tmin, tmax, offsets, valid, limits, choices)
    if only is not None:  # the packets left out are not walked: count the others only
        choices[only < 0] = -1
        counts = np.bincount(choices[choices >= 0], minlength=N_STRATEGIES).astype(np.int64)
    total = int(counts.sum())
    top = int(np.argmax(counts))  # the first of equals: the lower strategy number, as batch_choice's ties
    if total and total - counts[top] < min_share * total:
        choices[choices >= 0] = top
        counts = np.zeros(N_STRATEGIES, np.int64)
        counts[top] = total
        return counts, top
    return counts, whole


@njit(cache=True, parallel=True)
def choose_packets(bmin, bmax, org, dirs, tmin, tmax, offsets, valid, limits, choices):
    """choices[k] = the strategy ``engine.packet.choose.choose_packet`` picks for packet k;
    returns how many packets chose each strategy (i64[N_STRATEGIES], indexed by strategy)."""
    n_packets = offsets.shape[0] - 1
    scales = scene_scales(bmin, bmax)
    n_ranged = 0
    n_partition = 0
    n_masked = 0
    for k in prange(n_packets):
        start = offsets[k]
        choice = choose_packet(org, dirs, tmin, tmax, start, offsets[k + 1] - start, valid[k], scales, limits)
        choices[k] = choice
        n_ranged += choice == RANGED
        n_partition += choice == PARTITION
        n_masked += choice == MASKED
    counts = np.zeros(N_STRATEGIES, np.int64)
    counts[RANGED], counts[PARTITION], counts[MASKED] = n_ranged, n_partition, n_masked
    return counts


@njit(cache=True, inline="always")
def worker_scratch(max_rays, max_leaf):
    """One worker's scratch for ``walk_packet_range``: (rf, ri, near, fr, leaf_tris, ids, masks,
    stack_node, stack_carry, stack_depth, thread)."""
    rf, ri, near, fr, leaf_tris = packet_scratch(max_rays, max_leaf)
    ids = np.empty(max_rays // 4 + 1, np.int32)
    masks = np.empty(max_rays // 4 + 1, np.int32)
    stack_node = np.empty(STACK_SIZE, np.int32)
    stack_carry = np.empty(STACK_SIZE, np.int32)
    stack_depth = np.empty(STACK_SIZE, np.int32)
    return rf, ri, near, fr, leaf_tris, ids, masks, stack_node, stack_carry, stack_depth, get_thread_id()


@njit(cache=True, inline="always")
def walk_packet_range(strategy, scene, batch, work, begin, end, step, answers, counters, record, chosen):
    """Packets range(begin, end, step) (those with chosen[k] == strategy when chosen is not
    empty), each loaded, walked by ``strategy`` (a constant: not AUTO) and its hits stored
    into answers (out_t, out_prim, out_u, out_v, visits: the nodes visited are added to
    visits[thread]); ``work`` is the worker's scratch (rf, ri, near, fr, leaf_tris, ids, masks,
    stack_node, stack_carry, stack_depth, thread)."""
    bmin, bmax, first, count, prim, v0, v1, v2, order = scene
    org, inv, dirs, tmin, tmax, offsets, planes, valid, n_chunks, any_hit = batch
    out_t, out_prim, out_u, out_v, visits = answers
    rf, ri, near, fr, leaf_tris, ids, masks, stack_node, stack_carry, stack_depth, thread = work
    for k in range(begin, end, step):
        if chosen.shape[0] > 0 and chosen[k] != strategy:
            continue
        nodes = 0
        start = offsets[k]
        n = offsets[k + 1] - start
        n_simd = n // 4
        live = load_packet(org, inv, dirs, tmin, tmax, start, n, rf, ri, near)
        cull = load_frustum(planes, valid, k, fr)
        for walker in range(walkers(strategy, n_simd)):
            lanes, carry = walk_start(strategy, rf, ids, walker, n_simd, live)
            top = 0
            if lanes > 0:
                stack_node[0], stack_carry[0], stack_depth[0] = 0, carry, 0
                top = 1
            while top > 0 and lanes > 0:
                top -= 1
                node = stack_node[top]
                depth = stack_depth[top]
                carry_in = stack_carry[top]
                nodes += 1
                if counters is not None:
                    counters[thread, COUNTER_NODES, depth] += 1
                box = node_box(bmin, bmax, node)
                leaf = count[node] > 0
                outcome, carry, tests, hit_lanes = node_step(strategy, rf, ids, masks, carry_in, n_simd, box,
                                                             fr, cull, leaf)
                if counters is not None:
                    counters[thread, COUNTER_RAY_AABB, depth] += tests
                if record is not None and record[0].shape[0] > 0:  # a record without room: counting only
                    seen, seen_lanes = visit_record(strategy, rf, masks, carry_in, carry, hit_lanes, n_simd, box,
                                                    outcome)
                    record_visit(record, node, depth, seen, seen_lanes)
                if outcome != ENTERED:
                    continue
                if leaf:
                    n_tris = leaf_triangles(first, count, prim, node, v0, v1, v2, fr, cull, leaf_tris)
                    n_rays, tests = leaf_rays(strategy, rf, carry, n_simd, box)
                    tri_tests = 0
                    # SIMD rays with lanes to test go two at a time (8 lanes, AVX2's width).
                    waiting, waiting_mask = -1, 0
                    for j in range(n_rays):
                        i, mask = leaf_ray(strategy, rf, ids, masks, carry, hit_lanes, j, box)
                        if mask == 0:
                            continue
                        if waiting < 0:
                            waiting, waiting_mask = i, mask
                            continue
                        done, died = intersect_lanes_x2(rf, ri, 4 * waiting, 4 * i, waiting_mask | (mask << 4),
                                                        leaf_tris, n_tris, v0, v1, v2, any_hit)
                        tri_tests += done
                        lanes -= died
                        waiting = -1
                    if waiting >= 0:
                        done, died = intersect_lanes(rf, ri, 4 * waiting, waiting_mask, leaf_tris, n_tris,
                                                     v0, v1, v2, any_hit)
                        tri_tests += done
                        lanes -= died
                    if counters is not None:
                        counters[thread, COUNTER_RAY_AABB, depth] += tests
                        counters[thread, COUNTER_RAY_TRI, depth] += tri_tests
                    continue
                near_child = first[node] + near[order[node]]
                far_child = 2 * first[node] + 1 - near_child
                stack_node[top], stack_carry[top], stack_depth[top] = far_child, carry, depth + 1
                stack_node[top + 1], stack_carry[top + 1], stack_depth[top + 1] = near_child, carry, depth + 1
                top += 2
        store_hits(rf, ri, start, n, out_t, out_prim, out_u, out_v)
        # Added per packet: a sum carried across the packets and added after the loop was lost
        # (numba 0.68's parfor lowering wrote nothing), and per node the two threads' adjacent
        # slots would share a cache line at every visit.
        visits[thread] += nodes
