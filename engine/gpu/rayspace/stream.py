"""The (node, triangle) pair stream on the device, one level at a time from the root down.

A stream is ``nodes: i32[P]`` (index within the level) and ``tris: i32[P]``. One step from
parents at ``level`` to their children at ``level - 1`` is a stream compaction:

1. ``_count_children`` (one thread per pair): every child of the pair's node against the
   triangle's bounding sphere (``node_overlap``'s twin: the CPU's conservative test); the
   survivor count per pair, the survivors' bit mask (up to 63 children), and per CUDA block
   the child slots, tests and survivors summed in shared memory, one global atomic each;
2. the host reads the survivor total (int64: nothing can wrap) and refuses a step that would
   exceed the pair budget before anything is scanned or written;
3. the stable exclusive scan of the counts (``engine.gpu.scan``) gives each pair its output
   position;
4. ``_scatter_children`` (per pair): the survivors written there in child order (a level-1
   node with more than 63 slots re-runs the test instead of reading the mask).

The output keeps the input order, so a stream that starts sorted by triangle stays so, and
every level is the CPU's ``engine.rayspace.pair_stream.expand`` to the pair.
"""
from __future__ import annotations

import numpy as np

from engine.gpu.device import BLOCK, blocks, require_cuda
from engine.gpu.rayspace.hierarchy import child_grid, node_overlap

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
def _count_children(nodes, tris, n_pairs, level, base, centre, radius, axis, cos_a, sin_a, far, block_start,
                    level_width, level_height, sphere_c, sphere_r, abs_tol, counts, masks, work, step_kept):
    """Phase 1 for parents at ``level`` >= 1 (their children start at global node ``base``):
    counts[p] survivors, masks[p] their bits; work[level-1, :] += (child slots, tests, survivors);
    step_kept[0] += survivors."""
    shared = cuda.shared.array(3, np.int64)
    t = cuda.threadIdx.x
    if t < 3:
        shared[t] = 0
    cuda.syncthreads()
    p = cuda.grid(1)
    if p < n_pairs:
        tri = tris[p]
        sx, sy, sz, rho = sphere_c[tri, 0], sphere_c[tri, 1], sphere_c[tri, 2], sphere_r[tri]
        first, nx, ny, stride = child_grid(block_start, level_width, level_height, level, nodes[p])
        kept = 0
        tests = 0
        bits = np.int64(0)
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
        counts[p] = kept
        masks[p] = bits
        cuda.atomic.add(shared, WORK_SLOTS, nx * ny)
        cuda.atomic.add(shared, WORK_TESTS, tests)
        cuda.atomic.add(shared, WORK_KEPT, kept)
    cuda.syncthreads()
    if t < 3 and shared[t] != 0:
        cuda.atomic.add(work, (level - 1, t), shared[t])
        if t == WORK_KEPT:
            cuda.atomic.add(step_kept, 0, shared[t])


@cuda.jit
def _scatter_children(nodes, tris, n_pairs, level, base, centre, radius, axis, cos_a, sin_a, far, block_start,
                      level_width, level_height, sphere_c, sphere_r, abs_tol, masks, offsets, out_nodes, out_tris):
    """Phase 4: pair p's surviving children (indices within level - 1) at offsets[p] on."""
    p = cuda.grid(1)
    if p < n_pairs:
        pos = offsets[p]
        if offsets[p + 1] == pos:
            return
        tri = tris[p]
        first, nx, ny, stride = child_grid(block_start, level_width, level_height, level, nodes[p])
        bits = masks[p]
        retest = nx * ny > MASK_BITS
        j = 0
        for jy in range(ny):
            row = first + jy * stride
            for jx in range(nx):
                if retest:
                    keep = node_overlap(centre, radius, axis, cos_a, sin_a, far, base + row + jx, sphere_c[tri, 0],
                                        sphere_c[tri, 1], sphere_c[tri, 2], sphere_r[tri], abs_tol)
                else:
                    keep = ((bits >> j) & 1) == 1
                if keep:
                    out_nodes[pos] = row + jx
                    out_tris[pos] = tri
                    pos += 1
                j += 1


class Stream:
    """Walks triangle batches down a DeviceHierarchy with scratch buffers of its own."""

    def __init__(self, scratch, scanner):
        self.scratch = scratch
        self.scanner = scanner

    def _pairs(self, side: str, rows: int):
        return (self.scratch.get(f"nodes_{side}", rows, np.int32), self.scratch.get(f"tris_{side}", rows, np.int32))

    def descend(self, h, first: int, last: int, budget: int, work, pairs_after: list):
        """Stream triangles first .. last-1 from the root to the slots.

        work: device i64[levels+1, 3] (see ``_count_children``); pairs_after: host list by level,
        added to. Returns (slots i32[P], tris i32[P], P, None, peak) with the final pairs (device
        views, valid until the next call), or (None, None, 0, (level, pairs needed), peak) as soon
        as a level would exceed ``budget``.
        """
        count = last - first
        nodes, tris = self._pairs("a", count)
        _root_pairs[blocks(count), BLOCK](first, count, nodes, tris)
        pairs_after[h.levels] += count
        peak = count
        step_kept = self.scratch.get("step_kept", 1, np.int64)
        zero = np.zeros(1, np.int64)
        side = "b"
        for level in range(h.levels, 0, -1):
            if count == 0:
                break
            counts = self.scratch.get("counts", count, np.int32)
            masks = self.scratch.get("masks", count, np.int64)
            step_kept.copy_to_device(zero)
            base = int(h.level_offset_host[level - 1])
            geometry = (level, base, *h.nodes(), *h.layout(), h.sphere_c, h.sphere_r, h.abs_tol)
            _count_children[blocks(count), BLOCK](nodes, tris, count, *geometry, counts, masks, work, step_kept)
            kept = int(step_kept.copy_to_host()[0])
            if kept > budget:
                return None, None, 0, (level - 1, kept), peak
            offsets = self.scratch.get("offsets", count + 1, np.int32)
            self.scanner.exclusive_scan(counts, count, offsets)
            out_nodes, out_tris = self._pairs(side, kept)
            if kept:
                _scatter_children[blocks(count), BLOCK](nodes, tris, count, *geometry, masks, offsets, out_nodes,
                                                        out_tris)
            pairs_after[level - 1] += kept
            peak = max(peak, kept)
            nodes, tris, count = out_nodes, out_tris, kept
            side = "a" if side == "b" else "b"
        return nodes, tris, count, None, peak
