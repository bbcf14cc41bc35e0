"""Parallel query kernels over rays.

Every kernel takes the 8-wide tree's packed nodes and their int32 view
(``engine.query.wide.pack_nodes``, leaf slots pointing at blocks) and the leaves' triangles in blocks of four (blocks f32[G,10,4] and block_tri, their
int32 view: ``engine.query.leaf_blocks``), the world rays origins, directions
(f64[n,3], any direction length) with the mesh frame's center (f64[3]) and scale, and
``rows`` (i64[n]): row k walks input ray rows[k] (``order.ray_order``, or 0..n-1). Each ray is
moved into the local frame as it is walked (``frame.local_ray``), so no float32 copy of the
batch is made; a bad ray is a miss with ok[ray] False. Threads take contiguous chunks of rows.

The parallel kernels move the next ray into the local frame before walking the current one.
That step is a square root and divisions in double, about 40 cycles of latency, and a walk
cannot start before it ends; computed a ray ahead it runs while the current ray's first nodes
load (the out-of-order core does not look that far ahead across a walk's loop by itself).
Incoherent first hits, 200k rays, one thread, medians of 15 in one process: kitchen 27.0 -> 24.9
ms, bunny 65-73 -> 62-69 ms; the same answers. A float32 local copy of the rays made beforehand
walked in 23.5 ms on the kitchen, but costs a pass of its own.

- ``first_hit_kernel``: closest (or any) hit per ray.
- ``collect_hits_kernel``: every hit per ray in one walk, into per-thread scratch, sorted by
  distance, merged where one crossing reported two triangles, cut to ``max_hits`` and kept in a
  fixed slot of ``slot`` hits per row; a ray with more (rare) is marked for the path below.
- ``count_hits_kernel`` then ``fill_hits_kernel``: the same for any number of hits: counted,
  then written into exact slices (serial: waking threads costs more than these few rays).
- ``compact_hits_kernel``: the kept hits of all rays in ray order, as flat arrays.
"""
import numpy as np
from numba import njit, prange

from engine.query.frame import local_ray
from engine.query.walk import ANY, CLOSEST, COLLECT, merge_crossings, new_hit_buffers, new_stack, sort_hits, walk

CHUNK = 256  # rays per prange task: one stack allocation per chunk

#: Raw hits one walk may collect in scratch before its ray goes to the count-then-fill path.
SCRATCH = 256

F32_ZERO, F32_INF = np.float32(0.0), np.float32(np.inf)


