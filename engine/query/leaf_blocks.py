"""The mesh queries' leaf triangles in blocks of four, laid out as the four-triangle test loads
them: one <4 x float> per corner and axis, then the four triangles' indices.

    blocks: f32[G, 10, 4]     blocks[g, 3 * c + a, j]: axis a (x, y, z) of corner c (v0, v1, v2)
                              of the block's lane j; row 9 (``TRI_ROW``) holds the lanes'
                              triangle indices as int32 bits: 160 contiguous bytes a block
    block_tri: i32[G, 10, 4]  the same memory as int32 (``blocks.view(np.int32)``): block_tri[g,
                              TRI_ROW, j] is the triangle (row of the local ``Triangles``) in
                              lane j; -1 in the padding lanes of a leaf's last block (which
                              repeat its last triangle)

A leaf of n triangles takes ceil(n / 4) consecutive blocks, the leaves in the BVH's ``prim``
order, so a walk meets the triangles in the same order as in ``prim``. The 8-wide tree's leaf
slots point at their leaf's first block (``child``); ``size`` stays its number of triangles.

Why: the four-triangle test (``engine.packet.simd4_triangle.triangles_block``) picks each
corner's components by the ray's axis permutation. From rows of (x, y, z) corners that took 36
scalar loads and 36 inserts a group; from these blocks it is 9 vector loads at computed offsets.
The indices sit in the block because a walk that finds a hit reads its lane's index next: kept in
an array of their own, that read was a cache miss of its own (the bunny's incoherent rays: 3.5%
of the walk's time on that one load).
"""
import numpy as np
from numba import njit

LANES = 4
TRI_ROW = 9  # after 3 corners x 3 axes
ROWS = 10


@njit(cache=True)
def leaf_blocks(first, count, prim, v0, v1, v2, child, size):
    """(child_blocks i32[W,8], block_tri i32[G,10,4], blocks f32[G,10,4]) for the binary BVH's
    leaves (first, count i32[N], prim i32[P]), the local triangle corners v0, v1, v2 (f32[T,3],
    triangle order) and the 8-wide tree's child, size (i32[W,8], ``engine.query.wide``):
    child_blocks is child with every leaf slot's first prim row replaced by its first block;
    block_tri is blocks' memory as int32 (see the module doc)."""
    leaves = np.flatnonzero(count > 0)
    order = np.argsort(first[leaves])
    block_of_row = np.full(prim.shape[0], -1, np.int32)
    n_blocks = 0
    for k in order:
        leaf = leaves[k]
        block_of_row[first[leaf]] = n_blocks
        n_blocks += (count[leaf] + LANES - 1) // LANES
    blocks = np.empty((n_blocks, ROWS, LANES), np.float32)
    block_tri = blocks.view(np.int32)
    block_tri[:, TRI_ROW, :] = -1
    for k in order:
        leaf = leaves[k]
        g0 = block_of_row[first[leaf]]
        n = count[leaf]
        for slot in range(((n + LANES - 1) // LANES) * LANES):
            g = g0 + slot // LANES
            j = slot % LANES
            tri = prim[first[leaf] + min(slot, n - 1)]   # padding repeats the last triangle
            if slot < n:
                block_tri[g, TRI_ROW, j] = tri
            for a in range(3):
                blocks[g, a, j] = v0[tri, a]
                blocks[g, 3 + a, j] = v1[tri, a]
                blocks[g, 6 + a, j] = v2[tri, a]
    child_blocks = child.copy()
    for w in range(child.shape[0]):
        for s in range(child.shape[1]):
            if size[w, s] > 0:
                child_blocks[w, s] = block_of_row[child[w, s]]
    return child_blocks, block_tri, blocks
