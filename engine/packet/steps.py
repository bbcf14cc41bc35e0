"""The steps in which the packet traversal strategies differ, for the one walk of
``engine.packet.walk``.

Each is an inlined numba function that takes the strategy number (``engine.packet.strategies``)
and branches on it; the walk inlines them with the strategy a constant, so each strategy's copy
of the walk keeps only its own steps (no function arguments, no closures: the kernel lands in
numba's disk cache). The walk keeps a depth-first stack of (node, carry, depth); ``carry`` is
what a strategy hands down to a node's children:

- MASKED: nothing (0): every SIMD ray of the packet is tried at every node.
- RANGED: ``ia``, the first SIMD ray that may still hit the node.
- PARTITION: ``m``, the number of SIMD rays listed first in ``ids`` that hit the parent (their
  lane masks in ``masks``).
- SIMD: the SIMD ray walking (each SIMD ray of a packet walks alone).

Shared arguments: rf f32[RF_ROWS, L] the packet-local rows (``engine.packet.kernels``); ids,
masks i32[>= n_simd] PARTITION's list of SIMD rays and their lane masks; n_simd the packet's
SIMD rays; box a ``node_box`` tuple; fr f32[16], cull the packet frustum
(``engine.packet.frustum_cull``).
"""
from __future__ import annotations

from numba import njit

from engine.packet.frustum_cull import frustum_misses_box
from engine.packet.kernels import ALL_LANES, lane_count, live_mask4, slab_mask4, slab_mask4x2
from engine.packet.strategies import CULLED, ENTERED, MASKED, MISSED, PARTITION, RANGED, SIMD


@njit(cache=True, inline="always")
def first_hit(rf, lo, hi, box, fr, cull):
    """Overbeck's getFirstHit over SIMD rays lo .. hi-1: (index of the first one that hits
    ``box`` or hi, ray-box tests done, outcome). SIMD ray ``lo`` is tried first (early accept);
    if it misses, a valid frustum that misses the box rejects the rest at once (CULLED)."""
    if lo >= hi:
        return hi, 0, MISSED
    if slab_mask4(rf, 4 * lo, box) != 0:
        return lo, 4, ENTERED
    if cull and frustum_misses_box(fr, box):
        return hi, 4, CULLED
    tests = 4
    for i in range(lo + 1, hi):
        tests += 4
        if slab_mask4(rf, 4 * i, box) != 0:
            return i, tests, ENTERED
    return hi, tests, MISSED


@njit(cache=True, inline="always")
def last_hit(rf, ia, hi, box):
    """Overbeck's getLastHit: (one past the last SIMD ray in (ia, hi) that hits ``box``, or
    ia + 1 when only ``ia`` does; ray-box tests done)."""
    tests = 0
    for i in range(hi - 1, ia, -1):
        tests += 4
        if slab_mask4(rf, 4 * i, box) != 0:
            return i + 1, tests
    return ia + 1, tests


@njit(cache=True, inline="always")
def keep_if_hit(ids, masks, j, i, mask, live):
    """partRays' step for the SIMD ray i = ids[j] with lane mask ``mask``: move it to the
    front when it hit; returns the new live count."""
    if mask != 0:
        ids[j] = ids[live]
        ids[live] = i
        masks[live] = mask
        live += 1
    return live


@njit(cache=True, inline="always")
def part_rays(rf, ids, masks, m, box):
    """Overbeck's partRays: move the SIMD rays among ids[:m] that hit ``box`` to the front,
    with their lane masks in masks[:live]; returns live. Two SIMD rays are tested at once
    (``slab_mask4x2``, 8 lanes); the moves then happen one ray after the other, in list order,
    so the partition is the one-at-a-time loop's. (A move only swaps ids[j] with an earlier
    entry, so ids[j + 1], read before the moves, is still in place for its own.)"""
    live = 0
    j = 0
    while j + 1 < m:
        i0, i1 = ids[j], ids[j + 1]
        both = slab_mask4x2(rf, 4 * i0, 4 * i1, box)
        live = keep_if_hit(ids, masks, j, i0, both & ALL_LANES, live)
        live = keep_if_hit(ids, masks, j + 1, i1, both >> 4, live)
        j += 2
    if j < m:
        live = keep_if_hit(ids, masks, j, ids[j], slab_mask4(rf, 4 * ids[j], box), live)
    return live


