"""``bvh`` on the device: one thread per ray, a per-ray stack over the shared BVH.

The loop is Aila and Laine's (2009) in its simplest form: a thread pops a node, tests a leaf's
triangles or both children's boxes, and pushes the far child under the near one. The tree is the
CPU's, laid out as they suggest (``engine.gpu.scene_upload.DeviceBVH``): a node's row holds both
children's boxes, and triangles are stored in leaf order. The watertight triangle test and the
tie rule are the CPU's own functions compiled for the device (``engine.gpu.twin``) and the box
test is the CPU's own too, so every hit equals ``single``'s bit for bit: the box test is
conservative, and the closest hit under the tie rule does not depend on the visiting order.

Rays: org, dirs f32[C,3], tmin, tmax f32[C], the first n live (dead lanes have tmax < tmin).
"""
from __future__ import annotations

import numpy as np

from engine.core.triangle import F32_INF, closer, intersect_triangle, ray_shear, slab_interval
from engine.core.types import MAX_BVH_DEPTH
from engine.gpu.device import BLOCK, require_cuda
from engine.gpu.launch import PreparedLaunch
from engine.gpu.twin import device_twin
from engine.packet.compact import inverse_component

cuda = require_cuda()

_shear = device_twin(ray_shear)
_triangle = device_twin(intersect_triangle)
_closer = device_twin(closer)
_inverse = device_twin(inverse_component)

#: Most blocks of a grid-stride launch (enough to fill any current GPU).
MAX_BLOCKS = 8192
#: Stack entries per thread: the tree's depth bounds the far children waiting at once.
STACK = MAX_BVH_DEPTH + 2


_slab_interval = device_twin(slab_interval)


@cuda.jit(device=True)
def _slab(ox, oy, oz, ix, iy, iz, t_lo, t_hi, box, row, at):
    """The CPU's box test (``slab_interval``) against the box box[row, at:at+6] (min xyz, max
    xyz) of the packed table."""
    return _slab_interval(ox, oy, oz, ix, iy, iz, t_lo, t_hi, box[row, at], box[row, at + 1], box[row, at + 2],
                          box[row, at + 3], box[row, at + 4], box[row, at + 5])


@cuda.jit(device=True)
def ray_setup(org, dirs, r):
    """What a walk of ray r computes once: its origin, the inverse of its direction (the box
    test's), the watertight test's shear (kx, ky, kz, sx, sy, sz) and the origin in the shear's
    axis order (okx, oky, okz). Shared by the binary and the 8-wide walk."""
    dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
    kx, ky, kz, sx, sy, sz = _shear(dx, dy, dz)
    return (org[r, 0], org[r, 1], org[r, 2], _inverse(dx), _inverse(dy), _inverse(dz), kx, ky, kz, sx, sy, sz,
            org[r, kx], org[r, ky], org[r, kz])


@cuda.jit(device=True)
def _walk(org, dirs, tmin, tmax, r, any_hit, far_first, child_boxes, links, prim, v0, v1, v2, root):
    """(t, prim, u, v) of ray r's closest hit (any_hit: some hit), (inf, -1, 0, 0) if none.
    v0, v1, v2: the corners in leaf order (row i holds triangle prim[i]). far_first: the child
    the ray enters later is visited first (only an any-hit walk may: the answer is the same, only
    how soon a blocked ray stops changes)."""
    best_t = F32_INF
    best_prim = -1
    best_u = np.float32(0.0)
    best_v = np.float32(0.0)
    t_lo = tmin[r]
    t_hi = tmax[r]
    if not t_lo <= t_hi:
        return best_t, best_prim, best_u, best_v
    ox, oy, oz, ix, iy, iz, kx, ky, kz, sx, sy, sz, okx, oky, okz = ray_setup(org, dirs, r)
    stack = cuda.local.array(STACK, np.int32)
    top = 0
    if _slab(ox, oy, oz, ix, iy, iz, t_lo, t_hi, root, 0, 0) < F32_INF:  # root: f32[1,6]
        stack[0] = 0
        top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        first = links[node, 0]
        n_prims = links[node, 1]
        if n_prims > 0:
            for i in range(first, first + n_prims):
                tri = prim[i]
                t, u, v = _triangle(okx, oky, okz, kx, ky, kz, sx, sy, sz, t_lo, t_hi, v0, v1, v2, i)
                if t < F32_INF and _closer(t, tri, best_t, best_prim):
                    best_t, best_prim, best_u, best_v = t, tri, u, v
                    t_hi = t
                    if any_hit:
                        return best_t, best_prim, best_u, best_v
            continue
        t_left = _slab(ox, oy, oz, ix, iy, iz, t_lo, t_hi, child_boxes, node, 0)
        t_right = _slab(ox, oy, oz, ix, iy, iz, t_lo, t_hi, child_boxes, node, 6)
        near, far = first, first + 1
        t_near, t_far = t_left, t_right
        if (t_right < t_left) != far_first:
            near, far = first + 1, first
            t_near, t_far = t_right, t_left
        if t_far < F32_INF:
            stack[top] = far
            top += 1
        if t_near < F32_INF:
            stack[top] = near
            top += 1
    return best_t, best_prim, best_u, best_v


