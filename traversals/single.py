"""``single``: one ray at a time, stack-based, near child first.

The reference CPU traversal: every other CPU traversal must return exactly its hits.
Parallel over chunks of rays with ``prange``; ignores packets and frusta.
"""
from __future__ import annotations

import numpy as np
from numba import get_thread_id, njit, prange

from engine.core.triangle import F32_INF, closer, intersect_triangle, ray_shear, slab_test
from engine.core.registry import register_traversal
from engine.core.types import (COUNTER_NODES, COUNTER_RAY_AABB, COUNTER_RAY_TRI, MAX_BVH_DEPTH, check_answer_arrays,
                          empty_hits, thread_counters)

CHUNK = 256  # rays per prange task: one stack allocation per chunk


@njit(cache=True)
def walk_ray(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax, r, any_hit,
             stack, stack_depth, counters, thread, nodes):
    """``single``'s walk of ray r: (t, prim, u, v, popped) of its closest (any_hit: first) hit and
    how many nodes it popped. stack, stack_depth: i32[2 * MAX_BVH_DEPTH + 2] scratch. counters:
    i64[threads,3,D] or None (added to in row ``thread``); nodes: i32[N] or None, filled with the
    popped nodes in order (``packetrt show`` draws them)."""
    best_t = F32_INF
    best_prim = -1
    best_u = np.float32(0.0)
    best_v = np.float32(0.0)
    popped = 0
    t_lo = tmin[r]
    t_hi = tmax[r]
    if not t_lo <= t_hi:
        return best_t, best_prim, best_u, best_v, popped
    ox, oy, oz = org[r, 0], org[r, 1], org[r, 2]
    ix, iy, iz = inv[r, 0], inv[r, 1], inv[r, 2]
    kx, ky, kz, sx, sy, sz = ray_shear(dirs[r, 0], dirs[r, 1], dirs[r, 2])
    okx, oky, okz = org[r, kx], org[r, ky], org[r, kz]
    top = 0
    if counters is not None:
        counters[thread, COUNTER_RAY_AABB, 0] += 1
    if slab_test(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, 0) < F32_INF:
        stack[0] = 0
        stack_depth[0] = 0
        top = 1
    done = False
    while top > 0 and not done:
        top -= 1
        node = stack[top]
        depth = stack_depth[top]
        if nodes is not None:
            nodes[popped] = node
        popped += 1
        if counters is not None:
            counters[thread, COUNTER_NODES, depth] += 1
        if count[node] > 0:
            for i in range(first[node], first[node] + count[node]):
                tri = prim[i]
                if counters is not None:
                    counters[thread, COUNTER_RAY_TRI, depth] += 1
                t, u, v = intersect_triangle(okx, oky, okz, kx, ky, kz, sx, sy, sz, t_lo, t_hi, v0, v1, v2, tri)
                if t < F32_INF and closer(t, tri, best_t, best_prim):
                    best_t, best_prim, best_u, best_v = t, tri, u, v
                    if any_hit:
                        done = True
                        break
                    t_hi = t
            continue
        left = first[node]
        if counters is not None:
            counters[thread, COUNTER_RAY_AABB, depth + 1] += 2
        t_left = slab_test(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, left)
        t_right = slab_test(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, left + 1)
        near, far = left, left + 1
        t_near, t_far = t_left, t_right
        if t_right < t_left:
            near, far = left + 1, left
            t_near, t_far = t_right, t_left
        if t_far < F32_INF:
            stack[top] = far
            stack_depth[top] = depth + 1
            top += 1
        if t_near < F32_INF:
            stack[top] = near
            stack_depth[top] = depth + 1
            top += 1
    return best_t, best_prim, best_u, best_v, popped


@njit(cache=True, parallel=True)
def trace_single(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax,
                 any_hit, out_t, out_prim, out_u, out_v, counters):
    """Closest hit (any_hit False) or first hit (any_hit True) for every ray.

    org, inv, dirs: f32[R,3]; tmin, tmax: f32[R]. Writes out_t/out_prim/out_u/out_v (f32/i32[R]);
    for any_hit, out_prim >= 0 marks an occluded ray. counters: i64[threads,3,D] or None.
    """
    n_rays = org.shape[0]
    n_chunks = (n_rays + CHUNK - 1) // CHUNK
    for chunk in prange(n_chunks):
        stack = np.empty(2 * MAX_BVH_DEPTH + 2, np.int32)
        stack_depth = np.empty(2 * MAX_BVH_DEPTH + 2, np.int32)
        thread = get_thread_id()
        for r in range(chunk * CHUNK, min(n_rays, (chunk + 1) * CHUNK)):
            t, hit, u, v, _ = walk_ray(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax,
                                       r, any_hit, stack, stack_depth, counters, thread, None)
            out_t[r] = t
            out_prim[r] = hit
            out_u[r] = u
            out_v[r] = v


@register_traversal("single")
class SingleRayTraversal:
    """One ray at a time, stack-based, near child first; the reference CPU traversal."""

    #: Frusta are not read: the tracer builds none for this traversal.
    uses_frusta = False

    def intersect(self, bvh, tris, rays, packets, frusta, hits, stats):
        check_answer_arrays(rays.org.shape[0], hits.t, hits.prim, hits.u, hits.v)
        trace_single(bvh.bmin, bvh.bmax, bvh.first, bvh.count, bvh.prim, tris.v0, tris.v1, tris.v2,
                     rays.org, rays.inv_dir, rays.dir, rays.tmin, rays.tmax, False,
                     hits.t, hits.prim, hits.u, hits.v, thread_counters(stats))

    def occluded(self, bvh, tris, rays, packets, frusta, occluded, stats):
        any_hit = empty_hits(rays.org.shape[0])  # scratch: which triangle stopped each ray
        trace_single(bvh.bmin, bvh.bmax, bvh.first, bvh.count, bvh.prim, tris.v0, tris.v1, tris.v2,
                     rays.org, rays.inv_dir, rays.dir, rays.tmin, rays.tmax, True,
                     any_hit.t, any_hit.prim, any_hit.u, any_hit.v, thread_counters(stats))
        occluded[:] = any_hit.prim >= 0
