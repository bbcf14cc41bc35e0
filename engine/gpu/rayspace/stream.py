"""The (node, triangle) pair stream on the device, one level at a time from the root down.

A stream is ``nodes: i32[P]`` (index within the level) and ``tris: i32[P]``. One step from
parents at ``level`` to their children at ``level - 1`` is one launch of ``_expand``, a stream
compaction by appending:

1. every thread takes a pair (blocks stride over the level's pairs, whose count the previous
   launch left on the device) and tests every child of its node against the triangle's bounding
   sphere (``node_overlap``'s twin: the CPU's conservative test), remembering the survivors as
   bits (up to 63 children; a level-1 node with more slots re-tests them when writing);
2. the block's survivor counts are scanned in shared memory, one thread reserves the block's
   share of the output by a single atomic add on the level's counter, and every thread writes
   its survivors there -- only those that fit the output's capacity;
3. the counters are int64 (nothing can wrap) and exact whether or not the pairs fit; the buffers
   hold the pair budget, and a launch whose input overflowed reads nothing.

One launch per level and one read-back per descent (the host learns the counts, and whether a
level exceeded the budget -- then the caller splits the triangles -- after the last level): no
global scan, no second pass over the pairs, no wait between levels. The
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
#: Blocks of one ``_expand`` launch at most (they stride over the pairs). Measured on the H100
#: (kitchen-paper rayspace frame, _expand per frame): 2048 blocks 134-138 ms, 16384 116 ms,
#: 131072 135 ms. The simulator's tests set it lower.
GRID_BLOCKS = 16384
#: Columns of the per-level work counters i64[levels+1, 3].
WORK_SLOTS, WORK_TESTS, WORK_KEPT = 0, 1, 2


@cuda.jit
def _root_pairs(first, count, nodes, tris):
    """Triangles first .. first+count-1 paired with the root (node 0 of the top level)."""
    p = cuda.grid(1)
    if p < count:
        nodes[p] = 0
        tris[p] = first + p


@cuda.jit(device=True)
def _block_total(shared, t, value):
    """The sum of ``value`` over the block's threads (every thread calls it; shared: i64[BLOCK])."""
    shared[t] = value
    cuda.syncthreads()
    inclusive_in_block(shared, t)
    total = shared[BLOCK - 1]
    cuda.syncthreads()
    return total


@cuda.jit
def _expand(nodes, tris, level, base, centre, radius, axis, cos_a, sin_a, far, block_start, level_width,
            level_height, sphere_c, sphere_r, abs_tol, out_nodes, out_tris, capacity, work, level_kept):
    """The level_kept[level] pairs at ``level`` >= 1 (their children start at global node
    ``base``) to the surviving (child, triangle) pairs, appended to out_nodes / out_tris (children
    as indices within level - 1) up to ``capacity`` rows; level_kept[level - 1] += survivors (all
    of them, written or not); work[level - 1, :] += (child slots, tests, survivors).

    Any grid: blocks stride over the pairs. An input that overflowed its buffer (more pairs
    than ``capacity``) is not read: the host sees the overflow and streams fewer triangles.
    """
    ahead = cuda.shared.array(BLOCK, np.int32)   # survivors per thread, then their inclusive sums
    totals = cuda.shared.array(BLOCK, np.int64)
    start = cuda.shared.array(1, np.int64)
    t = cuda.threadIdx.x
    n_pairs = level_kept[level]
    if n_pairs > capacity:
        return
    slots = 0
    tests = 0
    survivors = 0
    for block_first in range(cuda.blockIdx.x * BLOCK, n_pairs, cuda.gridDim.x * BLOCK):
        p = block_first + t
        kept = 0
        bits = np.int64(0)
        tri = 0
        first, nx, ny, stride = 0, 0, 0, 0
        sx, sy, sz, rho = np.float32(0), np.float32(0), np.float32(0), np.float32(0)
        if p < n_pairs:
            tri = tris[p]
            sx, sy, sz, rho = sphere_c[tri, 0], sphere_c[tri, 1], sphere_c[tri, 2], sphere_r[tri]
            first, nx, ny, stride = child_grid(block_start, level_width, level_height, level, nodes[p])
            slots += nx * ny
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
            survivors += kept
        ahead[t] = kept
        cuda.syncthreads()
        inclusive_in_block(ahead, t)
        if t == BLOCK - 1:
            start[0] = cuda.atomic.add(level_kept, level - 1, np.int64(ahead[t]))
        cuda.syncthreads()
        if kept > 0:
            pos = start[0] + ahead[t] - kept
            retest = nx * ny > MASK_BITS
            j = 0
            for jy in range(ny):
                row = first + jy * stride
                for jx in range(nx):
                    if retest:
                        keep = node_overlap(centre, radius, axis, cos_a, sin_a, far, base + row + jx, sx, sy, sz, rho,
                                            abs_tol)
                    else:
                        keep = ((bits >> j) & 1) == 1
                    if keep:
                        if pos < capacity:
                            out_nodes[pos] = row + jx
                            out_tris[pos] = tri
                        pos += 1
                    j += 1
        cuda.syncthreads()  # ahead and start are rewritten by the next stride
    # The work counters: one block reduction each, one global atomic per block.
    slots = _block_total(totals, t, np.int64(slots))
    tests = _block_total(totals, t, np.int64(tests))
    survivors = _block_total(totals, t, np.int64(survivors))
    if t == 0 and slots != 0:
        cuda.atomic.add(work, (level - 1, WORK_SLOTS), slots)
        cuda.atomic.add(work, (level - 1, WORK_TESTS), tests)
        cuda.atomic.add(work, (level - 1, WORK_KEPT), survivors)


