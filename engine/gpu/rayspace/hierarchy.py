"""The cone-sphere hierarchy over one ray queue, built on the device (layout of
``engine.rayspace.cone_sphere``: level 0 = one slot per live ray grouped by 2x2 pixel block,
levels 1 .. L = mip-map grids up to the root).

Per call:

1. ``_count_blocks`` (one thread per ray): live rays counted per 2x2 pixel block with atomics;
   the stable scan (``engine.gpu.scan``) turns the counts into ``block_start``.
2. ``_fill_slots`` (per ray): each live ray takes a slot of its block by an atomic increment;
   ``_order_blocks`` (per block) then sorts the block's slots by ray id, so the layout is the
   CPU's stable counting sort whatever order the atomics ran in.
3. ``_leaves`` (per slot): the exact ray as a cone-sphere (``leaf_node``'s twin); with a light
   point given, reversed to leave the light as on the CPU.
4. ``_inner`` (per node, one launch per level, bottom-up): each node from its children
   (``merge_node``'s twin, float64 inside, float32 stored with outward rounding).
5. ``_spheres`` (per triangle): triangle bounding spheres (``store_sphere``'s twin), recomputed
   every call so a moving scene needs nothing refitted; ``_node_scale`` and the spheres give the
   test's absolute slack (``absolute_slack`` on the CPU) by block-reduced atomic maxima.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from engine.gpu.device import BLOCK, blocks, require_cuda
from engine.gpu.fill import fill_array
from engine.gpu.rayspace.scratch import Scratch
from engine.gpu.scan import Scanner
from engine.gpu.twin import device_twin
from engine.rayspace import cone_sphere, triangle_spheres
from engine.rayspace.cone_sphere import TEST_SLACK, level_grid

cuda = require_cuda()

# Device twins of the CPU build's helpers; each keyword re-binds a helper the twinned function
# calls by name to that helper's own twin.
_store_length = device_twin(cone_sphere.store_length)
_reversed_segment = device_twin(cone_sphere.reversed_segment)
_grow_sphere = device_twin(cone_sphere.grow_sphere)
_grow_cone = device_twin(cone_sphere.grow_cone)
child_grid = device_twin(cone_sphere.child_grid)
node_overlap = device_twin(cone_sphere.node_overlap)
_leaf_node = device_twin(cone_sphere.leaf_node, reversed_segment=_reversed_segment, store_length=_store_length)
_merge_node = device_twin(cone_sphere.merge_node, child_grid=child_grid, grow_sphere=_grow_sphere,
                          grow_cone=_grow_cone, store_length=_store_length)
_store_sphere = device_twin(triangle_spheres.store_sphere,
                            smallest_sphere=device_twin(triangle_spheres.smallest_sphere))


@dataclass
class DeviceHierarchy:
    """``engine.rayspace.cone_sphere.RayHierarchy`` on the device (M nodes over all levels,
    S = ``n_slots`` live-ray slots; arrays may be longer than M, S: scratch views).

    centre, axis: f32[M,3]; radius (-1 = empty), alpha, cos_a, sin_a, far: f32[M].
    level_offset: i64[levels+2] (``level_offset_host``: its host copy); level_width,
    level_height: i64[levels+1] (level 0: S x 1).
    block_start: i32[n1+1] (slots of level-1 block b); slot_ray: i32[S].
    sphere_c: f32[T,3], sphere_r: f32[T]: the triangles' bounding spheres; abs_tol: the test's
    absolute slack (float32). level_sizes: host list of the node count of every level.
    """

    centre: object
    radius: object
    axis: object
    alpha: object
    cos_a: object
    sin_a: object
    far: object
    level_offset: object
    level_offset_host: np.ndarray
    level_width: object
    level_height: object
    block_start: object
    slot_ray: object
    sphere_c: object
    sphere_r: object
    n_slots: int
    levels: int
    level_sizes: list
    abs_tol: np.float32

    def nodes(self):
        """The node arrays in the order the twins take them (centre, radius, axis, cos_a, sin_a, far)."""
        return self.centre, self.radius, self.axis, self.cos_a, self.sin_a, self.far

    def layout(self):
        """(block_start, level_width, level_height): what ``child_grid`` reads."""
        return self.block_start, self.level_width, self.level_height


@cuda.jit(device=True)
def _block_of(p, width, block_width):
    """The 2x2 pixel block of pixel p on a screen ``width`` wide."""
    return (p // width // 2) * block_width + (p % width) // 2


@cuda.jit
def _count_blocks(pixel, tmin, tmax, n, width, n_pixels, block_width, block_count, bad_pixel):
    """Live rays (pixel >= 0, tmin <= tmax) counted per block; a pixel outside the screen goes
    to bad_pixel[0] (atomic max) instead."""
    r = cuda.grid(1)
    if r < n and pixel[r] >= 0 and tmin[r] <= tmax[r]:
        p = pixel[r]
        if p >= n_pixels:
            cuda.atomic.max(bad_pixel, 0, p)
        else:
            cuda.atomic.add(block_count, _block_of(p, width, block_width), 1)


@cuda.jit
def _fill_slots(pixel, tmin, tmax, n, width, block_width, block_start, fill, slot_ray):
    """slot_ray[block_start[b] + k] = r for the k-th live ray of block b to arrive."""
    r = cuda.grid(1)
    if r < n and pixel[r] >= 0 and tmin[r] <= tmax[r]:
        b = _block_of(pixel[r], width, block_width)
        slot_ray[block_start[b] + cuda.atomic.add(fill, b, 1)] = r


@cuda.jit
def _order_blocks(block_start, n_blocks, slot_ray):
    """Insertion sort of each block's slots by ray id (blocks hold a few rays per pixel)."""
    b = cuda.grid(1)
    if b < n_blocks:
        lo = block_start[b]
        for i in range(lo + 1, block_start[b + 1]):
            ray = slot_ray[i]
            j = i - 1
            while j >= lo and slot_ray[j] > ray:
                slot_ray[j + 1] = slot_ray[j]
                j -= 1
            slot_ray[j + 1] = ray


