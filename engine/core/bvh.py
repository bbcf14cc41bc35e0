"""Binned-SAH BVH over triangles, in the flat layout of ``engine.core.types.BVH``.

The builder works on primitive bounds and centroids only; it never sees a triangle,
so any primitive with a box can be organised by it. Children of a node are adjacent
(``first`` and ``first + 1``) and always stored after their parent, so a reverse sweep
over the node array visits children before parents (``engine.core.bvh_refit`` refits a tree
for moved triangles that way, and measures its SAH cost).
"""
from __future__ import annotations

import time

import numpy as np
from numba import njit

from engine.core.errors import ConfigError, ConfigTypeError
from engine.core.types import BVH, MAX_BVH_DEPTH, Triangles

#: Relative cost of one node traversal step against one ray-triangle test.
TRAVERSAL_COST = np.float32(1.0)

SPLIT_SAH, SPLIT_MEDIAN = 0, 1

#: Node boxes are widened by this fraction of the scene's largest |coordinate|. A slab test
#: computes (box - origin) in float32, which is off by up to half an ulp of the larger of the
#: two; its relative slack on t cannot cover that when the origin sits next to the box (a
#: secondary ray leaving a surface into a corner), so the box carries the absolute part.
BOX_PAD_SCALE = np.float32(2.0 ** -20)


@njit(cache=True)
def _half_area(lo, hi):
    dx = max(hi[0] - lo[0], 0.0)
    dy = max(hi[1] - lo[1], 0.0)
    dz = max(hi[2] - lo[2], 0.0)
    return dx * dy + dy * dz + dz * dx


@njit(cache=True)
def _build(pmin, pmax, cent, n_bins, max_leaf, method):
    """Top-down build. pmin, pmax, cent: f32[T,3]. Returns the node arrays, prim and depth."""
    n_prims = pmin.shape[0]
    prim = np.arange(n_prims).astype(np.int32)
    max_nodes = max(2 * n_prims - 1, 1)
    bmin = np.empty((max_nodes, 3), np.float32)
    bmax = np.empty((max_nodes, 3), np.float32)
    first = np.zeros(max_nodes, np.int32)
    count = np.zeros(max_nodes, np.int32)

    stack_node = np.empty(2 * MAX_BVH_DEPTH + 2, np.int64)
    stack_lo = np.empty(2 * MAX_BVH_DEPTH + 2, np.int64)
    stack_hi = np.empty(2 * MAX_BVH_DEPTH + 2, np.int64)
    stack_depth = np.empty(2 * MAX_BVH_DEPTH + 2, np.int64)
    top = 0
    stack_node[0], stack_lo[0], stack_hi[0], stack_depth[0] = 0, 0, n_prims, 0
    top = 1
    n_nodes = 1
    deepest = 0

    bin_lo = np.empty((n_bins, 3), np.float32)
    bin_hi = np.empty((n_bins, 3), np.float32)
    bin_n = np.empty(n_bins, np.int64)
    right_area = np.empty(n_bins, np.float32)
    right_n = np.empty(n_bins, np.int64)
    lo3 = np.empty(3, np.float32)
    hi3 = np.empty(3, np.float32)

    while top > 0:
        top -= 1
        node = stack_node[top]
        lo = stack_lo[top]
        hi = stack_hi[top]
        depth = stack_depth[top]
        deepest = max(deepest, depth)

        # Node box and centroid box.
        for a in range(3):
            bmin[node, a] = np.inf
            bmax[node, a] = -np.inf
        cmin = np.full(3, np.inf, np.float32)
        cmax = np.full(3, -np.inf, np.float32)
        for i in range(lo, hi):
            p = prim[i]
            for a in range(3):
                bmin[node, a] = min(bmin[node, a], pmin[p, a])
                bmax[node, a] = max(bmax[node, a], pmax[p, a])
                cmin[a] = min(cmin[a], cent[p, a])
                cmax[a] = max(cmax[a], cent[p, a])
        n = hi - lo
        if n <= max_leaf or depth + 1 >= MAX_BVH_DEPTH:
            first[node] = lo
            count[node] = n
            continue

        axis = 0
        for a in range(1, 3):
            if cmax[a] - cmin[a] > cmax[axis] - cmin[axis]:
                axis = a
        mid = lo
        if method == SPLIT_SAH and cmax[axis] > cmin[axis]:
            # Binned SAH over all three axes; pick the cheapest boundary.
            best_cost = np.inf
            best_axis = -1
            best_bin = -1
            for a in range(3):
                extent = cmax[a] - cmin[a]
                if extent <= 0.0:
                    continue
                scale = n_bins / extent
                for b in range(n_bins):
                    bin_n[b] = 0
                    for c in range(3):
                        bin_lo[b, c] = np.inf
                        bin_hi[b, c] = -np.inf
                for i in range(lo, hi):
                    p = prim[i]
                    b = min(int((cent[p, a] - cmin[a]) * scale), n_bins - 1)
                    bin_n[b] += 1
                    for c in range(3):
                        bin_lo[b, c] = min(bin_lo[b, c], pmin[p, c])
                        bin_hi[b, c] = max(bin_hi[b, c], pmax[p, c])
                # Sweep from the right, then from the left evaluating each boundary.
                for c in range(3):
                    lo3[c] = np.inf
                    hi3[c] = -np.inf
                acc = 0
                for b in range(n_bins - 1, 0, -1):
                    acc += bin_n[b]
                    for c in range(3):
                        lo3[c] = min(lo3[c], bin_lo[b, c])
                        hi3[c] = max(hi3[c], bin_hi[b, c])
                    right_area[b] = _half_area(lo3, hi3)
                    right_n[b] = acc
                for c in range(3):
                    lo3[c] = np.inf
                    hi3[c] = -np.inf
                acc = 0
                for b in range(0, n_bins - 1):
                    acc += bin_n[b]
                    for c in range(3):
                        lo3[c] = min(lo3[c], bin_lo[b, c])
                        hi3[c] = max(hi3[c], bin_hi[b, c])
                    if acc == 0 or right_n[b + 1] == 0:
                        continue
                    cost = _half_area(lo3, hi3) * acc + right_area[b + 1] * right_n[b + 1]
                    if cost < best_cost:
                        best_cost = cost
                        best_axis = a
                        best_bin = b
            if best_axis >= 0:
                a = best_axis
                scale = n_bins / (cmax[a] - cmin[a])
                # In-place partition: bins <= best_bin go left.
                i = lo
                j = hi - 1
                while i <= j:
                    b = min(int((cent[prim[i], a] - cmin[a]) * scale), n_bins - 1)
                    if b <= best_bin:
                        i += 1
                    else:
                        prim[i], prim[j] = prim[j], prim[i]
                        j -= 1
                mid = i
        if mid <= lo or mid >= hi:
            # Median split on the widest centroid axis (also the fallback when all
            # centroids coincide, e.g. many degenerate triangles at one point).
            keys = np.empty(n, np.float32)
            for i in range(n):
                keys[i] = cent[prim[lo + i], axis]
            order = np.argsort(keys, kind="mergesort")
            chunk = prim[lo:hi].copy()
            for i in range(n):
                prim[lo + i] = chunk[order[i]]
            mid = lo + n // 2

        left = n_nodes
        n_nodes += 2
        first[node] = left
        count[node] = 0
        stack_node[top], stack_lo[top], stack_hi[top], stack_depth[top] = left + 1, mid, hi, depth + 1
        top += 1
        stack_node[top], stack_lo[top], stack_hi[top], stack_depth[top] = left, lo, mid, depth + 1
        top += 1

    return (bmin[:n_nodes].copy(), bmax[:n_nodes].copy(), first[:n_nodes].copy(),
            count[:n_nodes].copy(), prim, deepest)


