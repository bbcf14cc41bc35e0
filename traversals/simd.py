"""``simd``: every 2x2 SIMD ray walks the BVH on its own (the paper's "2x2 SIMD" baseline).

Overbeck, Ramamoorthi, Mark 2008, Section 6: the small-packet reference the large packets are
measured against. Packets only group the SIMD rays (and share a frustum): each SIMD ray has its
own stack; on a pop its four lanes test the box together, and the node is skipped when none
hits (or when the packet frustum misses the box, tested first). At a leaf the lanes that hit
the box test the triangles the frustum does not cull. Near child first from the packet's
direction signs.
"""
from __future__ import annotations

import numpy as np
from numba import get_thread_id, njit, prange

from engine.packet.frustum_cull import frustum_misses_box, load_frustum
from engine.packet.kernels import (STACK_SIZE, intersect_lanes, largest_leaf, leaf_triangles, live_mask4,
                                   load_packet, longest_packet, node_box, packet_scratch, slab_mask4,
                                   store_hits)
from engine.packet.plugin import PacketTraversal
from engine.core.registry import register_traversal
from engine.core.types import COUNTER_NODES, COUNTER_RAY_AABB, COUNTER_RAY_TRI


@njit(cache=True, parallel=True)
def trace_simd(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax,
               offsets, planes, valid, order, n_chunks, any_hit, out_t, out_prim, out_u, out_v,
               counters):
    """Closest (any_hit False) or first (any_hit True) hits of every SIMD ray; see the module doc
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
            load_packet(org, inv, dirs, tmin, tmax, start, n, rf, ri, near)
            cull = load_frustum(planes, valid, k, fr)
            for i in range(n // 4):
                lane0 = 4 * i
                live = live_mask4(rf, lane0)
                top = 0
                if live != 0:
                    stack_node[0], stack_depth[0] = 0, 0
                    top = 1
                while top > 0 and live != 0:
                    top -= 1
                    node = stack_node[top]
                    depth = stack_depth[top]
                    if counters is not None:
                        counters[thread, COUNTER_NODES, depth] += 1
                    box = node_box(bmin, bmax, node)
                    if cull and frustum_misses_box(fr, box):
                        continue
                    mask = slab_mask4(rf, lane0, box)
                    if counters is not None:
                        counters[thread, COUNTER_RAY_AABB, depth] += 4
                    if mask == 0:
                        continue
                    if count[node] > 0:
                        n_tris = leaf_triangles(first, count, prim, node, v0, v1, v2, fr, cull, leaf_tris)
                        tri_tests, died = intersect_lanes(rf, ri, lane0, mask, leaf_tris, n_tris,
                                                          v0, v1, v2, any_hit)
                        if died:
                            live = live_mask4(rf, lane0)
                        if counters is not None:
                            counters[thread, COUNTER_RAY_TRI, depth] += tri_tests
                        continue
                    near_child = first[node] + near[order[node]]
                    far_child = 2 * first[node] + 1 - near_child
                    stack_node[top], stack_depth[top] = far_child, depth + 1
                    stack_node[top + 1], stack_depth[top + 1] = near_child, depth + 1
                    top += 2
            store_hits(rf, ri, start, n, out_t, out_prim, out_u, out_v)


@register_traversal("simd")
class SimdTraversal(PacketTraversal):
    """Each 2x2 SIMD ray of a packet traverses alone: the small-packet baseline (Overbeck et al. 2008)."""

    kernel = trace_simd
