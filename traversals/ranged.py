"""``ranged``: the packet walks the BVH with the index range of its active SIMD rays.

Overbeck, Ramamoorthi, Mark 2008, Section 3 (after Wald et al.'s large-packet BVH traversal).
Each stack entry holds a node and ``ia``, the first SIMD ray that may still hit it. On a pop,
getFirstHit advances ``ia`` to the first SIMD ray that hits the node's box (trying ``ia``
itself first, then the packet frustum as early reject); no hit ends the subtree. At a leaf,
getLastHit scans back from the end for the last SIMD ray ``ie - 1`` that hits, and every ray in
[ia, ie) tests the leaf's triangles (those the frustum does not cull). Children are pushed far
first so the near one, chosen from the packet's direction signs, is popped first.

Cheap per node when rays are coherent (usually one box test decides); on incoherent rays the
range [ia, ie) fills with rays that miss the leaf, which ``partition`` avoids.
"""
from __future__ import annotations

import numpy as np
from numba import get_thread_id, njit, prange

from engine.packet.kernels import (ALL_LANES, STACK_SIZE, first_hit, intersect_lanes, largest_leaf,
                                   leaf_triangles, load_packet, longest_packet, node_box,
                                   packet_scratch, slab_mask4, store_hits)
from engine.packet.frustum_cull import load_frustum
from engine.packet.plugin import PacketTraversal
from engine.core.registry import register_traversal
from engine.core.types import COUNTER_NODES, COUNTER_RAY_AABB, COUNTER_RAY_TRI


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


@njit(cache=True, parallel=True)
def trace_ranged(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax,
                 offsets, planes, valid, order, n_chunks, any_hit, out_t, out_prim, out_u, out_v,
                 counters):
    """Closest (any_hit False) or first (any_hit True) hits of every packet; see the module doc
    and ``engine.packet.plugin`` for the arguments."""
    n_packets = offsets.shape[0] - 1
    max_rays = longest_packet(offsets)
    max_leaf = largest_leaf(count)
    for chunk in prange(n_chunks):
        rf, ri, near, fr, leaf_tris = packet_scratch(max_rays, max_leaf)
        stack_node = np.empty(STACK_SIZE, np.int32)
        stack_ia = np.empty(STACK_SIZE, np.int32)
        stack_depth = np.empty(STACK_SIZE, np.int32)
        thread = get_thread_id()
        for k in range(chunk, n_packets, n_chunks):
            start = offsets[k]
            n = offsets[k + 1] - start
            n_simd = n // 4
            live = load_packet(org, inv, dirs, tmin, tmax, start, n, rf, ri, near)
            cull = load_frustum(planes, valid, k, fr)
            top = 0
            if live > 0:
                stack_node[0], stack_ia[0], stack_depth[0] = 0, 0, 0
                top = 1
            while top > 0 and live > 0:
                top -= 1
                node = stack_node[top]
                depth = stack_depth[top]
                if counters is not None:
                    counters[thread, COUNTER_NODES, depth] += 1
                box = node_box(bmin, bmax, node)
                ia, tests = first_hit(rf, stack_ia[top], n_simd, box, fr, cull)
                if counters is not None:
                    counters[thread, COUNTER_RAY_AABB, depth] += tests
                if ia >= n_simd:
                    continue
                if count[node] > 0:
                    ie, tests = last_hit(rf, ia, n_simd, box)
                    n_tris = leaf_triangles(first, count, prim, node, v0, v1, v2, fr, cull, leaf_tris)
                    tri_tests = 0
                    for i in range(ia, ie):
                        done, died = intersect_lanes(rf, ri, 4 * i, ALL_LANES, leaf_tris, n_tris,
                                                     v0, v1, v2, any_hit)
                        tri_tests += done
                        live -= died
                    if counters is not None:
                        counters[thread, COUNTER_RAY_AABB, depth] += tests
                        counters[thread, COUNTER_RAY_TRI, depth] += tri_tests
                    continue
                near_child = first[node] + near[order[node]]
                far_child = 2 * first[node] + 1 - near_child
                stack_node[top], stack_ia[top], stack_depth[top] = far_child, ia, depth + 1
                stack_node[top + 1], stack_ia[top + 1], stack_depth[top + 1] = near_child, ia, depth + 1
                top += 2
            store_hits(rf, ri, start, n, out_t, out_prim, out_u, out_v)


@register_traversal("ranged")
class RangedTraversal(PacketTraversal):
    """Large packets with the active SIMD rays as an index range [ia, ie) (Overbeck et al. 2008)."""

    kernel = trace_ranged
