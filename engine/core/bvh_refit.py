"""Refit: the same BVH topology with its boxes recomputed for moved triangles (animation).

The builder stores children after their parent, so nodes grouped by depth and visited deepest
level first see every child before its parent. Each level's nodes are independent, so a level
is one ``prange``: leaves take the bounds of their triangles' corners, inner nodes the union of
their two children. Boxes are then widened by the builder's pad (``BOX_PAD_SCALE`` times the
largest |coordinate|), so a refitted tree is exactly the tree the builder's boxes would give for
the same topology. Float32 minima and maxima are exact, so the result does not depend on the
thread count.
"""
from __future__ import annotations

import time

import numpy as np
from numba import njit, prange

from engine.core.bvh import BOX_PAD_SCALE, TRAVERSAL_COST
from engine.core.types import BVH, Triangles

#: Triangles per chunk of the parallel largest-|coordinate| reduction.
PAD_CHUNK = 8192


@njit(cache=True)
def refit_levels(first, count):
    """(level_start i32[L+1], level_nodes i32[N]): the nodes grouped by depth, root level 0;
    level d is ``level_nodes[level_start[d]:level_start[d + 1]]``. first, count: i32[N]."""
    n = first.shape[0]
    depth = np.zeros(n, np.int32)
    deepest = 0
    for node in range(n):                     # parents come before children
        if count[node] == 0:
            depth[first[node]] = depth[first[node] + 1] = depth[node] + 1
            deepest = max(deepest, depth[node] + 1)
    level_start = np.zeros(deepest + 2, np.int32)
    for node in range(n):
        level_start[depth[node] + 1] += 1
    for d in range(deepest + 1):
        level_start[d + 1] += level_start[d]
    fill = level_start[:-1].copy()
    level_nodes = np.empty(n, np.int32)
    for node in range(n):
        level_nodes[fill[depth[node]]] = node
        fill[depth[node]] += 1
    return level_start, level_nodes


@njit(cache=True, parallel=True)
def _largest_magnitude(v0, v1, v2):
    """max |coordinate| over every corner of f32[T,3] v0, v1, v2 (float32)."""
    t = v0.shape[0]
    chunks = (t + PAD_CHUNK - 1) // PAD_CHUNK
    partial = np.zeros(max(chunks, 1), np.float32)
    for c in prange(chunks):
        m = np.float32(0.0)
        for i in range(c * PAD_CHUNK, min(t, (c + 1) * PAD_CHUNK)):
            for a in range(3):
                m = max(m, abs(v0[i, a]), abs(v1[i, a]), abs(v2[i, a]))
        partial[c] = m
    return partial.max()


@njit(cache=True, parallel=True)
def _refit(bmin, bmax, first, count, prim, v0, v1, v2, level_start, level_nodes, pad):
    levels = level_start.shape[0] - 1
    for level in range(levels - 1, -1, -1):
        for j in prange(level_start[level], level_start[level + 1]):
            node = level_nodes[j]
            if count[node] > 0:
                for a in range(3):
                    lo = np.float32(np.inf)
                    hi = np.float32(-np.inf)
                    for i in range(first[node], first[node] + count[node]):
                        p = prim[i]
                        lo = min(lo, v0[p, a], v1[p, a], v2[p, a])
                        hi = max(hi, v0[p, a], v1[p, a], v2[p, a])
                    bmin[node, a] = lo
                    bmax[node, a] = hi
            else:
                left = first[node]
                for a in range(3):
                    bmin[node, a] = min(bmin[left, a], bmin[left + 1, a])
                    bmax[node, a] = max(bmax[left, a], bmax[left + 1, a])
    # Pad after the sweep: children's unpadded boxes make their parent's.
    for node in prange(bmin.shape[0]):
        for a in range(3):
            bmin[node, a] -= pad
            bmax[node, a] += pad


def refit_bvh(bvh: BVH, tris: Triangles, levels=None) -> BVH:
    """``bvh`` with its boxes recomputed for ``tris`` (the triangles it was built over, moved;
    same count and order). ``levels``: ``refit_levels(bvh.first, bvh.count)``, computed here
    when not given (keep it between frames: it depends on the topology only).
    ``build_seconds`` of the result is this refit's time."""
    start = time.perf_counter()
    if tris.v0.shape[0] != bvh.prim.shape[0]:
        raise ValueError(f"refit needs the triangles the tree was built over: {bvh.prim.shape[0]}, "
                         f"got {tris.v0.shape[0]}")
    level_start, level_nodes = levels if levels is not None else refit_levels(bvh.first, bvh.count)
    bmin, bmax = np.empty_like(bvh.bmin), np.empty_like(bvh.bmax)
    pad = BOX_PAD_SCALE * _largest_magnitude(tris.v0, tris.v1, tris.v2)
    _refit(bmin, bmax, bvh.first, bvh.count, bvh.prim, tris.v0, tris.v1, tris.v2, level_start, level_nodes,
           np.float32(pad))
    return bvh._replace(bmin=bmin, bmax=bmax, build_seconds=time.perf_counter() - start)


@njit(cache=True)
def _sah_cost(bmin, bmax, count, traversal_cost):
    total = 0.0
    root = 0.0
    for node in range(bmin.shape[0]):
        dx = max(bmax[node, 0] - bmin[node, 0], 0.0)
        dy = max(bmax[node, 1] - bmin[node, 1], 0.0)
        dz = max(bmax[node, 2] - bmin[node, 2], 0.0)
        area = float(dx) * dy + float(dy) * dz + float(dz) * dx
        if node == 0:
            root = area
        total += area * (traversal_cost if count[node] == 0 else count[node])
    return total / (root if root > 0 else 1.0)


def sah_cost(bvh: BVH) -> float:
    """Expected SAH cost of the tree: the area-weighted node and triangle test costs over the
    root's area (a unitless number; refits that loosen the tree raise it)."""
    return float(_sah_cost(bvh.bmin, bvh.bmax, bvh.count, float(TRAVERSAL_COST)))