@njit(cache=True, parallel=True)
def first_hit_kernel(nodes, node_bits, block_tri, blocks, origins, directions, center, scale, rows,
                     any_hit, out_tri, out_u, out_v, ok):
    """out_tri (i64[n], -1 = miss), out_u, out_v (f32[n]: barycentrics) of the closest hit
    (any_hit False) or of some hit (any_hit True) of every ray on [0, inf), by input ray;
    ok (bool[n]): the ray was well formed."""
    n = rows.shape[0]
    empty_t = np.empty(0, np.float32)
    empty_i = np.empty(0, np.int32)
    mode = ANY if any_hit else CLOSEST
    for c in prange((n + CHUNK - 1) // CHUNK):
        stack, stack_t, entries, answers = new_stack()
        end = min(n, (c + 1) * CHUNK)
        ahead = local_ray(origins, directions, rows[c * CHUNK], center, scale)
        for k in range(c * CHUNK, end):
            r = rows[k]
            out_tri[r] = -1
            out_u[r] = 0
            out_v[r] = 0
            good, ox, oy, oz, dx, dy, dz = ahead
            if k + 1 < end:  # the next ray, a step ahead (see the module doc)
                ahead = local_ray(origins, directions, rows[k + 1], center, scale)
            ok[r] = good
            if not good:
                continue
            hit, t, tri, u, v = walk(nodes, node_bits, block_tri, blocks, ox, oy, oz, dx, dy, dz,
                                     F32_ZERO, F32_INF, mode, stack, stack_t, entries, answers,
                                     empty_t, empty_i, empty_t, empty_t, 0)
            if hit:
                out_tri[r] = tri
                out_u[r] = u
                out_v[r] = v


@njit(cache=True, parallel=True)
def collect_hits_kernel(nodes, node_bits, block_tri, blocks, origins, directions, center, scale, rows,
                        gap, max_hits, slot, out_t, out_tri, out_u, out_v, kept, ok):
    """Row k's hits, sorted by (t, triangle), merged within ``gap`` and cut to max_hits, go to
    out_*[k * slot : k * slot + kept[k]] (out_t, out_u, out_v f32[n * slot], out_tri i32[n * slot]);
    kept[k] = -1 when they do not fit (more than SCRATCH raw hits or ``slot`` kept ones).
    ok (bool[n], by input ray): the ray was well formed."""
    n = rows.shape[0]
    for c in prange((n + CHUNK - 1) // CHUNK):
        stack, stack_t, entries, answers = new_stack()
        st, stri, su, sv = new_hit_buffers(SCRATCH)
        end = min(n, (c + 1) * CHUNK)
        ahead = local_ray(origins, directions, rows[c * CHUNK], center, scale)
        for k in range(c * CHUNK, end):
            kept[k] = 0
            r = rows[k]
            good, ox, oy, oz, dx, dy, dz = ahead
            if k + 1 < end:  # the next ray, a step ahead (see the module doc)
                ahead = local_ray(origins, directions, rows[k + 1], center, scale)
            ok[r] = good
            if not good:
                continue
            found, _, _, _, _ = walk(nodes, node_bits, block_tri, blocks, ox, oy, oz, dx, dy, dz,
                                     F32_ZERO, F32_INF, COLLECT, stack, stack_t, entries, answers,
                                     st, stri, su, sv, SCRATCH)
            if found > SCRATCH:
                kept[k] = -1
                continue
            sort_hits(st, stri, su, sv, found)
            m = min(merge_crossings(st, stri, su, sv, found, gap), max_hits)
            if m > slot:
                kept[k] = -1
                continue
            kept[k] = m
            for j in range(m):
                out_t[k * slot + j] = st[j]
                out_tri[k * slot + j] = stri[j]
                out_u[k * slot + j] = su[j]
                out_v[k * slot + j] = sv[j]


@njit(cache=True)  # serial: only the rare rays with many hits come here
def count_hits_kernel(nodes, node_bits, block_tri, blocks, origins, directions, center, scale, rows,
                      counts):
    """counts (i64[n]): how many triangles the ray of each row hits on [0, inf), before merging
    (rows: well-formed rays only)."""
    n = rows.shape[0]
    empty_t = np.empty(0, np.float32)
    empty_i = np.empty(0, np.int32)
    for c in range((n + CHUNK - 1) // CHUNK):
        stack, stack_t, entries, answers = new_stack()
        for k in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            _, ox, oy, oz, dx, dy, dz = local_ray(origins, directions, rows[k], center, scale)
            counts[k], _, _, _, _ = walk(nodes, node_bits, block_tri, blocks, ox, oy, oz, dx, dy, dz,
                                         F32_ZERO, F32_INF, COLLECT, stack, stack_t, entries, answers,
                                         empty_t, empty_i, empty_t, empty_t, 0)


@njit(cache=True)  # serial: only the rare rays with many hits come here
def fill_hits_kernel(nodes, node_bits, block_tri, blocks, origins, directions, center, scale, rows,
                     offsets, gap, max_hits, buf_t, buf_tri, buf_u, buf_v, kept):
    """Row k's hits go to slice offsets[k] : offsets[k + 1] of buf_t, buf_tri, buf_u, buf_v
    (sized by ``count_hits_kernel``), sorted by (t, triangle), merged within ``gap`` (local
    units) and cut to max_hits; kept (i64[n]) is how many of them are real."""
    n = rows.shape[0]
    for c in range((n + CHUNK - 1) // CHUNK):
        stack, stack_t, entries, answers = new_stack()
        for k in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            kept[k] = 0
            lo, hi = offsets[k], offsets[k + 1]
            if hi == lo:
                continue
            _, ox, oy, oz, dx, dy, dz = local_ray(origins, directions, rows[k], center, scale)
            st, stri, su, sv = buf_t[lo:hi], buf_tri[lo:hi], buf_u[lo:hi], buf_v[lo:hi]
            found, _, _, _, _ = walk(nodes, node_bits, block_tri, blocks, ox, oy, oz, dx, dy, dz,
                                     F32_ZERO, F32_INF, COLLECT, stack, stack_t, entries, answers,
                                     st, stri, su, sv, hi - lo)
            found = min(found, hi - lo)
            sort_hits(st, stri, su, sv, found)
            kept[k] = min(merge_crossings(st, stri, su, sv, found, gap), max_hits)


@njit(cache=True)
def compact_hits_kernel(offsets, kept, rank, out_offsets, buf_t, buf_tri, buf_u, buf_v,
                        index_ray, index_tri, t, u, v):
    """Copy input ray r's kept hits (row k = rank[r]: buf_*[offsets[k] : offsets[k] + kept[k]])
    to the flat answers at out_offsets[r] (exclusive prefix sum over input rays of kept[rank[r]]):
    index_ray, index_tri (i64[m]), t, u, v (f32[m]), so the answers come in input ray order.
    Serial: a copy, not worth waking threads for."""
    for r in range(rank.shape[0]):
        k = rank[r]
        src = offsets[k]
        dst = out_offsets[r]
        for j in range(kept[k]):
            index_ray[dst + j] = r
            index_tri[dst + j] = buf_tri[src + j]
            t[dst + j] = buf_t[src + j]
            u[dst + j] = buf_u[src + j]
            v[dst + j] = buf_v[src + j]
