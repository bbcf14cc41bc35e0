"""The (node, triangle) pair stream on the device, one level at a time from the root down.

A stream is ``nodes: i32[P]`` (index within the level) and ``tris: i32[P]``. One step from
parents at ``level`` to their children at ``level - 1`` is one launch of ``_expand``, a stream
compaction by appending:

1. every thread takes a pair and tests every child of its node against the triangle's bounding
   sphere (``node_overlap``'s twin: the CPU's conservative test), remembering the survivors as
   bits (up to 63 children; a level-1 node with more slots re-tests them when writing);
2. the block's survivor counts are scanned in shared memory, one thread reserves the block's
   share of the output by a single atomic add on the level's counter, and every thread writes
   its survivors there -- only those that fit the output's capacity;
3. the host reads the level's counter (int64: nothing can wrap). More than the pair budget stops
   the descent (the caller splits the triangles); more than the capacity but within the budget
   grows the buffers and repeats the level (the counter is exact either way).

One launch and one read-back per level: no global scan, no second pass over the pairs. The
output is in no particular order -- the final tests reduce per ray by atomic minima, which do
not depend on it -- but it holds exactly the pairs of the CPU's
``engine.rayspace.pair_stream.expand``, and the per-level counts are the CPU plugin's.
"""
from __future__ import annotations

import numpy as np

from engine.gpu.device import BLOCK, blocks, require_cuda
from engine.gpu.rayspace.hierarchy import child_grid, node_overlap
from engine.gpu.scan import inclusive_in_block

cuda = require_cuda()

MASK_BITS = 63    # children a pair's int64 mask remembers (sign bit unused)
#: Columns of the per-level work counters i64[levels+1, 3].
WORK_SLOTS, WORK_TESTS, WORK_KEPT = 0, 1, 2


@cuda.jit
def _root_pairs(first, count, nodes, tris):
    """Triangles first .. first+count-1 paired with the root (node 0 of the top level)."""
    p = cuda.grid(1)
    if p < count:
        nodes[p] = 0
        tris[p] = first + p


@cuda.jit
def _expand(nodes, tris, n_pairs, level, base, centre, radius, axis, cos_a, sin_a, far, block_start, level_width,
            level_height, sphere_c, sphere_r, abs_tol, out_nodes, out_tris, capacity, work, level_kept):
    """Pairs at ``level`` >= 1 (their children start at global node ``base``) to the surviving
    (child, triangle) pairs, appended to out_nodes / out_tris (children as indices within
    level - 1) up to ``capacity`` rows; level_kept[level - 1] += survivors (all of them, written
    or not); work[level - 1, :] += (child slots, tests, survivors)."""
    ahead = cuda.shared.array(BLOCK, np.int32)   # survivors per thread, then their inclusive sums
    sums = cuda.shared.array(3, np.int32)         # int32: native shared atomics (int64 ones loop)
    start = cuda.shared.array(1, np.int64)
    t = cuda.threadIdx.x
    if t < 3:
        sums[t] = 0
    cuda.syncthreads()
    p = cuda.grid(1)
    kept = 0
    bits = np.int64(0)
    tri = 0
    first, nx, ny, stride = 0, 0, 0, 0
    sx, sy, sz, rho = np.float32(0), np.float32(0), np.float32(0), np.float32(0)
    if p < n_pairs:
        tri = tris[p]
        sx, sy, sz, rho = sphere_c[tri, 0], sphere_c[tri, 1], sphere_c[tri, 2], sphere_r[tri]
        first, nx, ny, stride = child_grid(block_start, level_width, level_height, level, nodes[p])
        tests = 0
        j = 0
        for jy in range(ny):
            row = base + first + jy * stride
            for jx in range(nx):
                if radius[row + jx] >= 0:  # an empty node is no test (and fails)
                    tests += 1
                    if node_overlap(centre, radius, axis, cos_a, sin_a, far, row + jx, sx, sy, sz, rho, abs_tol):
                        kept += 1
                        if j < MASK_BITS:
                            bits |= np.int64(1) << j
                j += 1
        cuda.atomic.add(sums, WORK_SLOTS, np.int32(nx * ny))
        cuda.atomic.add(sums, WORK_TESTS, np.int32(tests))
        cuda.atomic.add(sums, WORK_KEPT, np.int32(kept))
    ahead[t] = kept
    cuda.syncthreads()
    inclusive_in_block(ahead, t)
    if t == BLOCK - 1:
        start[0] = cuda.atomic.add(level_kept, level - 1, np.int64(ahead[t]))
    if t < 3 and sums[t] != 0:
        cuda.atomic.add(work, (level - 1, t), np.int64(sums[t]))
    cuda.syncthreads()
    if kept == 0:
        return
    pos = start[0] + ahead[t] - kept
    retest = nx * ny > MASK_BITS
    j = 0
    for jy in range(ny):
        row = first + jy * stride
        for jx in range(nx):
            if retest:
                keep = node_overlap(centre, radius, axis, cos_a, sin_a, far, base + row + jx, sx, sy, sz, rho, abs_tol)
            else:
                keep = ((bits >> j) & 1) == 1
            if keep:
                if pos < capacity:
                    out_nodes[pos] = row + jx
                    out_tris[pos] = tri
                pos += 1
            j += 1