@cuda.jit
def _leaves(centre, radius, axis, alpha, cos_a, sin_a, far, slot_ray, n_slots, org, dirs, tmin, tmax,
            reverse, ax, ay, az):
    """Level-0 nodes. Reversed (leaving a) only for bounded segments: an unbounded one has no
    far end to start from, and a forward leaf in a reversed hierarchy is still exact."""
    s = cuda.grid(1)
    if s < n_slots:
        r = slot_ray[s]
        turn = reverse and math.isfinite(tmin[r]) and math.isfinite(tmax[r])
        _leaf_node(centre, radius, axis, alpha, cos_a, sin_a, far, slot_ray, s, org, dirs, tmin, tmax, turn,
                   ax, ay, az)


@cuda.jit
def _inner(centre, radius, axis, alpha, cos_a, sin_a, far, level_offset, block_start, level_width, level_height,
           level, count):
    """Every node of ``level`` >= 1 (``count`` of them) from its children."""
    local = cuda.grid(1)
    if local < count:
        _merge_node(centre, radius, axis, alpha, cos_a, sin_a, far, level_offset, block_start, level_width,
                    level_height, level_offset[level] + local, level, local)


@cuda.jit
def _spheres(v0, v1, v2, count, centre, radius, scale):
    """Triangle spheres; scale[1] = max |centre component|, scale[2] = max radius."""
    shared = cuda.shared.array(2, np.float32)
    if cuda.threadIdx.x == 0:
        shared[0] = 0
        shared[1] = 0
    cuda.syncthreads()
    i = cuda.grid(1)
    if i < count:
        _store_sphere(v0, v1, v2, i, centre, radius)
        cuda.atomic.max(shared, 0, max(abs(centre[i, 0]), abs(centre[i, 1]), abs(centre[i, 2])))
        cuda.atomic.max(shared, 1, radius[i])
    cuda.syncthreads()
    if cuda.threadIdx.x == 0:
        cuda.atomic.max(scale, 1, shared[0])
        cuda.atomic.max(scale, 2, shared[1])


@cuda.jit
def _node_scale(centre, radius, count, scale):
    """scale[0] = max |centre component| over the non-empty nodes."""
    shared = cuda.shared.array(1, np.float32)
    if cuda.threadIdx.x == 0:
        shared[0] = 0
    cuda.syncthreads()
    i = cuda.grid(1)
    if i < count and radius[i] >= 0:
        cuda.atomic.max(shared, 0, max(abs(centre[i, 0]), abs(centre[i, 1]), abs(centre[i, 2])))
    cuda.syncthreads()
    if cuda.threadIdx.x == 0:
        cuda.atomic.max(scale, 0, shared[0])


def _uploaded(scratch: Scratch, name: str, host: np.ndarray):
    """``host`` (1-d) copied into the scratch array ``name``: the same view for the same length."""
    view = scratch.get(name, host.shape[0], host.dtype)
    view.copy_to_device(np.ascontiguousarray(host))
    return view


