"""An 8-wide BVH collapsed from the binary one, with its children's boxes side by side.

A per-ray walk is a chain of dependent loads: each node's children are known only once its box
test is done. A node of eight children, their boxes stored per axis as 8 consecutive floats,
is one <8 x float> test (``engine.packet.simd4.slab1x8``: AVX2's width), and a walk visits
about half as many levels as in a 4-wide tree (1.3-1.4x faster per ray on the bunny and the
kitchen; see the README's trimesh section). Leaves (and triangle order) are the binary tree's.

``collapse`` gives the tree as three arrays:

    box: f32[W,6,8]       child boxes, rows lo x, y, z, hi x, y, z: box[w, row, slot];
                          NaN in empty slots, so that no ray ever hits them
    child: i32[W,8]       inner slot: index of the wide node; leaf slot: start in ``prim``
    size: i32[W,8]        0 = inner, > 0 = leaf of that many triangles, -1 = empty slot

and ``pack_nodes`` puts them into the one array the walks read, a node per 256-byte row, the
array starting on a cache line, so that a node is exactly four lines:

    nodes: f32[W,8,8]     rows 0-5 the boxes, row 6 the child and row 7 the size (int32 bits;
                          the walks read them through ``nodes.view(np.int32)``)

Kept apart, a node's boxes, child and size rows were three places in memory, and the child and
size loads, which wait for the box test's answer, were a second cache miss after the boxes' on
a large mesh; prefetching those two rows before each box test (08374a2) took the bunny's
incoherent first hits from 40.0 to 37.4 ms on two threads. In one row they come with the boxes,
one stream of lines: against that, 200,000 incoherent rays, medians of 31 alternating calls, two
threads, first hits bunny 40.8 -> 39.6 and kitchen 18.5 -> 17.7 ms, any hits bunny 39.6 -> 38.2
and kitchen 12.5 -> 12.5 ms; one thread, bunny any hits 78.4 -> 73.7 ms, first hits the same
(83.1 / 83.2). A few per cent, never slower, and one array for the walks instead of three.

Built by ``collapse`` (each wide node replaces its largest-area inner child by that child's two
children until it has eight) and refitted by collapsing again (the binary tree is refitted first).
"""
import numpy as np
from numba import njit

from engine.core.prefetch import LINE_BYTES
from engine.query.leaf_blocks import leaf_blocks

WIDTH = 8


@njit(cache=True)
def _area(bmin, bmax, node):
    dx = bmax[node, 0] - bmin[node, 0]
    dy = bmax[node, 1] - bmin[node, 1]
    dz = bmax[node, 2] - bmin[node, 2]
    return dx * dy + dy * dz + dz * dx


@njit(cache=True)
def collapse(bmin, bmax, first, count):
    """(box, child, size) of the 8-wide tree over a binary BVH's arrays (see the module doc)."""
    n_nodes = bmin.shape[0]
    cap = max(n_nodes, 1)
    box = np.full((cap, 6, WIDTH), np.nan, np.float32)
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
                box[w, a, s] = bmin[x, a]
                box[w, 3 + a, s] = bmax[x, a]
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
    return box[:n_wide].copy(), child[:n_wide].copy(), size[:n_wide].copy()


#: Rows of a packed node (``pack_nodes``): the six box rows, then the child and size rows.
CHILD_ROW, SIZE_ROW, NODE_ROWS = 6, 7, 8


def pack_nodes(box: np.ndarray, child: np.ndarray, size: np.ndarray) -> np.ndarray:
    """nodes f32[W,8,8] (see the module doc) from box f32[W,6,8], child and size i32[W,8],
    starting on a 64-byte boundary (numpy and numba align to 16 or 32 bytes only)."""
    shape = (box.shape[0], NODE_ROWS, WIDTH)
    nbytes = shape[0] * NODE_ROWS * WIDTH * 4
    raw = np.empty(nbytes + LINE_BYTES, np.uint8)
    start = (-raw.ctypes.data) % LINE_BYTES
    nodes = raw[start:start + nbytes].view(np.float32).reshape(shape)
    nodes[:, :CHILD_ROW, :] = box
    bits = nodes.view(np.int32)
    bits[:, CHILD_ROW, :] = child
    bits[:, SIZE_ROW, :] = size
    return nodes


def packed_tree(bvh, v0, v1, v2) -> tuple:
    """(nodes, block_tri, blocks): the walks' 8-wide tree over a binary ``bvh`` (``pack_nodes``)
    with its leaves' triangles, corners v0, v1, v2 f32[T,3], in blocks (``leaf_blocks``). The
    mesh queries build it over the mesh's local frame, the ``wide`` traversal over a scene."""
    box, child, size = collapse(bvh.bmin, bvh.bmax, bvh.first, bvh.count)
    child, block_tri, blocks = leaf_blocks(bvh.first, bvh.count, bvh.prim, v0, v1, v2, child, size)
    return pack_nodes(box, child, size), block_tri, blocks
