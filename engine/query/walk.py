"""The per-ray BVH walk every mesh query shares (one ray, a stack, near child first).

Modes (integer constants, so one compiled helper serves every kernel and reaches the disk cache):

- ``CLOSEST``: the closest hit (ties to the smaller triangle index, ``engine.core.triangle.closer``);
  the segment shrinks as hits are found.
- ``ANY``: stop at the first hit found.
- ``COLLECT``: every hit on [t_lo, t_hi]; the first ``cap`` are written to the scratch buffers
  (unsorted) and the total is returned, so a caller can count (cap 0) and then fill.

Triangles are the watertight test's float32 corners in the mesh's local frame, stored in the
BVH's ``prim`` order (row i is triangle prim[i]), so a leaf's corners are contiguous in memory.
"""
import numpy as np
from numba import njit

from engine.core.triangle import F32_INF, closer, intersect_triangle, ray_shear, slab_test
from engine.core.types import MAX_BVH_DEPTH

CLOSEST, ANY, COLLECT = 0, 1, 2

#: Size of the per-thread traversal stack (i32).
STACK_SIZE = 2 * MAX_BVH_DEPTH + 2


@njit(cache=True)
def walk(bmin, bmax, first, count, prim, v0, v1, v2, org, dirs, inv, r, t_lo, t_hi, mode, stack,
         buf_t, buf_tri, buf_u, buf_v, cap):
    """Walk ray r (row of org, dirs, inv: f32[R,3]) over [t_lo, t_hi].

    v0, v1, v2: f32[P,3] corners in prim order. Returns (n, t, tri, u, v): tri is a mesh face
    index (prim[i]). For CLOSEST / ANY, n is 1 on a hit and (t, tri, u, v) the hit;
    for COLLECT, n is the number of hits (all of them, even past ``cap``); the first min(n, cap)
    are in buf_t, buf_tri, buf_u, buf_v (f32/i32/f32/f32[cap]) in the order found.
    stack: i32[STACK_SIZE] scratch.
    """
    best_t = F32_INF
    best_tri = -1
    best_u = np.float32(0.0)
    best_v = np.float32(0.0)
    n = 0
    ox, oy, oz = org[r, 0], org[r, 1], org[r, 2]
    ix, iy, iz = inv[r, 0], inv[r, 1], inv[r, 2]
    kx, ky, kz, sx, sy, sz = ray_shear(dirs[r, 0], dirs[r, 1], dirs[r, 2])
    okx, oky, okz = org[r, kx], org[r, ky], org[r, kz]
    if slab_test(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, 0) == F32_INF:
        return 0, best_t, best_tri, best_u, best_v
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        if count[node] > 0:
            for i in range(first[node], first[node] + count[node]):
                t, u, v = intersect_triangle(okx, oky, okz, kx, ky, kz, sx, sy, sz, t_lo, t_hi, v0, v1, v2, i)
                if t == F32_INF:
                    continue
                tri = prim[i]
                if mode == COLLECT:
                    if n < cap:
                        buf_t[n] = t
                        buf_tri[n] = tri
                        buf_u[n] = u
                        buf_v[n] = v
                    n += 1
                elif closer(t, tri, best_t, best_tri):
                    best_t, best_tri, best_u, best_v = t, tri, u, v
                    n = 1
                    if mode == ANY:
                        return n, best_t, best_tri, best_u, best_v
                    t_hi = t  # CLOSEST: nothing beyond this hit matters any more
            continue
        left = first[node]
        t_left = slab_test(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, left)
        t_right = slab_test(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, left + 1)
        near, far = left, left + 1
        if t_right < t_left:
            near, far = left + 1, left
            t_left, t_right = t_right, t_left
        if t_right < F32_INF:
            stack[top] = far
            top += 1
        if t_left < F32_INF:
            stack[top] = near
            top += 1
    return n, best_t, best_tri, best_u, best_v


@njit(cache=True)
def sort_hits(buf_t, buf_tri, buf_u, buf_v, n):
    """Insertion sort of the first n buffered hits by (t, triangle index); n is small."""
    for i in range(1, n):
        t, tri, u, v = buf_t[i], buf_tri[i], buf_u[i], buf_v[i]
        j = i - 1
        while j >= 0 and closer(t, tri, buf_t[j], buf_tri[j]):
            buf_t[j + 1], buf_tri[j + 1], buf_u[j + 1], buf_v[j + 1] = buf_t[j], buf_tri[j], buf_u[j], buf_v[j]
            j -= 1
        buf_t[j + 1], buf_tri[j + 1], buf_u[j + 1], buf_v[j + 1] = t, tri, u, v


@njit(cache=True)
def merge_crossings(buf_t, buf_tri, buf_u, buf_v, n, gap):
    """Drop sorted hits closer than ``gap`` (along t) to the previous kept hit: a ray through a
    shared edge or vertex reports each triangle there, but it crosses the surface once (trimesh
    steps 1e-6 of the mesh scale past each hit for the same reason). Returns the kept count."""
    kept = 0
    for i in range(n):
        if kept > 0 and buf_t[i] - buf_t[kept - 1] < gap:
            continue
        buf_t[kept], buf_tri[kept], buf_u[kept], buf_v[kept] = buf_t[i], buf_tri[i], buf_u[i], buf_v[i]
        kept += 1
    return kept