def build(scratch: Scratch, scanner: Scanner, tris, org, dirs, tmin, tmax, pixel, n: int, width: int,
          height: int, light=None) -> DeviceHierarchy:
    """The hierarchy over rays 0 .. n-1 (device org, dirs f32[C,3]; tmin, tmax f32[C]; pixel i32[C]
    = y * width + x, -1 or tmax < tmin = dead) and the spheres of ``tris`` (DeviceTriangles).

    light: None, or the point (3 floats) every ray aims at: the leaves are then the segments
    reversed to leave it (stored as float32, as on the CPU). A pixel outside the screen of a live
    ray raises ValueError, as the CPU build does.
    """
    widths, heights, levels = level_grid(width, height)
    n_blocks = int(widths[1] * heights[1])
    block_count = scratch.get("block_count", n_blocks, np.int32)
    fill = scratch.get("block_fill", n_blocks, np.int32)
    bad = scratch.get("bad_pixel", 1, np.int32)
    launch = scratch.launch
    launch(fill_array, blocks(n_blocks), BLOCK, block_count, n_blocks, 0)
    launch(fill_array, blocks(n_blocks), BLOCK, fill, n_blocks, 0)
    launch(fill_array, 1, BLOCK, bad, 1, -1)
    launch(_count_blocks, blocks(n), BLOCK, pixel, tmin, tmax, n, width, width * height, int(widths[1]), block_count,
           bad)
    block_start = scratch.get("block_start", n_blocks + 1, np.int32)
    n_slots = scanner.exclusive_scan(block_count, n_blocks, block_start)
    worst = int(bad.copy_to_host()[0])
    if worst >= 0:
        raise ValueError(f"ray pixel {worst} is outside the {width}x{height} screen grid")
    slot_ray = scratch.get("slot_ray", n_slots, np.int32)
    if n_slots:
        launch(_fill_slots, blocks(n), BLOCK, pixel, tmin, tmax, n, width, int(widths[1]), block_start, fill, slot_ray)
        launch(_order_blocks, blocks(n_blocks), BLOCK, block_start, n_blocks, slot_ray)

    sizes = [n_slots] + [int(w * h) for w, h in zip(widths[1:], heights[1:])]
    level_offset = np.zeros(levels + 2, np.int64)
    np.cumsum(sizes, out=level_offset[1:])
    widths[0], heights[0] = n_slots, 1
    m = int(level_offset[-1])
    f32 = np.float32
    h = DeviceHierarchy(
        scratch.get("centre", m, f32, 3), scratch.get("radius", m, f32), scratch.get("axis", m, f32, 3),
        scratch.get("alpha", m, f32), scratch.get("cos_a", m, f32), scratch.get("sin_a", m, f32),
        scratch.get("far", m, f32), _uploaded(scratch, "level_offset", level_offset), level_offset,
        _uploaded(scratch, "level_width", widths), _uploaded(scratch, "level_height", heights), block_start, slot_ray, scratch.get("sphere_c", tris.count, f32, 3),
        scratch.get("sphere_r", tris.count, f32), n_slots, int(levels), sizes, np.float32(0))
    node_arrays = (h.centre, h.radius, h.axis, h.alpha, h.cos_a, h.sin_a, h.far)
    if n_slots:
        # The light as the CPU stores a shared apex: a float32 point, used in float64.
        a = np.zeros(3) if light is None else np.asarray(light, np.float32).astype(np.float64)
        launch(_leaves, blocks(n_slots), BLOCK, *node_arrays, slot_ray, n_slots, org, dirs, tmin, tmax,
               light is not None, float(a[0]), float(a[1]), float(a[2]))
    for level in range(1, levels + 1):
        launch(_inner, blocks(sizes[level]), BLOCK, *node_arrays, h.level_offset, block_start, h.level_width,
               h.level_height, level, sizes[level])

    scale = scratch.get("scale", 3, f32)
    scale.copy_to_device(np.zeros(3, f32))
    launch(_node_scale, blocks(m), BLOCK, h.centre, h.radius, m, scale)
    if tris.count:
        launch(_spheres, blocks(tris.count), BLOCK, tris.v0, tris.v1, tris.v2, tris.count, h.sphere_c, h.sphere_r,
               scale)
    s = scale.copy_to_host()
    # As ``absolute_slack``: the spheres' bound is a float32 sum, the product float64.
    h.abs_tol = np.float32(float(TEST_SLACK) * max(float(s[0]), float(s[1] + s[2])))
    return h
