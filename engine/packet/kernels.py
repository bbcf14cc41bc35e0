"""Packet-local ray state and the kernels every packet traversal shares.

The packet traversals of Overbeck, Ramamoorthi and Mark (2008) -- simd, masked, ranged,
partition -- differ only in the steps a packet takes at a node and at a leaf
(``engine.packet.steps``) of their one walk (``engine.packet.walk``). What else they share lives
here:

- ``load_packet`` copies packet k (rays offsets[k] : offsets[k+1], whole 2x2 SIMD rays) into
  packet-local structure-of-arrays rows, so the four lanes of SIMD ray i are the consecutive
  floats 4i .. 4i+3 of every row: the layout the fixed 4-lane loops vectorise on. It also does
  the per-ray set-up of the watertight test once (``engine.core.triangle.ray_shear``) and picks the
  packet's near-child order from its direction signs.
- ``slab_mask4``: the 4-lane ray-box test of one SIMD ray (``engine.packet.simd4.slab4``), a bit mask
  of the lanes that hit; ``live_mask4`` and ``lane_count`` for the lanes still live.
- ``leaf_triangles`` / ``intersect_lanes``: the leaf, frustum-culled, then the shared
  ``intersect_triangle`` and tie rule ``closer`` for each lane, exactly as ``single`` does, run
  on the four lanes at once (``engine.packet.simd4_triangle.intersect4``).
- ``store_hits``: the packet's answers back into the batch's Hits arrays.

Packet-local state (L = the longest packet of the batch):
    rf: f32[RF_ROWS, L]  rows OX..IZ origin and inv_dir; TLO, THI the live segment (THI shrinks
                         to the best hit); SX, SY, SZ and OKX, OKY, OKZ the shear and the
                         permuted origin; BEST_T, BEST_U, BEST_V the best hit so far.
    ri: i32[RI_ROWS, L]  rows KX, KY, KZ the shear's axes; BEST_PRIM the best triangle (-1).
    near: i64[6]         near-child offset (0: left child first) per ``child_order_keys`` key.

A dead lane gets TLO = +inf and THI = -inf, so every box and triangle test misses it; an
occlusion query kills a lane the same way as soon as it is blocked.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from engine.packet.frustum_cull import frustum_misses_triangle
from engine.core.triangle import F32_INF, ray_shear
from engine.core.lanes8 import rows_of_three
from engine.packet.load8 import ROWS_F as LOAD8_ROWS_F, ROWS_I as LOAD8_ROWS_I, load_rays8
from engine.packet.simd4 import slab4, slab4x2
from engine.packet.simd4_triangle import ROWS_F, ROWS_I, intersect4, intersect4x2
from engine.core.types import MAX_BVH_DEPTH

OX, OY, OZ, IX, IY, IZ, TLO, THI, SX, SY, SZ, OKX, OKY, OKZ, BEST_T, BEST_U, BEST_V = range(17)
RF_ROWS = 17
KX, KY, KZ, BEST_PRIM = range(4)
RI_ROWS = 4
# intersect4 is written against this layout.
assert ROWS_F == {"TLO": TLO, "THI": THI, "SX": SX, "SY": SY, "SZ": SZ, "OKX": OKX, "OKY": OKY, "OKZ": OKZ,
                  "BEST_T": BEST_T, "BEST_U": BEST_U, "BEST_V": BEST_V}
assert ROWS_I == {"KX": KX, "KY": KY, "KZ": KZ, "BEST_PRIM": BEST_PRIM}
# and load_rays8 against this one.
assert LOAD8_ROWS_F == {name: row for row, name in enumerate(
    "OX OY OZ IX IY IZ TLO THI SX SY SZ OKX OKY OKZ BEST_T BEST_U BEST_V".split())}
assert LOAD8_ROWS_I == {"KX": KX, "KY": KY, "KZ": KZ, "BEST_PRIM": BEST_PRIM}

#: Depth-first traversal that tests a node when it is popped holds at most two entries per level.
STACK_SIZE = 2 * MAX_BVH_DEPTH + 2

F32_NEG_INF = np.float32(-np.inf)
F32_ZERO = np.float32(0.0)
ALL_LANES = 0xF


@njit(cache=True)
def longest_packet(offsets):
    """The most rays in one packet (offsets: i32[K+1])."""
    longest = 0
    for k in range(offsets.shape[0] - 1):
        longest = max(longest, offsets[k + 1] - offsets[k])
    return longest


@njit(cache=True)
def largest_leaf(count):
    """The most triangles in one leaf (count: i32[N])."""
    largest = 0
    for node in range(count.shape[0]):
        largest = max(largest, count[node])
    return largest


@njit(cache=True)
def packet_scratch(max_rays, max_leaf):
    """Per-worker buffers: (rf f32[RF_ROWS,L], ri i32[RI_ROWS,L], near i64[6], fr f32[16],
    leaf_tris i32[max_leaf]), L = max_rays rounded up to an odd number of 64-byte lines: with a
    row stride of a multiple of 4 KiB (1024 rays) the rows one lane touches would all fall in the
    same L1 cache set and evict each other."""
    lines = (max_rays + 15) // 16
    stride = 16 * (lines + 1 - lines % 2)
    rf = np.empty((RF_ROWS, stride), np.float32)
    ri = np.empty((RI_ROWS, stride), np.int32)
    near = np.zeros(6, np.int64)
    fr = np.zeros(16, np.float32)
    leaf_tris = np.empty(max(max_leaf, 1), np.int32)
    return rf, ri, near, fr, leaf_tris


@njit(cache=True)
def child_order_keys(bmin, bmax, first, count):
    """i8[N]: for each inner node, 2 * axis + upper, where ``axis`` is the axis along which its
    children's box centres lie farthest apart and ``upper`` is 1 when the left child's centre is
    the higher one along it. With the packet's direction signs this gives the near child."""
    n = first.shape[0]
    keys = np.zeros(n, np.int8)
    for node in range(n):
        if count[node] > 0:
            continue
        left = first[node]
        best_axis = 0
        best_gap = np.float32(-1.0)
        upper = 0
        for a in range(3):
            # Doubled centres: the factor 1/2 does not change the comparison.
            gap = (bmin[left + 1, a] + bmax[left + 1, a]) - (bmin[left, a] + bmax[left, a])
            if abs(gap) > best_gap:
                best_gap = abs(gap)
                best_axis = a
                upper = 1 if gap < F32_ZERO else 0
        keys[node] = 2 * best_axis + upper
    return keys


