"""``masked``: the whole packet descends while any of its rays hits; lane masks at the leaves.

Overbeck, Ramamoorthi, Mark 2008, Section 3 (the classic packet traversal, Wald et al.): the
stack holds nodes only. On a pop, the packet's SIMD rays are tried in order until one hits the
box (the first one, then the packet frustum as early reject, then the rest); one hit sends the
whole packet into the children, near child first from the packet's direction signs. At a leaf
(unless the frustum rejects it) every SIMD ray tests the leaf box, and the lanes that hit it
test the triangles the frustum does not cull.

Inner nodes cost little while rays are coherent, but the packet is never narrowed: as
coherence falls it visits ever more nodes that most of its rays miss.
"""
from __future__ import annotations

import numpy as np
from numba import get_thread_id, njit, prange

from engine.packet.frustum_cull import frustum_misses_box, load_frustum
from engine.packet.kernels import (STACK_SIZE, first_hit, intersect_lanes, largest_leaf, leaf_triangles,
                                   load_packet, longest_packet, node_box, packet_scratch, slab_mask4,
                                   store_hits)
from engine.packet.plugin import PacketTraversal
from engine.core.registry import register_traversal
from engine.core.types import COUNTER_NODES, COUNTER_RAY_AABB, COUNTER_RAY_TRI


@njit(cache=True, parallel=True)
def trace_masked(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax,
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
                stack_node[0], stack_depth[0] = 0, 0
                top = 1
            while top > 0 and live > 0:
                top -= 1
                node = stack_node[top]
                depth = stack_depth[top]
                if counters is not None:
                    counters[thread, COUNTER_NODES, depth] += 1
                box = node_box(bmin, bmax, node)
                if count[node] > 0:
                    if cull and frustum_misses_box(fr, box):
                        continue
                    n_tris = leaf_triangles(first, count, prim, node, v0, v1, v2, fr, cull, leaf_tris)
                    tri_tests = 0
                    for i in range(n_simd):
                        mask = slab_mask4(rf, 4 * i, box)
                        if mask != 0:
                            done, died = intersect_lanes(rf, ri, 4 * i, mask, leaf_tris, n_tris,
                                                         v0, v1, v2, any_hit)
                            tri_tests += done
                            live -= died
                    if counters is not None:
                        counters[thread, COUNTER_RAY_AABB, depth] += 4 * n_simd
                        counters[thread, COUNTER_RAY_TRI, depth] += tri_tests
                    continue
                hit, tests = first_hit(rf, 0, n_simd, box, fr, cull)
                if counters is not None:
                    counters[thread, COUNTER_RAY_AABB, depth] += tests
                if hit >= n_simd:
                    continue
                near_child = first[node] + near[order[node]]
                far_child = 2 * first[node] + 1 - near_child
                stack_node[top], stack_depth[top] = far_child, depth + 1
                stack_node[top + 1], stack_depth[top + 1] = near_child, depth + 1
                top += 2
            store_hits(rf, ri, start, n, out_t, out_prim, out_u, out_v)


@register_traversal("masked")
class MaskedTraversal(PacketTraversal):
    """Large packets that descend while any ray hits, lane masks at the leaves (Overbeck et al. 2008)."""

    kernel = trace_masked
