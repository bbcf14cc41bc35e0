"""The per-ray BVH walk every mesh query shares (one ray, a stack, over the 8-wide tree of
``engine.query.wide``): nearest child first for ``CLOSEST``; ``ANY`` and ``COLLECT`` take a
node's children in slot order, unsorted: no order changes their answers (``COLLECT``'s hits
are sorted afterwards), and unsorted measured faster: incoherent any-hit queries on the kitchen
26.1 -> 21.7 ms (200,000 rays, one thread, medians of 15 in alternating processes), all hits
25.1 -> 23.4 ms (50,000 rays); the bunny within its noise.

Modes (integer constants, so one compiled helper serves every kernel and reaches the disk cache):

- ``CLOSEST``: the closest hit (ties to the smaller triangle index, ``engine.core.triangle.closer``);
  the segment shrinks as hits are found.
- ``ANY``: stop at the first hit found.
- ``COLLECT``: every hit on [t_lo, t_hi]; the first ``cap`` are written to the scratch buffers
  (unsorted) and the total is returned, so a caller can count (cap 0) and then fill.

Triangles are the watertight test's float32 corners in the mesh's local frame, in blocks of
four per leaf (``engine.query.leaf_blocks``), in the BVH's ``prim`` order. A node's eight child
boxes are one <8 x float> test (``engine.packet.simd4.slab1x8``) and a leaf's blocks are tested
one at a time (``engine.packet.simd4_triangle.triangles_block``), each lane the scalar
watertight test's operations: numba leaves such small loops scalar. Both tests store their lanes'
answers in the walk's scratch (``new_stack``) and return a mask of the lanes hit, which the walk
visits bit by bit: a tuple indexed by a run-time lane compiles to a jump table, and its indirect
branches were the walk's costliest mispredictions. The stack is indexed by an unsigned counter,
so numba adds no negative-index wraparound to its loads and stores. A child pushed on the stack
has its row (node boxes or leaf block) prefetched as it is pushed: on the bunny's incoherent
rays the walk's time went mostly to cache misses on those rows. A node's children and sizes
sit in its own row, after its boxes (``engine.query.wide.pack_nodes``), so they arrive with them.
"""
import numpy as np
from numba import njit
from numba.cpython.unsafe.numbers import trailing_zeros

from engine.core.prefetch import prefetch_node, prefetch_row
from engine.core.triangle import F32_INF, F32_ONE, HUGE_INV, closer, ray_shear
from engine.packet.simd4 import slab1x8
from engine.packet.simd4_triangle import triangles_block
from engine.query.leaf_blocks import TRI_ROW
from engine.query.wide import CHILD_ROW, SIZE_ROW, WIDTH
from engine.core.types import MAX_BVH_DEPTH

CLOSEST, ANY, COLLECT = 0, 1, 2

#: Entries of the per-thread traversal stack: at most WIDTH - 1 left behind per level.
STACK_SIZE = WIDTH * MAX_BVH_DEPTH + 2


@njit(cache=True, inline="always")
def safe_inverse1(d):
    """1/d for one f32 direction component, zero mapped to +-HUGE_INV (as ``safe_inverse``)."""
    if d == 0:
        return -HUGE_INV if np.signbit(d) else HUGE_INV
    return F32_ONE / d


@njit(cache=True)
def new_stack():
    """Scratch for one thread's walks: (stack i32[STACK_SIZE, 2]: node (or first block) and size
    of each entry, stack_t f32[STACK_SIZE]: its entry distance, entries f32[8]: the last node
    test's child entry distances, answers f32[12]: the last leaf block's t, u, v per lane)."""
    return (np.empty((STACK_SIZE, 2), np.int32), np.empty(STACK_SIZE, np.float32), np.empty(8, np.float32),
            np.empty(12, np.float32))


@njit(cache=True)
def new_hit_buffers(cap):
    """Scratch for COLLECT walks: (t f32[cap], tri i32[cap], u f32[cap], v f32[cap])."""
    return (np.empty(cap, np.float32), np.empty(cap, np.int32), np.empty(cap, np.float32),
            np.empty(cap, np.float32))