@njit(cache=True, inline="always")
def walkers(strategy, n_simd):
    """How many walks a packet makes: one per SIMD ray for SIMD, else one."""
    return n_simd if strategy == SIMD else 1


@njit(cache=True, inline="always")
def walk_start(strategy, rf, ids, walker, n_simd, live):
    """Set up walk ``walker`` of a packet with ``live`` live lanes: (live lanes of the walk,
    carry of the root)."""
    if strategy == SIMD:
        return lane_count(live_mask4(rf, 4 * walker)), walker
    if strategy == PARTITION:
        m = 0
        for i in range(n_simd):
            if live_mask4(rf, 4 * i) != 0:
                ids[m] = i
                m += 1
        return live, m
    return live, 0


@njit(cache=True, inline="always")
def node_step(strategy, rf, ids, masks, carry, n_simd, box, fr, cull, leaf):
    """Visit a node (``leaf``: it is one) with ``carry``: (outcome, carry for its children or
    leaf step, ray-box tests done, hit_lanes: for SIMD the mask of its lanes that hit the box).
    The walk goes on only when the outcome is ENTERED."""
    if strategy == MASKED:
        if leaf:  # the leaf step tries every SIMD ray; only the frustum can reject it first
            return (CULLED if cull and frustum_misses_box(fr, box) else ENTERED), 0, 0, 0
        _, tests, outcome = first_hit(rf, 0, n_simd, box, fr, cull)
        return outcome, 0, tests, 0
    if strategy == RANGED:
        ia, tests, outcome = first_hit(rf, carry, n_simd, box, fr, cull)
        return outcome, ia, tests, 0
    if cull and frustum_misses_box(fr, box):
        return CULLED, carry, 0, 0
    if strategy == SIMD:
        mask = slab_mask4(rf, 4 * carry, box)
        return (ENTERED if mask != 0 else MISSED), carry, 4, mask
    m = part_rays(rf, ids, masks, carry, box)
    return (ENTERED if m > 0 else MISSED), m, 4 * carry, 0


@njit(cache=True, inline="always")
def leaf_rays(strategy, rf, carry, n_simd, box):
    """At an entered leaf: (how many SIMD rays ``leaf_ray`` lists, ray-box tests done)."""
    if strategy == MASKED:
        return n_simd, 4 * n_simd
    if strategy == RANGED:
        ie, tests = last_hit(rf, carry, n_simd, box)
        return ie - carry, tests
    if strategy == SIMD:
        return 1, 0
    return carry, 0


@njit(cache=True, inline="always")
def leaf_ray(strategy, rf, ids, masks, carry, hit_lanes, j, box):
    """The j-th SIMD ray to test an entered leaf's triangles and its lanes that do (a mask, 0:
    none), given the visit's ``carry`` and, for SIMD, ``hit_lanes`` from ``node_step``."""
    if strategy == MASKED:
        return j, slab_mask4(rf, 4 * j, box)
    if strategy == RANGED:
        return carry + j, ALL_LANES
    if strategy == SIMD:
        return carry, hit_lanes
    return ids[j], masks[j]


@njit(cache=True, inline="always")
def visit_record(strategy, rf, masks, carry_in, carry_out, hit_lanes, n_simd, box, outcome):
    """What a packet trace records of a visit (for ``packetrt show``, not for the walk):
    (outcome, lanes), ``lanes`` being the live lanes among the SIMD rays the strategy tried at
    the node whose segments meet its box, counted before the leaf's triangles shorten them.
    MASKED and RANGED stop at the first SIMD ray that hits, so the rest are tested here. A visit
    that is not culled counts as ENTERED when some lane meets the box (a MASKED leaf that no lane
    meets is MISSED)."""
    if outcome == CULLED:
        return CULLED, 0
    count = 0
    if strategy == SIMD:
        count = lane_count(hit_lanes)
    elif strategy == PARTITION:
        for j in range(carry_out):
            count += lane_count(masks[j])
    else:
        for i in range(carry_in, n_simd):  # MASKED carries 0: all its SIMD rays
            count += lane_count(slab_mask4(rf, 4 * i, box))
    return (ENTERED if count > 0 else MISSED), count
