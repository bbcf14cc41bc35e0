"""The stream of (node, triangle) pairs of the ray-space traversal, and its compaction.

A stream is two aligned arrays, ``node: i32[P]`` (a node's index within its level) and
``tri: i32[P]``. One step down the hierarchy replaces every pair (parent, tri) by the pairs
(child, tri) that pass the cone-sphere test, in the three phases of a GPU stream compaction,
each over fixed blocks of pairs:

1. count (prange over blocks): test each pair's children, keep a bit mask per pair and a
   survivor count per block;
2. exclusive scan of the block counts: each block's first output position;
3. scatter (prange over blocks): write the survivors at those positions.

The output keeps the input order, so a stream that starts sorted by triangle stays so.
The caller learns the output size after phase 1 and can refuse it (memory budget) before
anything is allocated. ``group_by_slot`` turns the last stream into per-ray candidate lists.
"""
from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from engine.rayspace.cone_sphere import children, cone_sphere_overlap

BLOCK = 2048      # pairs per prange task
MASK_BITS = 63    # children per pair a bit mask can remember (int64, sign bit unused)


class StepReport(NamedTuple):
    """What one level step did.

    slots: child slots before compaction (input pairs x their in-grid children, empty ones too);
    tests: cone-sphere tests run (non-empty children); survivors: pairs after compaction;
    count_seconds, compact_seconds: wall time of phase 1 and of phases 2-3.
    """

    slots: int
    tests: int
    survivors: int
    count_seconds: float
    compact_seconds: float


def root_stream(first: int, last: int) -> tuple[np.ndarray, np.ndarray]:
    """(node i32[n], tri i32[n]): triangles first .. last-1 paired with the root (index 0)."""
    return np.zeros(last - first, np.int32), np.arange(first, last, dtype=np.int32)


@njit(cache=True, parallel=True)
def _count(h, level, nodes, tris, sphere_c, sphere_r, abs_tol, use_mask, masks, block_counts,
           block_tests, block_slots):
    """Phase 1 for parents at ``level`` >= 1: per-pair child masks i64[P], per-block counts."""
    n_pairs = nodes.shape[0]
    base = h.level_offset[level - 1]
    for b in prange(block_counts.shape[0]):
        kept = 0
        tests = 0
        slots = 0
        for p in range(b * BLOCK, min(n_pairs, (b + 1) * BLOCK)):
            parent = nodes[p]
            tri = tris[p]
            sx, sy, sz, rho = sphere_c[tri, 0], sphere_c[tri, 1], sphere_c[tri, 2], sphere_r[tri]
            first, nx, ny, stride = children(h, level, parent)
            slots += nx * ny
            bits = 0
            j = 0
            for jy in range(ny):
                row = base + first + jy * stride
                for jx in range(nx):
                    # Counted without branches: the outcome is unpredictable.
                    tests += h.radius[row + jx] >= 0  # an empty node is no test (and fails)
                    hit = cone_sphere_overlap(h, row + jx, sx, sy, sz, rho, abs_tol)
                    kept += hit
                    if j < MASK_BITS:  # always true when masks are used
                        bits |= np.int64(hit) << j
                    j += 1
            if use_mask:
                masks[p] = bits  # (bits past MASK_BITS are never read)
        block_counts[b] = kept
        block_tests[b] = tests
        block_slots[b] = slots


@njit(cache=True)
def exclusive_scan(counts):
    """i64[n] -> i64[n+1]: out[i] = sum(counts[:i]); out[n] is the total."""
    out = np.empty(counts.shape[0] + 1, np.int64)
    total = 0
    for i in range(counts.shape[0]):
        out[i] = total
        total += counts[i]
    out[counts.shape[0]] = total
    return out


@njit(cache=True, parallel=True)
def _scatter(h, level, nodes, tris, sphere_c, sphere_r, abs_tol, use_mask, masks, offsets,
             out_nodes, out_tris):
    """Phase 3: survivors of each block written from offsets[block] on, in input order.

    Without masks (a level-1 block with more rays than MASK_BITS) the tests are re-run.
    """
    n_pairs = nodes.shape[0]
    base = h.level_offset[level - 1]
    for b in prange(offsets.shape[0] - 1):
        pos = offsets[b]
        for p in range(b * BLOCK, min(n_pairs, (b + 1) * BLOCK)):
            parent = nodes[p]
            tri = tris[p]
            if use_mask and masks[p] == 0:
                continue
            first, nx, ny, stride = children(h, level, parent)
            j = 0
            for jy in range(ny):
                row = first + jy * stride
                for jx in range(nx):
                    if use_mask:
                        keep = ((masks[p] >> j) & 1) == 1
                    else:
                        keep = cone_sphere_overlap(
                            h, base + row + jx, sphere_c[tri, 0], sphere_c[tri, 1], sphere_c[tri, 2],
                            sphere_r[tri], abs_tol)
                    if keep:
                        out_nodes[pos] = row + jx
                        out_tris[pos] = tri
                        pos += 1
                    j += 1


def expand(h, level: int, nodes, tris, sphere_c, sphere_r, abs_tol: float, capacity: int):
    """One step from parents at ``level`` >= 1 to their children at ``level - 1``.

    nodes, tris: i32[P] the input stream; sphere_c f32[T,3], sphere_r f32[T]: triangle
    spheres. Returns (out_nodes, out_tris, report); when the output would exceed ``capacity``
    pairs, nothing is written and out_nodes, out_tris are None (report.survivors says how
    many pairs it would have taken).
    """
    start = time.perf_counter()
    n_blocks = -(-nodes.shape[0] // BLOCK)
    use_mask = level >= 2 or h.max_block_rays <= MASK_BITS
    masks = np.empty(nodes.shape[0] if use_mask else 0, np.int64)
    block_counts = np.empty(n_blocks, np.int64)
    block_tests = np.empty(n_blocks, np.int64)
    block_slots = np.empty(n_blocks, np.int64)
    _count(h, level, nodes, tris, sphere_c, sphere_r, np.float32(abs_tol), use_mask, masks,
           block_counts, block_tests, block_slots)
    counted = time.perf_counter()
    offsets = exclusive_scan(block_counts)
    total = int(offsets[-1])
    report = StepReport(int(block_slots.sum()), int(block_tests.sum()), total, counted - start, 0.0)
    if total > capacity:
        return None, None, report
    out_nodes = np.empty(total, np.int32)
    out_tris = np.empty(total, np.int32)
    _scatter(h, level, nodes, tris, sphere_c, sphere_r, np.float32(abs_tol), use_mask, masks, offsets,
             out_nodes, out_tris)
    return out_nodes, out_tris, report._replace(compact_seconds=time.perf_counter() - counted)


@njit(cache=True)
def group_by_slot(slots, tris, n_slots):
    """Counting sort of the final (slot, tri) stream by slot (stable).

    slots, tris: i32[P]. Returns (start i64[n_slots+1], cand i32[P]): the candidate triangles
    of slot s are cand[start[s] : start[s+1]], in stream (triangle) order.
    """
    start = np.zeros(n_slots + 1, np.int64)
    for p in range(slots.shape[0]):
        start[slots[p] + 1] += 1
    for s in range(n_slots):
        start[s + 1] += start[s]
    fill = start[:-1].copy()
    cand = np.empty(tris.shape[0], np.int32)
    for p in range(slots.shape[0]):
        s = slots[p]
        cand[fill[s]] = tris[p]
        fill[s] += 1
    return start, cand
