"""``wide`` on the device: the CPU's 8-wide tree (``engine.query.wide``), one thread per ray.

``bvh`` (``engine.gpu.bvh_trace``) walks the binary tree, two boxes a node; this walks the tree
the CPU's ``wide`` traversal and the mesh queries walk, collapsed from the same binary BVH:
eight child boxes a node, about half as many levels, and a node's children visited nearest
first. Issue 20 asks the GPU's node layout and width to be measured against Aila and Laine's
binary walk; this is the wide side of that comparison (the config word ``wide`` selects it on
``device = "cuda"`` as on the CPU). Leaves and triangle order are the binary tree's, so the
uploaded ``DeviceBVH``'s leaf-ordered corners serve both, and the triangle test, box test and
tie rule are the CPU's functions compiled for the device (``engine.gpu.twin``): every closest
hit equals ``single``'s bit for bit, whatever order the children are visited in.

Device layout, W wide nodes: box f32[W,6,8] (rows lo x, y, z, hi x, y, z; column = slot) and
meta i32[W,2,8] (row 0: child -- a wide node, or a leaf's first row of the leaf-ordered
triangles; row 1: size -- 0 inner, > 0 a leaf of that many triangles, -1 an empty slot; empty
slots are skipped by their size, never by their NaN boxes, whose min/max differ between targets).

An animation that refits the binary tree (``engine.gpu.refit``) refits this one by collapsing
the refitted host tree again and copying its boxes and links into the same device arrays
(``refit_from``): the collapse follows box areas, so a refit may merge other nodes (other
links, and rarely another node count, when the frame makes the traversal anew).
"""
from __future__ import annotations

import numpy as np

from engine.core.triangle import F32_INF, closer, intersect_triangle, slab_interval
from engine.core.types import MAX_BVH_DEPTH
from engine.gpu.bvh_trace import DeviceBVHTraversal, launch_grid, ray_setup
from engine.gpu.device import BLOCK, require_cuda
from engine.gpu.launch import PreparedLaunch
from engine.gpu.scene_upload import upload
from engine.gpu.twin import device_twin
from engine.query.wide import WIDTH, collapse

cuda = require_cuda()

_triangle = device_twin(intersect_triangle)
_closer = device_twin(closer)
_slab_interval = device_twin(slab_interval)

#: Stack entries per thread: a node pushes at most WIDTH entries and pops one, at most
#: MAX_BVH_DEPTH nodes deep (the CPU walk's bound, ``engine.query.walk.STACK_SIZE``).
STACK = WIDTH * MAX_BVH_DEPTH + 2


@cuda.jit(device=True)
def _walk(org, dirs, tmin, tmax, r, any_hit, box, meta, prim, v0, v1, v2):
    """(t, prim, u, v) of ray r's closest hit (any_hit: some hit), (inf, -1, 0, 0) if none."""
    best_t = F32_INF
    best_prim = -1
    best_u = np.float32(0.0)
    best_v = np.float32(0.0)
    t_lo = tmin[r]
    t_hi = tmax[r]
    if not t_lo <= t_hi:
        return best_t, best_prim, best_u, best_v
    ox, oy, oz, ix, iy, iz, kx, ky, kz, sx, sy, sz, okx, oky, okz = ray_setup(org, dirs, r)
    stack_node = cuda.local.array(STACK, np.int32)
    stack_size = cuda.local.array(STACK, np.int32)
    stack_t = cuda.local.array(STACK, np.float32)
    hit_t = cuda.local.array(WIDTH, np.float32)
    hit_slot = cuda.local.array(WIDTH, np.int32)
    stack_node[0] = 0  # the root's wide node (its slots' boxes are the tests)
    stack_size[0] = 0
    stack_t[0] = t_lo
    top = 1
    while top > 0:
        top -= 1
        if stack_t[top] > t_hi:  # entered beyond the closest hit found since it was pushed
            continue
        node = stack_node[top]
        size = stack_size[top]
        if size > 0:
            for i in range(node, node + size):
                tri = prim[i]
                t, u, v = _triangle(okx, oky, okz, kx, ky, kz, sx, sy, sz, t_lo, t_hi, v0, v1, v2, i)
                if t < F32_INF and _closer(t, tri, best_t, best_prim):
                    best_t, best_prim, best_u, best_v = t, tri, u, v
                    t_hi = t
                    if any_hit:
                        return best_t, best_prim, best_u, best_v
            continue
        # The node's children that the ray enters, sorted by entry distance (insertion).
        hits = 0
        for s in range(WIDTH):
            if meta[node, 1, s] < 0:
                continue
            t = _slab_interval(ox, oy, oz, ix, iy, iz, t_lo, t_hi, box[node, 0, s], box[node, 1, s],
                               box[node, 2, s], box[node, 3, s], box[node, 4, s], box[node, 5, s])
            if t < F32_INF:
                j = hits
                while j > 0 and hit_t[j - 1] > t:
                    hit_t[j] = hit_t[j - 1]
                    hit_slot[j] = hit_slot[j - 1]
                    j -= 1
                hit_t[j] = t
                hit_slot[j] = s
                hits += 1
        # Farthest pushed first, so the nearest is popped next.
        for j in range(hits - 1, -1, -1):
            s = hit_slot[j]
            stack_node[top] = meta[node, 0, s]
            stack_size[top] = meta[node, 1, s]
            stack_t[top] = hit_t[j]
            top += 1
    return best_t, best_prim, best_u, best_v