@njit(cache=True, inline="always")
def set_segment(rf, ri, i, tlo, thi, kx, ky, kz, sx, sy, sz, okx, oky, okz):
    """Lane i's live segment [tlo, thi] and the watertight test's set-up (shear axes kx, ky, kz,
    shear sx, sy, sz, permuted origin okx, oky, okz) into the packet-local rows."""
    rf[TLO, i] = tlo
    rf[THI, i] = thi
    ri[KX, i] = kx
    ri[KY, i] = ky
    ri[KZ, i] = kz
    rf[SX, i] = sx
    rf[SY, i] = sy
    rf[SZ, i] = sz
    rf[OKX, i] = okx
    rf[OKY, i] = oky
    rf[OKZ, i] = okz


@njit(cache=True, inline="always")
def load_lane(org, inv, dirs, tmin, tmax, r, rf, ri, i):
    """Ray r into lane i of the packet-local rows (``load_rays8`` does eight at once, bit for
    bit the same); returns 1 when the ray is live (tmin <= tmax), else 0."""
    rf[OX, i] = org[r, 0]
    rf[OY, i] = org[r, 1]
    rf[OZ, i] = org[r, 2]
    rf[IX, i] = inv[r, 0]
    rf[IY, i] = inv[r, 1]
    rf[IZ, i] = inv[r, 2]
    rf[BEST_T, i] = F32_INF
    rf[BEST_U, i] = F32_ZERO
    rf[BEST_V, i] = F32_ZERO
    ri[BEST_PRIM, i] = -1
    if tmin[r] <= tmax[r]:
        kx, ky, kz, sx, sy, sz = ray_shear(dirs[r, 0], dirs[r, 1], dirs[r, 2])
        set_segment(rf, ri, i, tmin[r], tmax[r], kx, ky, kz, sx, sy, sz, org[r, kx], org[r, ky], org[r, kz])
        return 1
    set_segment(rf, ri, i, F32_INF, F32_NEG_INF, 0, 1, 2, F32_ZERO, F32_ZERO, F32_ZERO,
                F32_ZERO, F32_ZERO, F32_ZERO)
    return 0


@njit(cache=True, inline="always")
def load_packet(org, inv, dirs, tmin, tmax, start, n, rf, ri, near):
    """Transpose rays start .. start+n (org, inv, dirs: f32[R,3]; tmin, tmax: f32[R]) into the
    packet-local rows rf, ri and set the near-child table from the live rays' summed direction.
    Returns the number of live lanes. Eight rays at a time (``load_rays8``), the rest one by
    one."""
    live = 0
    sum_x = 0.0
    sum_y = 0.0
    sum_z = 0.0
    i = 0
    if n >= 8 and rows_of_three(org) and rows_of_three(inv) and rows_of_three(dirs):
        while i + 8 <= n:
            mask = load_rays8(org, inv, dirs, tmin, tmax, start + i, rf, ri, i)
            live += lane_count(mask & ALL_LANES) + lane_count(mask >> 4)
            i += 8
        # Those rays' directions summed in lane order; a dead lane adds +0.0, which changes no
        # sum's value (the sums start at +0.0) and needs no branch.
        for k in range(i):
            r = start + k
            alive = tmin[r] <= tmax[r]
            sum_x += dirs[r, 0] if alive else F32_ZERO
            sum_y += dirs[r, 1] if alive else F32_ZERO
            sum_z += dirs[r, 2] if alive else F32_ZERO
    # The rest one by one (all of a 2x2 SIMD ray's packet: the baseline walks 262,144 a frame).
    while i < n:
        r = start + i
        if load_lane(org, inv, dirs, tmin, tmax, r, rf, ri, i):
            live += 1
            sum_x += dirs[r, 0]
            sum_y += dirs[r, 1]
            sum_z += dirs[r, 2]
        i += 1
    # Travelling towards -axis, the upper child comes first: near offset = upper XOR negative.
    neg_x = 1 if sum_x < 0.0 else 0
    neg_y = 1 if sum_y < 0.0 else 0
    neg_z = 1 if sum_z < 0.0 else 0
    near[0], near[1] = neg_x, 1 - neg_x
    near[2], near[3] = neg_y, 1 - neg_y
    near[4], near[5] = neg_z, 1 - neg_z
    return live