@cuda.jit
def closest_kernel(org, dirs, tmin, tmax, count, child_boxes, links, prim, leaf_tris, root, t_out, prim_out, u_out,
                   v_out):
    """Closest hit of rays [0, count[0]): t, prim (-1 on a miss), barycentrics u, v. count is a
    device i32[1] (a queue's length, written by an earlier kernel); grid-stride over it."""
    n = min(count[0], org.shape[0])
    v0, v1, v2 = leaf_tris[0], leaf_tris[1], leaf_tris[2]
    for r in range(cuda.grid(1), n, cuda.gridsize(1)):
        t, p, u, v = _walk(org, dirs, tmin, tmax, r, False, False, child_boxes, links, prim, v0, v1, v2, root)
        t_out[r] = t
        prim_out[r] = p
        u_out[r] = u
        v_out[r] = v


@cuda.jit
def occluded_kernel(org, dirs, tmin, tmax, count, child_boxes, links, prim, leaf_tris, root, far_first, occluded):
    """occluded[r] = 1 when ray r < count[0] hits anything in [tmin, tmax], else 0 (u8[C]);
    far_first: walk the child the ray enters later first."""
    n = min(count[0], org.shape[0])
    v0, v1, v2 = leaf_tris[0], leaf_tris[1], leaf_tris[2]
    for r in range(cuda.grid(1), n, cuda.gridsize(1)):
        t, p, u, v = _walk(org, dirs, tmin, tmax, r, True, far_first, child_boxes, links, prim, v0, v1, v2, root)
        occluded[r] = 1 if p >= 0 else 0


def launch_grid(bound: int) -> int:
    """Blocks of a grid-stride launch over at most ``bound`` rays."""
    return max(1, min(MAX_BLOCKS, -(-int(bound) // BLOCK)))


class DeviceBVHTraversal:
    """The device ``bvh`` traversal over an uploaded ``DeviceBVH`` and ``DeviceTriangles``.

    ``closest_queue`` / ``occluded_queue`` take a queue's length as a device counter (the frame
    never waits for the GPU); ``closest`` / ``occluded`` take a host count (the API, the bench).
    far_first: occlusion walks visit the child a ray enters later first -- for shadow rays cast
    from a surface, the end at the light (``engine.gpu.traversals.walks_far_first``).
    """

    name = "bvh"
    uses_bvh = True

    def __init__(self, bvh, tris, far_first: bool = False):
        self.bvh, self.tris = bvh, tris
        self.far_first = bool(far_first)

    def closest_queue(self, org, dirs, tmin, tmax, pixel, count, bound, width, height, t_out, prim_out, u_out,
                      v_out) -> None:
        """Closest hits of the first count[0] (device i32[1], at most ``bound``) rays.
        pixel, width, height: unused here (the ray-space hierarchy indexes rays by pixel)."""
        b = self.bvh
        closest_kernel[launch_grid(bound), BLOCK](org, dirs, tmin, tmax, count, b.child_boxes, b.links, b.prim,
                                                  b.leaf_tris, b.root_row, t_out, prim_out, u_out, v_out)

    def occluded_queue(self, org, dirs, tmin, tmax, pixel, count, bound, width, height, out) -> None:
        """out[r] = 1 where ray r < count[0] is blocked within [tmin, tmax], else 0 (u8)."""
        b = self.bvh
        occluded_kernel[launch_grid(bound), BLOCK](org, dirs, tmin, tmax, count, b.child_boxes, b.links, b.prim,
                                                   b.leaf_tris, b.root_row, self.far_first, out)

    def queue_launch(self, query: str, org, dirs, tmin, tmax, pixel, count, bound, width, height, *out, light=None,
                     secondary=False):
        """A prepared launch (``engine.gpu.launch``) of ``closest_queue`` (query "closest", out =
        t, prim, u, v) or ``occluded_queue`` (query "occluded", out = flags) on fixed arrays.
        light, secondary: unused (the ray-space hierarchy groups rays by them)."""
        b = self.bvh
        kernel, order = (closest_kernel, ()) if query == "closest" else (occluded_kernel, (self.far_first,))
        return PreparedLaunch(kernel, launch_grid(bound), BLOCK, (org, dirs, tmin, tmax, count, b.child_boxes, b.links,
                                                                  b.prim, b.leaf_tris, b.root_row, *order, *out))

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
