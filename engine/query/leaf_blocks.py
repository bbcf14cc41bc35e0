"""The mesh queries' leaf triangles in blocks of four, laid out as the four-triangle test loads
them: one <4 x float> per corner and axis.

    blocks: f32[G, 9, 4]   blocks[g, 3 * c + a, j]: axis a (x, y, z) of corner c (v0, v1, v2)
                           of the block's lane j: 144 contiguous bytes a block
    lane_tri: i32[G * 4]   the triangle (row of the local ``Triangles``) in each lane; -1 in the
                           padding lanes of a leaf's last block (which repeat its last triangle)

A leaf of n triangles takes ceil(n / 4) consecutive blocks, the leaves in the BVH's ``prim``
order, so a walk meets the triangles in the same order as in ``prim``. The 8-wide tree's leaf
slots point at their leaf's first block (``child``); ``size`` stays its number of triangles.

Why: the four-triangle test (``engine.packet.simd4_triangle.triangles_block``) picks each
corner's components by the ray's axis permutation. From rows of (x, y, z) corners that took 36
scalar loads and 36 inserts a group; from these blocks it is 9 vector loads at computed offsets.
"""
import numpy as np
from numba import njit

LANES = 4
ROWS = 9  # 3 corners x 3 axes


@njit(cache=True)
def leaf_blocks(first, count, prim, v0, v1, v2, child, size):
    """(child_blocks i32[W,8], lane_tri i32[G*4], blocks f32[G,9,4]) for the binary BVH's leaves
    (first, count i32[N], prim i32[P]), the local triangle corners v0, v1, v2 (f32[T,3], triangle
    order) and the 8-wide tree's child, size (i32[W,8], ``engine.query.wide``): child_blocks is
    child with every leaf slot's first prim row replaced by its first block."""
    leaves = np.flatnonzero(count > 0)
    order = np.argsort(first[leaves])
    block_of_row = np.full(prim.shape[0], -1, np.int32)
    n_blocks = 0
    for k in order:
        leaf = leaves[k]
        block_of_row[first[leaf]] = n_blocks
        n_blocks += (count[leaf] + LANES - 1) // LANES
    blocks = np.empty((n_blocks, ROWS, LANES), np.float32)
    lane_tri = np.full(n_blocks * LANES, -1, np.int32)
    for k in order:
        leaf = leaves[k]
        g0 = block_of_row[first[leaf]]
        n = count[leaf]
        for slot in range(((n + LANES - 1) // LANES) * LANES):
            g = g0 + slot // LANES
            j = slot % LANES
            tri = prim[first[leaf] + min(slot, n - 1)]   # padding repeats the last triangle
            if slot < n:
                lane_tri[g * LANES + j] = tri
            for a in range(3):
                blocks[g, a, j] = v0[tri, a]
                blocks[g, 3 + a, j] = v1[tri, a]
                blocks[g, 6 + a, j] = v2[tri, a]
    child_blocks = child.copy()
    for w in range(child.shape[0]):
        for s in range(child.shape[1]):
            if size[w, s] > 0:
                child_blocks[w, s] = block_of_row[child[w, s]]
    return child_blocks, lane_tri, blocks