@njit(cache=True, inline="always")
def node_box(bmin, bmax, node):
    """Box ``node`` as a tuple (x0, y0, z0, x1, y1, z1), read once per visit: loops that also
    store (partitions, hits) would otherwise reload it for every SIMD ray."""
    return bmin[node, 0], bmin[node, 1], bmin[node, 2], bmax[node, 0], bmax[node, 1], bmax[node, 2]


@njit(cache=True, inline="always")
def slab_mask4(rf, lane0, box):
    """4-bit mask of the lanes of SIMD ray lane0 .. lane0+3 whose live segment meets ``box`` (a
    ``node_box`` tuple): ``engine.core.triangle.slab_test`` on all four lanes at once, in SSE-style
    vector code."""
    return slab4(rf, lane0, box[0], box[1], box[2], box[3], box[4], box[5])


@njit(cache=True, inline="always")
def slab_mask4x2(rf, lane0, lane1, box):
    """``slab_mask4`` of the SIMD rays at lane0 and lane1 in one 8-lane test: lane0's mask in
    bits 0-3, lane1's in bits 4-7."""
    return slab4x2(rf, lane0, lane1, box[0], box[1], box[2], box[3], box[4], box[5])


@njit(cache=True, inline="always")
def live_mask4(rf, lane0):
    """4-bit mask of the lanes of SIMD ray lane0 that are still live (TLO <= THI)."""
    mask = 0
    for lane in range(4):
        mask |= (1 << lane) if rf[TLO, lane0 + lane] <= rf[THI, lane0 + lane] else 0
    return mask


@njit(cache=True, inline="always")
def lane_count(mask):
    """Number of lanes set in a 4-bit lane mask."""
    return (mask & 1) + ((mask >> 1) & 1) + ((mask >> 2) & 1) + ((mask >> 3) & 1)


@njit(cache=True, inline="always")
def leaf_triangles(first, count, prim, node, v0, v1, v2, fr, cull, leaf_tris):
    """Copy leaf ``node``'s triangles into leaf_tris, dropping those the packet frustum culls;
    returns how many remain."""
    n = 0
    for i in range(first[node], first[node] + count[node]):
        tri = prim[i]
        if cull and frustum_misses_triangle(fr, v0, v1, v2, tri):
            continue
        leaf_tris[n] = tri
        n += 1
    return n


@njit(cache=True, inline="always")
def intersect_lanes(rf, ri, lane0, mask, leaf_tris, n_tris, v0, v1, v2, any_hit):
    """Test the live lanes of SIMD ray lane0 selected by ``mask`` against leaf_tris[:n_tris].

    Per lane and triangle this is ``intersect_triangle`` with the lane's own shear and segment,
    then the update ``closer``, exactly as in ``single``, so the best hit is bit-identical whatever
    the order; ``engine.packet.simd4_triangle.intersect4`` runs it on the four lanes at once. For
    ``any_hit`` a lane dies (THI = -inf) at its first hit. Returns (ray-triangle tests done,
    lanes that died).
    """
    return intersect4(rf, ri, lane0, mask, leaf_tris, n_tris, v0, v1, v2, any_hit)


@njit(cache=True, inline="always")
def intersect_lanes_x2(rf, ri, lane0, lane1, mask, leaf_tris, n_tris, v0, v1, v2, any_hit):
    """``intersect_lanes`` of the SIMD rays at lane0 and lane1 in one 8-lane test (``mask``
    bits 0-3 for lane0's lanes, 4-7 for lane1's): every lane ends exactly as two calls would
    leave it, at about the cost of one (``engine.packet.simd4_triangle.intersect4x2``)."""
    return intersect4x2(rf, ri, lane0, lane1, mask, leaf_tris, n_tris, v0, v1, v2, any_hit)


@njit(cache=True, inline="always")
def store_hits(rf, ri, start, n, out_t, out_prim, out_u, out_v):
    """Write the packet's best hits to rays start .. start+n of the output arrays (f32/i32[R])."""
    for i in range(n):
        out_t[start + i] = rf[BEST_T, i]
        out_prim[start + i] = ri[BEST_PRIM, i]
        out_u[start + i] = rf[BEST_U, i]
        out_v[start + i] = rf[BEST_V, i]