class Stream:
    """Walks triangle batches down a DeviceHierarchy with scratch buffers of its own."""

    def __init__(self, scratch):
        self.scratch = scratch

    def _pairs(self, side: str, rows: int):
        return (self.scratch.get(f"nodes_{side}", rows, np.int32), self.scratch.get(f"tris_{side}", rows, np.int32))

    def descend(self, h, first: int, last: int, budget: int, work, pairs_after: list):
        """Stream triangles first .. last-1 from the root to the slots.

        work: device i64[levels+1, 3] (see ``_expand``); pairs_after: host list by level, added
        to. Returns (slots i32[P], tris i32[P], P, None, peak) with the final pairs (device
        views, valid until the next call), or (None, None, 0, (level, pairs needed), peak) as soon
        as a level would exceed ``budget``.
        """
        count = last - first
        nodes, tris = self._pairs("a", count)
        _root_pairs[blocks(count), BLOCK](first, count, nodes, tris)
        pairs_after[h.levels] += count
        peak = count
        level_kept = self.scratch.get("level_kept", h.levels + 1, np.int64)
        level_kept.copy_to_device(np.zeros(h.levels + 1, np.int64))
        side = "b"
        for level in range(h.levels, 0, -1):
            if count == 0:
                break
            base = int(h.level_offset_host[level - 1])
            geometry = (level, base, *h.nodes(), *h.layout(), h.sphere_c, h.sphere_r, h.abs_tol)
            # Whatever the side's buffers hold already (at least as many rows as this level's pairs).
            capacity = min(self.scratch.rows(f"nodes_{side}"), self.scratch.rows(f"tris_{side}"))
            if capacity < count:
                capacity = count
            out_nodes, out_tris = self._pairs(side, capacity)
            _expand[blocks(count), BLOCK](nodes, tris, count, *geometry, out_nodes, out_tris, capacity, work,
                                          level_kept)
            kept = int(level_kept[level - 1:level].copy_to_host()[0])
            if kept > budget:
                return None, None, 0, (level - 1, kept), peak
            if kept > capacity:
                # Grown once for this size; the level runs again (its work counted once).
                out_nodes, out_tris = self._pairs(side, kept)
                level_kept[level - 1:level].copy_to_device(np.zeros(1, np.int64))
                _expand[blocks(count), BLOCK](nodes, tris, count, *geometry, out_nodes, out_tris, kept,
                                              self._spare_work(work), level_kept)
            pairs_after[level - 1] += kept
            peak = max(peak, kept)
            nodes, tris, count = out_nodes[:kept], out_tris[:kept], kept
            side = "a" if side == "b" else "b"
        return nodes, tris, count, None, peak

    def _spare_work(self, work):
        """A work table that is discarded: a repeated level must not count its tests twice."""
        return self.scratch.get("spare_work", work.shape[0], np.int64, work.shape[1])
