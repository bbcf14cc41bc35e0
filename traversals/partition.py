"""``partition``: the packet walks the BVH with an in-place partitioned list of its live SIMD rays.

Overbeck, Ramamoorthi, Mark 2008, Section 3 -- the paper's new traversal, robust to degrading
coherence. The packet keeps a list of its SIMD ray indices. At each node (unless the packet
frustum rejects the box outright) partRays tests the first ``m`` listed rays against the box
and swaps those that hit to the front; their count is what the children see, pushed on the stack
with them. Partitions below a node only permute a prefix of its own range, so when the stack
unwinds to a sibling its ``m`` rays are still the first ``m`` of the list. At a leaf only the
live rays -- and of those only the lanes that hit the leaf box -- test the triangles the
frustum does not cull. Near child first, from the packet's direction signs.

Every live ray is tested at every node it reaches, so coherent packets pay more box tests than
``ranged``; incoherent ones (reflections, refractions) save many triangle tests.
"""
from __future__ import annotations

import numpy as np
from numba import get_thread_id, njit, prange

from engine.packet.frustum_cull import frustum_misses_box, load_frustum
from engine.packet.kernels import (STACK_SIZE, intersect_lanes, largest_leaf, leaf_triangles,
                                   live_mask4, load_packet, longest_packet, node_box, packet_scratch,
                                   slab_mask4, store_hits)
from engine.packet.plugin import PacketTraversal
from engine.core.registry import register_traversal
from engine.core.types import COUNTER_NODES, COUNTER_RAY_AABB, COUNTER_RAY_TRI


@njit(cache=True, inline="always")
def part_rays(rf, ids, masks, m, box):
    """Overbeck's partRays: move the SIMD rays among ids[:m] that hit ``box`` to the front,
    with their lane masks in masks[:live]; returns live."""
    live = 0
    for j in range(m):
        i = ids[j]
        mask = slab_mask4(rf, 4 * i, box)
        if mask != 0:
            ids[j] = ids[live]
            ids[live] = i
            masks[live] = mask
            live += 1
    return live


@njit(cache=True, parallel=True)
def trace_partition(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax,
                    offsets, planes, valid, order, n_chunks, any_hit, out_t, out_prim, out_u, out_v,
                    counters):
    """Closest (any_hit False) or first (any_hit True) hits of every packet; see the module doc
    and ``engine.packet.plugin`` for the arguments."""
    n_packets = offsets.shape[0] - 1
    max_rays = longest_packet(offsets)
    max_leaf = largest_leaf(count)
    for chunk in prange(n_chunks):
        rf, ri, near, fr, leaf_tris = packet_scratch(max_rays, max_leaf)
        ids = np.empty(max_rays // 4 + 1, np.int32)
        masks = np.empty(max_rays // 4 + 1, np.int32)
        stack_node = np.empty(STACK_SIZE, np.int32)
        stack_m = np.empty(STACK_SIZE, np.int32)
        stack_depth = np.empty(STACK_SIZE, np.int32)
        thread = get_thread_id()
        for k in range(chunk, n_packets, n_chunks):
            start = offsets[k]
            n = offsets[k + 1] - start
            live = load_packet(org, inv, dirs, tmin, tmax, start, n, rf, ri, near)
            cull = load_frustum(planes, valid, k, fr)
            m = 0
            for i in range(n // 4):
                if live_mask4(rf, 4 * i) != 0:
                    ids[m] = i
                    m += 1
            top = 0
            if m > 0:
                stack_node[0], stack_m[0], stack_depth[0] = 0, m, 0
                top = 1
            while top > 0 and live > 0:
                top -= 1
                node = stack_node[top]
                depth = stack_depth[top]
                m_in = stack_m[top]
                if counters is not None:
                    counters[thread, COUNTER_NODES, depth] += 1
                box = node_box(bmin, bmax, node)
                if cull and frustum_misses_box(fr, box):
                    continue
                m = part_rays(rf, ids, masks, m_in, box)
                if counters is not None:
                    counters[thread, COUNTER_RAY_AABB, depth] += 4 * m_in
                if m == 0:
                    continue
                if count[node] > 0:
                    n_tris = leaf_triangles(first, count, prim, node, v0, v1, v2, fr, cull, leaf_tris)
                    tri_tests = 0
                    for j in range(m):
                        done, died = intersect_lanes(rf, ri, 4 * ids[j], masks[j], leaf_tris, n_tris,
                                                     v0, v1, v2, any_hit)
                        tri_tests += done
                        live -= died
                    if counters is not None:
                        counters[thread, COUNTER_RAY_TRI, depth] += tri_tests
                    continue
                near_child = first[node] + near[order[node]]
                far_child = 2 * first[node] + 1 - near_child
                stack_node[top], stack_m[top], stack_depth[top] = far_child, m, depth + 1
                stack_node[top + 1], stack_m[top + 1], stack_depth[top + 1] = near_child, m, depth + 1
                top += 2
            store_hits(rf, ri, start, n, out_t, out_prim, out_u, out_v)


@register_traversal("partition")
class PartitionTraversal(PacketTraversal):
    """Large packets with an in-place partitioned list of live SIMD rays (Overbeck et al. 2008)."""

    kernel = trace_partition