class Stream:
    """Walks triangle batches down a DeviceHierarchy with scratch buffers of its own."""

    def __init__(self, scratch):
        self.scratch = scratch

    def _pairs(self, side: str, rows: int):
        return (self.scratch.get(f"nodes_{side}", rows, np.int32), self.scratch.get(f"tris_{side}", rows, np.int32))

    def descend(self, h, first: int, last: int, budget: int, work, pairs_after: list):
        """Stream triangles first .. last-1 from the root to the slots.

        Every level is launched without waiting: the pair counts stay on the device
        (``level_kept``) and are read back once, after the last level. Both pair buffers hold
        ``budget`` rows (or the batch's triangles, if more), so a level that would exceed the
        budget is found then, and the levels below it did nothing.

        work: device i64[levels+1, 3] (see ``_expand``); pairs_after: host list by level, added
        to. Returns (slots i32[P], tris i32[P], P, None, peak) with the final pairs (device
        views, valid until the next call), or (None, None, 0, (level, pairs needed), peak) for
        the first level that exceeds ``budget``.
        """
        count = last - first
        capacity = max(budget, count)
        source, target = self._pairs("a", capacity), self._pairs("b", capacity)
        launch = self.scratch.launch
        launch(_root_pairs, blocks(count), BLOCK, first, count, *source)
        level_kept = self.scratch.get("level_kept", h.levels + 1, np.int64)
        start = np.zeros(h.levels + 1, np.int64)
        start[h.levels] = count
        level_kept.copy_to_device(start)
        for level in range(h.levels, 0, -1):
            base = int(h.level_offset_host[level - 1])
            # At most every triangle against every node of the level, and no more than fit.
            most = min(capacity, count * int(h.level_sizes[level]))
            launch(_expand, min(GRID_BLOCKS, blocks(most)), BLOCK, *source, level, base, *h.nodes(), *h.layout(),
                   h.sphere_c, h.sphere_r, h.abs_tol, *target, capacity, work, level_kept)
            source, target = target, source
        kept = level_kept.copy_to_host()
        pairs_after[h.levels] += count
        peak = count
        for level in range(h.levels - 1, -1, -1):
            if kept[level] > budget:
                return None, None, 0, (level, int(kept[level])), peak
            pairs_after[level] += int(kept[level])
            peak = max(peak, int(kept[level]))
        final = int(kept[0])
        return self.scratch.prefix(source[0], final), self.scratch.prefix(source[1], final), final, None, peak
