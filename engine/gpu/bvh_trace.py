"""``bvh`` on the device: one thread per ray, a per-ray stack over the shared BVH.

The structure is Aila and Laine's (2009) while-while loop in its simplest form: a thread pops a
node, tests a leaf's triangles or both children's boxes, and pushes the far child under the near
one. The node layout is the CPU's (``engine.core.types.BVH``), read through the read-only cache;
the box test, the watertight triangle test and the tie rule are the CPU's own functions compiled
for the device (``engine.gpu.twin``), so every hit equals ``single``'s bit for bit: the box test
is conservative, and the closest hit under the tie rule does not depend on the visiting order.

Rays: org, dirs f32[C,3], tmin, tmax f32[C], the first n live (dead lanes have tmax < tmin).
"""
from __future__ import annotations

import numpy as np

from engine.core.triangle import F32_INF, closer, intersect_triangle, ray_shear, slab_test
from engine.core.types import MAX_BVH_DEPTH
from engine.gpu.device import BLOCK, require_cuda
from engine.gpu.twin import device_twin
from engine.packet.compact import inverse_component

cuda = require_cuda()

_shear = device_twin(ray_shear)
_triangle = device_twin(intersect_triangle)
_closer = device_twin(closer)
_slab = device_twin(slab_test)
_inverse = device_twin(inverse_component)

#: Most blocks of a grid-stride launch (enough to fill any current GPU).
MAX_BLOCKS = 8192
#: Stack entries per thread: the tree's depth bounds the far children waiting at once.
STACK = MAX_BVH_DEPTH + 2


@cuda.jit(device=True, inline=True)
def _walk(org, dirs, tmin, tmax, r, any_hit, bmin, bmax, first, count, prim, v0, v1, v2):
    """(t, prim, u, v) of ray r's closest hit (any_hit: some hit), (inf, -1, 0, 0) if none."""
    best_t = F32_INF
    best_prim = -1
    best_u = np.float32(0.0)
    best_v = np.float32(0.0)
    t_lo = tmin[r]
    t_hi = tmax[r]
    if not t_lo <= t_hi:
        return best_t, best_prim, best_u, best_v
    ox, oy, oz = org[r, 0], org[r, 1], org[r, 2]
    dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
    ix, iy, iz = _inverse(dx), _inverse(dy), _inverse(dz)
    kx, ky, kz, sx, sy, sz = _shear(dx, dy, dz)
    okx, oky, okz = org[r, kx], org[r, ky], org[r, kz]
    stack = cuda.local.array(STACK, np.int32)
    top = 0
    if _slab(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, 0) < F32_INF:
        stack[0] = 0
        top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        n_prims = count[node]
        if n_prims > 0:
            start = first[node]
            for i in range(start, start + n_prims):
                tri = prim[i]
                t, u, v = _triangle(okx, oky, okz, kx, ky, kz, sx, sy, sz, t_lo, t_hi, v0, v1, v2, tri)
                if t < F32_INF and _closer(t, tri, best_t, best_prim):
                    best_t, best_prim, best_u, best_v = t, tri, u, v
                    t_hi = t
                    if any_hit:
                        return best_t, best_prim, best_u, best_v
            continue
        left = first[node]
        t_left = _slab(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, left)
        t_right = _slab(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, left + 1)
        near, far = left, left + 1
        t_near, t_far = t_left, t_right
        if t_right < t_left:
            near, far = left + 1, left
            t_near, t_far = t_right, t_left
        if t_far < F32_INF:
            stack[top] = far
            top += 1
        if t_near < F32_INF:
            stack[top] = near
            top += 1
    return best_t, best_prim, best_u, best_v


@cuda.jit
def closest_kernel(org, dirs, tmin, tmax, count, bmin, bmax, first, count_in_leaf, prim, v0, v1, v2,
                   t_out, prim_out, u_out, v_out):
    """Closest hit of rays [0, count[0]): t, prim (-1 on a miss), barycentrics u, v. count is a
    device i32[1] (a queue's length, written by an earlier kernel); grid-stride over it."""
    n = min(count[0], org.shape[0])
    for r in range(cuda.grid(1), n, cuda.gridsize(1)):
        t, p, u, v = _walk(org, dirs, tmin, tmax, r, False, bmin, bmax, first, count_in_leaf, prim, v0, v1, v2)
        t_out[r] = t
        prim_out[r] = p
        u_out[r] = u
        v_out[r] = v


@cuda.jit
def occluded_kernel(org, dirs, tmin, tmax, count, bmin, bmax, first, count_in_leaf, prim, v0, v1, v2, occluded):
    """occluded[r] = 1 when ray r < count[0] hits anything in [tmin, tmax], else 0 (u8[C])."""
    n = min(count[0], org.shape[0])
    for r in range(cuda.grid(1), n, cuda.gridsize(1)):
        t, p, u, v = _walk(org, dirs, tmin, tmax, r, True, bmin, bmax, first, count_in_leaf, prim, v0, v1, v2)
        occluded[r] = 1 if p >= 0 else 0


def launch_grid(bound: int) -> int:
    """Blocks of a grid-stride launch over at most ``bound`` rays."""
    return max(1, min(MAX_BLOCKS, -(-int(bound) // BLOCK)))


class DeviceBVHTraversal:
    """The device ``bvh`` traversal over an uploaded ``DeviceBVH`` and ``DeviceTriangles``.

    ``closest_queue`` / ``occluded_queue`` take a queue's length as a device counter (the frame
    never waits for the GPU); ``closest`` / ``occluded`` take a host count (the API, the bench).
    """

    name = "bvh"
    uses_bvh = True

    def __init__(self, bvh, tris):
        self.bvh, self.tris = bvh, tris

    def closest_queue(self, org, dirs, tmin, tmax, pixel, count, bound, width, height, t_out, prim_out, u_out,
                      v_out) -> None:
        """Closest hits of the first count[0] (device i32[1], at most ``bound``) rays.
        pixel, width, height: unused here (the ray-space hierarchy indexes rays by pixel)."""
        b, t = self.bvh, self.tris
        closest_kernel[launch_grid(bound), BLOCK](org, dirs, tmin, tmax, count, b.bmin, b.bmax, b.first, b.count,
                                                  b.prim, t.v0, t.v1, t.v2, t_out, prim_out, u_out, v_out)

    def occluded_queue(self, org, dirs, tmin, tmax, pixel, count, bound, width, height, out) -> None:
        """out[r] = 1 where ray r < count[0] is blocked within [tmin, tmax], else 0 (u8)."""
        b, t = self.bvh, self.tris
        occluded_kernel[launch_grid(bound), BLOCK](org, dirs, tmin, tmax, count, b.bmin, b.bmax, b.first, b.count,
                                                   b.prim, t.v0, t.v1, t.v2, out)

    def closest(self, org, dirs, tmin, tmax, pixel, n, width, height, t_out, prim_out, u_out, v_out) -> None:
        """Closest hits of the first n rays (host int) into t_out, prim_out (-1: miss), u_out, v_out."""
        if n > 0:
            self.closest_queue(org, dirs, tmin, tmax, pixel, cuda.to_device(np.array([n], np.int32)), n, width,
                               height, t_out, prim_out, u_out, v_out)

    def occluded(self, org, dirs, tmin, tmax, pixel, n, width, height, out) -> None:
        """out[r] = 1 where ray r (< n, host int) is blocked within [tmin, tmax], else 0 (u8)."""
        if n > 0:
            self.occluded_queue(org, dirs, tmin, tmax, pixel, cuda.to_device(np.array([n], np.int32)), n, width,
                                height, out)