@cuda.jit
def closest_kernel(org, dirs, tmin, tmax, count, box, meta, prim, leaf_tris, t_out, prim_out, u_out, v_out):
    """Closest hit of rays [0, count[0]) (device i32[1]): t, prim (-1 on a miss), u, v;
    grid-stride over them."""
    n = min(count[0], org.shape[0])
    v0, v1, v2 = leaf_tris[0], leaf_tris[1], leaf_tris[2]
    for r in range(cuda.grid(1), n, cuda.gridsize(1)):
        t, p, u, v = _walk(org, dirs, tmin, tmax, r, False, box, meta, prim, v0, v1, v2)
        t_out[r] = t
        prim_out[r] = p
        u_out[r] = u
        v_out[r] = v


@cuda.jit
def occluded_kernel(org, dirs, tmin, tmax, count, box, meta, prim, leaf_tris, occluded):
    """occluded[r] = 1 when ray r < count[0] hits anything in [tmin, tmax], else 0 (u8[C])."""
    n = min(count[0], org.shape[0])
    v0, v1, v2 = leaf_tris[0], leaf_tris[1], leaf_tris[2]
    for r in range(cuda.grid(1), n, cuda.gridsize(1)):
        t, p, u, v = _walk(org, dirs, tmin, tmax, r, True, box, meta, prim, v0, v1, v2)
        occluded[r] = 1 if p >= 0 else 0


def wide_tables(bvh) -> tuple[np.ndarray, np.ndarray]:
    """(box f32[W,6,8], meta i32[W,2,8]) of the 8-wide tree collapsed from host ``bvh`` (a tree
    of no triangles: one node of empty slots)."""
    if bvh.prim.shape[0] == 0:
        return np.full((1, 6, WIDTH), np.nan, np.float32), np.stack(
            [np.zeros((1, WIDTH), np.int32), np.full((1, WIDTH), -1, np.int32)], axis=1)
    box, child, size = collapse(bvh.bmin, bvh.bmax, bvh.first, bvh.count)
    return np.ascontiguousarray(box, np.float32), np.ascontiguousarray(np.stack([child, size], axis=1), np.int32)


class DeviceWideTraversal(DeviceBVHTraversal):
    """The device ``wide`` traversal: ``DeviceBVHTraversal``'s interface (its host-count
    ``closest`` / ``occluded`` go through the queue methods below) over the 8-wide tree of
    ``host_bvh``, the tree ``device_bvh`` was uploaded from, whose leaf-ordered triangles it reads.
    A node's children are visited nearest first for every query (no far-first order)."""

    name = "wide"

    def __init__(self, device_bvh, tris, host_bvh):
        super().__init__(device_bvh, tris, far_first=False)
        box, meta = wide_tables(host_bvh)
        self.box, self.meta = upload(box), upload(meta)
        self.nodes = box.shape[0]

    def refit_from(self, host_bvh) -> bool:
        """The 8-wide tree of a refit of the binary tree, boxes and links, copied into the uploaded
        arrays; False (nothing copied) when it has another number of wide nodes, and the caller
        makes the traversal anew. The collapse opens the inner child with the larger box first, so
        refitted boxes can merge other nodes: the same topology does not give the same links."""
        box, meta = wide_tables(host_bvh)
        if box.shape[0] != self.nodes:
            return False
        self.box.copy_to_device(box)
        self.meta.copy_to_device(meta)
        return True

    def _args(self, org, dirs, tmin, tmax, count):
        b = self.bvh
        return org, dirs, tmin, tmax, count, self.box, self.meta, b.prim, b.leaf_tris

    def closest_queue(self, org, dirs, tmin, tmax, pixel, count, bound, width, height, t_out, prim_out, u_out,
                      v_out) -> None:
        """Closest hits of the first count[0] (device i32[1], at most ``bound``) rays."""
        closest_kernel[launch_grid(bound), BLOCK](*self._args(org, dirs, tmin, tmax, count), t_out, prim_out, u_out,
                                                  v_out)

    def occluded_queue(self, org, dirs, tmin, tmax, pixel, count, bound, width, height, out) -> None:
        """out[r] = 1 where ray r < count[0] is blocked within [tmin, tmax], else 0 (u8)."""
        occluded_kernel[launch_grid(bound), BLOCK](*self._args(org, dirs, tmin, tmax, count), out)

    def queue_launch(self, query: str, org, dirs, tmin, tmax, pixel, count, bound, width, height, *out, light=None,
                     secondary=False):
        """A prepared launch of ``closest_queue`` / ``occluded_queue`` on fixed arrays (as ``bvh``'s)."""
        kernel = closest_kernel if query == "closest" else occluded_kernel
        return PreparedLaunch(kernel, launch_grid(bound), BLOCK, (*self._args(org, dirs, tmin, tmax, count), *out))
