"""A 4-wide BVH collapsed from the binary one, with children's boxes side by side.

The binary tree's slab tests dominate a per-ray walk (about two per node visited); here a node
holds up to four children whose boxes are stored per axis as 4 consecutive floats, so one node
visit tests all four with straight-line code the compiler vectorises, and a walk visits about
half as many nodes. Leaves (and triangle order) are the binary tree's.

    lo, hi: f32[W,3,4]    child boxes, axis-major: lo[w, axis, slot]
    child: i32[W,4]       inner slot: index of the wide node; leaf slot: start in ``prim``
    size: i32[W,4]        0 = inner, > 0 = leaf of that many triangles, -1 = empty slot

Built by ``collapse`` (each wide node replaces its largest-area inner child by that child's two
children until it has four) and refitted by collapsing again (the binary tree is refitted first).
"""
import numpy as np
from numba import njit

WIDTH = 4


@njit(cache=True)
def _area(bmin, bmax, node):
    dx = bmax[node, 0] - bmin[node, 0]
    dy = bmax[node, 1] - bmin[node, 1]
    dz = bmax[node, 2] - bmin[node, 2]
    return dx * dy + dy * dz + dz * dx


@njit(cache=True)
def collapse(bmin, bmax, first, count):
    """(lo, hi, child, size) of the 4-wide tree over a binary BVH's arrays (see the module doc)."""
    n_nodes = bmin.shape[0]
    cap = max(n_nodes, 1)
    lo = np.full((cap, 3, WIDTH), np.inf, np.float32)
    hi = np.full((cap, 3, WIDTH), -np.inf, np.float32)
    child = np.zeros((cap, WIDTH), np.int32)
    size = np.full((cap, WIDTH), -1, np.int32)
    stack_bin = np.empty(cap, np.int64)
    stack_wide = np.empty(cap, np.int64)
    slots = np.empty(WIDTH, np.int64)
    top = 1
    stack_bin[0] = 0
    stack_wide[0] = 0
    n_wide = 1
    while top > 0:
        top -= 1
        b = stack_bin[top]
        w = stack_wide[top]
        m = 1
        slots[0] = b
        if count[b] == 0:  # open the root of this wide node, then the largest inner children
            slots[0] = first[b]
            slots[1] = first[b] + 1
            m = 2
            while m < WIDTH:
                best = -1
                best_area = -1.0
                for s in range(m):
                    x = slots[s]
                    if count[x] == 0 and _area(bmin, bmax, x) > best_area:
                        best_area = _area(bmin, bmax, x)
                        best = s
                if best < 0:
                    break
                x = slots[best]
                slots[best] = first[x]
                slots[m] = first[x] + 1
                m += 1
        for s in range(m):
            x = slots[s]
            for a in range(3):
                lo[w, a, s] = bmin[x, a]
                hi[w, a, s] = bmax[x, a]
            if count[x] > 0:
                child[w, s] = first[x]
                size[w, s] = count[x]
            else:
                child[w, s] = n_wide
                size[w, s] = 0
                stack_bin[top] = x
                stack_wide[top] = n_wide
                top += 1
                n_wide += 1
    return lo[:n_wide].copy(), hi[:n_wide].copy(), child[:n_wide].copy(), size[:n_wide].copy()