@njit(cache=True, inline="always")  # inlined: a call per ray costs as much as a short walk
def walk(nodes, node_bits, block_tri, blocks, ox, oy, oz, dx, dy, dz, t_lo, t_hi, mode, stack, stack_t,
         entries, answers, buf_t, buf_tri, buf_u, buf_v, cap):
    """Walk the ray (ox, oy, oz) + t (dx, dy, dz) (f32 scalars, local frame, non-zero direction)
    over [t_lo, t_hi] through the 8-wide tree (nodes f32[W,8,8] and node_bits, its int32 view:
    ``engine.query.wide.pack_nodes``).

    blocks f32[G,10,4], block_tri (its int32 view): the leaves' triangles
    (``engine.query.leaf_blocks``; a leaf slot's child is its first block). Returns
    (n, t, tri, u, v): tri is a triangle (mesh face) index. For CLOSEST / ANY, n is 1 on a hit
    and (t, tri, u, v) the hit; for COLLECT, n is the number of hits (all of them, even past
    ``cap``); the first min(n, cap) are in buf_t, buf_tri, buf_u, buf_v (f32/i32/f32/f32[cap]) in
    the order found. stack, stack_t, entries, answers: scratch from ``new_stack``.
    """
    best_t = F32_INF
    best_tri = -1
    best_u = np.float32(0.0)
    best_v = np.float32(0.0)
    n = 0
    ix, iy, iz = safe_inverse1(dx), safe_inverse1(dy), safe_inverse1(dz)
    kx, ky, kz, sx, sy, sz = ray_shear(dx, dy, dz)
    okx = ox if kx == 0 else (oy if kx == 1 else oz)
    oky = ox if ky == 0 else (oy if ky == 1 else oz)
    okz = ox if kz == 0 else (oy if kz == 1 else oz)
    node = 0  # the current entry: a wide node (leaf 0) or a leaf's first block and triangle count
    leaf = 0
    one = np.uint64(1)
    top = np.uint64(0)
    while True:
        if leaf > 0:
            for done in range(0, leaf, 4):
                # A block of up to four triangles in one <4 x float> test; within a block a hit
                # does not shrink the others' segment, but ``closer`` drops any hit beyond it.
                g = node + done // 4
                lanes = triangles_block(blocks, g, min(4, leaf - done), okx, oky, okz, kx, ky, kz, sx, sy, sz,
                                        t_lo, t_hi, answers)
                while lanes != 0:  # the lanes hit, in lane order
                    j = trailing_zeros(lanes)
                    lanes &= lanes - 1
                    t = answers[j]
                    tri = block_tri[g, TRI_ROW, j]
                    if mode == COLLECT:
                        if n < cap:
                            buf_t[n] = t
                            buf_tri[n] = tri
                            buf_u[n] = answers[4 + j]
                            buf_v[n] = answers[8 + j]
                        n += 1
                    elif closer(t, tri, best_t, best_tri):
                        best_t, best_tri, best_u, best_v = t, tri, answers[4 + j], answers[8 + j]
                        n = 1
                        if mode == ANY:
                            return n, best_t, best_tri, best_u, best_v
                        t_hi = t  # CLOSEST: nothing beyond this hit matters any more
        else:
            hit = slab1x8(nodes, node, ox, oy, oz, ix, iy, iz, t_lo, t_hi, entries)
            if hit != 0:
                if hit & (hit - 1) == 0:  # one child hit: straight there, no stack traffic
                    s = trailing_zeros(hit)
                    leaf = node_bits[node, SIZE_ROW, s]
                    node = node_bits[node, CHILD_ROW, s]
                    continue
                # Several: push them all (CLOSEST: keeping stack[base:top] sorted far (bottom)
                # to near (top)), then take the top one.
                base = top
                while hit != 0:
                    s = trailing_zeros(hit)
                    hit &= hit - 1
                    tn = entries[s]
                    j = top
                    while mode == CLOSEST and j > base and stack_t[j - one] < tn:
                        stack[j, 0] = stack[j - one, 0]
                        stack[j, 1] = stack[j - one, 1]
                        stack_t[j] = stack_t[j - one]
                        j -= one
                    pushed = node_bits[node, CHILD_ROW, s]
                    pushed_size = node_bits[node, SIZE_ROW, s]
                    # Its row is fetched now, while the nearer subtrees are walked
                    # (``engine.core.prefetch``).
                    if pushed_size > 0:
                        prefetch_row(blocks, pushed)
                    else:
                        prefetch_node(nodes, pushed)
                    stack[j, 0] = pushed
                    stack[j, 1] = pushed_size
                    stack_t[j] = tn
                    top += one
                top -= one
                node = stack[top, 0]
                leaf = stack[top, 1]
                continue
        # A leaf done or a node missed: the nearest entry left that is not beyond the segment
        # (CLOSEST shrinks it).
        while top > 0 and stack_t[top - one] > t_hi:
            top -= one
        if top == 0:
            return n, best_t, best_tri, best_u, best_v
        top -= one
        node = stack[top, 0]
        leaf = stack[top, 1]