def triangle_bounds(tris: Triangles):
    """(pmin, pmax, centroid): f32[T,3] each."""
    pmin = np.minimum(np.minimum(tris.v0, tris.v1), tris.v2)
    pmax = np.maximum(np.maximum(tris.v0, tris.v1), tris.v2)
    cent = ((pmin + pmax) * np.float32(0.5)).astype(np.float32)
    return np.ascontiguousarray(pmin), np.ascontiguousarray(pmax), cent


def _pad_boxes(bmin, bmax, pmin, pmax) -> None:
    """Widen every node box (f32[N,3], in place) by ``BOX_PAD_SCALE`` x the largest |coordinate|."""
    pad = BOX_PAD_SCALE * np.float32(max(np.abs(pmin).max(), np.abs(pmax).max()))
    bmin -= pad
    bmax += pad


def check_build_settings(leaf_size, bins) -> tuple[int, int]:
    """(leaf_size, bins) as ints if each is an integer in its range (leaf_size 1..255, bins
    2..256); else a ConfigTypeError (not an integer: a float, string, bool or None) or a
    ConfigError (out of range), one line naming the setting."""
    settings = []
    for name, value, lo, hi in (("leaf_size", leaf_size, 1, 255), ("bins", bins, 2, 256)):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise ConfigTypeError(f"bvh {name} must be an integer in {lo}..{hi}, got {value!r}")
        if not lo <= value <= hi:
            raise ConfigError(f"bvh {name} must be in {lo}..{hi}, got {value}")
        settings.append(int(value))
    return settings[0], settings[1]


def build_bvh(tris: Triangles, *, leaf_size: int = 4, bins: int = 16, split: str = "sah") -> BVH:
    """Build a BVH over ``tris``: binned SAH with ``bins`` bins, leaves of <= ``leaf_size``.

    ``split = "median"`` builds an object-median tree instead (a baseline for SAH quality).
    """
    leaf_size, bins = check_build_settings(leaf_size, bins)
    methods = {"sah": SPLIT_SAH, "median": SPLIT_MEDIAN}
    if split not in methods:
        raise ConfigError(f"bvh split must be one of {sorted(methods)}, got {split!r}")
    start = time.perf_counter()
    pmin, pmax, cent = triangle_bounds(tris)
    if pmin.shape[0] == 0:
        raise ConfigError("cannot build a BVH over a scene with no triangles")
    bmin, bmax, first, count, prim, depth = _build(pmin, pmax, cent, bins, leaf_size, methods[split])
    _pad_boxes(bmin, bmax, pmin, pmax)
    return BVH(bmin, bmax, first, count, prim, int(depth), time.perf_counter() - start)


def node_depths(bvh: BVH) -> np.ndarray:
    """i32[N]: depth of every node (root 0)."""
    depth = np.zeros(len(bvh.first), np.int32)
    for node in range(len(bvh.first)):
        if bvh.count[node] == 0:
            depth[bvh.first[node]] = depth[bvh.first[node] + 1] = depth[node] + 1
    return depth


def scene_bounds(bvh: BVH) -> np.ndarray:
    """f32[2,3]: the root box (min, max)."""
    return np.stack([bvh.bmin[0], bvh.bmax[0]]).astype(np.float32)