@njit(cache=True)
def sort_hits(buf_t, buf_tri, buf_u, buf_v, n):
    """Insertion sort of the first n buffered hits by (t, triangle index); n is small."""
    for i in range(1, n):
        t, tri, u, v = buf_t[i], buf_tri[i], buf_u[i], buf_v[i]
        j = i - 1
        while j >= 0 and closer(t, tri, buf_t[j], buf_tri[j]):
            buf_t[j + 1], buf_tri[j + 1], buf_u[j + 1], buf_v[j + 1] = buf_t[j], buf_tri[j], buf_u[j], buf_v[j]
            j -= 1
        buf_t[j + 1], buf_tri[j + 1], buf_u[j + 1], buf_v[j + 1] = t, tri, u, v


#: Hits on edges within this fraction of their distance are one crossing (2 to 4 float32 units
#: of t: 2^-22 fixed the edge rays too, 2^-20 also merged two kitchen surfaces that trimesh keeps
#: apart).
MERGE_RELATIVE = np.float32(2.0 ** -21)

#: A hit this close to its triangle's boundary, in barycentric units, is on an edge (or a
#: vertex). Where a ray runs through an edge the watertight test gives an edge function of
#: exactly 0: u or v is 0, or 1 - u - v a few float32 units of 1.
EDGE_BARYCENTRIC = np.float32(1e-5)


@njit(cache=True, inline="always")
def on_edge(u, v):
    """Whether a hit with barycentrics (u, v) lies on an edge or a vertex of its triangle."""
    return min(u, v, np.float32(1.0) - u - v) <= EDGE_BARYCENTRIC


@njit(cache=True)
def merge_crossings(buf_t, buf_tri, buf_u, buf_v, n, gap):
    """Drop sorted hits that are the previous kept hit's crossing again: closer than ``gap``
    along t (trimesh steps that far past each hit, 1e-6 of its ``mesh.scale``, for the same
    reason), or, both on an edge of their triangles, closer than MERGE_RELATIVE of their t. A ray
    through a shared edge or vertex reports each triangle there, but it crosses the surface once.
    The relative part: float32 t at 50 mesh sizes is 4e-6 coarse, and the two triangles of an edge
    gave t a few units apart there, two crossings for one. Only for hits on edges: a plate 7e-6
    of the mesh's size thick, its faces crossed inside, was one crossing from 30 sizes away,
    where Embree and exact geometry see two (session 40). Returns the kept count."""
    kept = 0
    for i in range(n):
        if kept > 0:
            apart = buf_t[i] - buf_t[kept - 1]
            if apart < gap or (apart < buf_t[i] * MERGE_RELATIVE and on_edge(buf_u[i], buf_v[i])
                               and on_edge(buf_u[kept - 1], buf_v[kept - 1])):
                continue
        buf_t[kept], buf_tri[kept], buf_u[kept], buf_v[kept] = buf_t[i], buf_tri[i], buf_u[i], buf_v[i]
        kept += 1
    return kept
