"""Inside/outside by parity: count the surface crossings along a ray from the point, both ways.

No hit list is materialised: one walk per direction collects the hits along the whole line
through the point (t in (-inf, inf): the forward cast is t > 0, the backward one t < 0) in
per-thread scratch of at most ``CAP`` hits, sorts and merges them (``walk.merge_crossings``) and
keeps only the two counts. A line is
*ambiguous* when the point lies on the surface (a hit at t < gap), when a hit sits exactly on a
triangle's edge (barycentric 0), when two triangles report one crossing (the ray may graze an
edge or a vertex rather than cross), or when it has more than CAP hits. As in trimesh, the
answer is taken from the forward and backward counts of the first direction in ``DIRECTIONS``
whose line is not ambiguous and whose two parities agree, or is outside at the first direction
whose parities disagree where one way meets no surface (trimesh's free-space rule: on an open
mesh, a line out through a hole); when none decides, the parities of all casts vote. Points outside the mesh's bounding box are outside without a cast.
"""
import numpy as np
from numba import njit, prange

from engine.query.walk import COLLECT, merge_crossings, new_hit_buffers, new_stack, sort_hits, walk

#: Hits one cast may collect before it counts as ambiguous.
CAP = 256

#: Cast directions, tried in turn (the first is trimesh's default direction); unit length.
DIRECTIONS = np.array([[0.4395064455, 0.617598629942, 0.652231566745],
                       [-0.5773502691896258, 0.5773502691896258, 0.5773502691896258],
                       [0.2672612419124244, -0.5345224838248488, 0.8017837257372732],
                       [0.8164965809277261, 0.4082482904638631, -0.4082482904638631]])
DIRECTIONS = DIRECTIONS / np.linalg.norm(DIRECTIONS, axis=1, keepdims=True)


@njit(cache=True, inline="always")
def _line(nodes, node_bits, block_tri, blocks, ox, oy, oz, dx, dy, dz, stack, stack_t, entries, answers, bt,
          btri, bu, bv, gap):
    """(crossings ahead, crossings behind, ambiguous) of the line (ox, oy, oz) + t (dx, dy, dz)."""
    n, _, _, _, _ = walk(nodes, node_bits, block_tri, blocks, ox, oy, oz, dx, dy, dz,
                         np.float32(-np.inf), np.float32(np.inf), COLLECT, stack, stack_t, entries, answers,
                         bt, btri, bu, bv, CAP)
    if n > CAP:
        # Too many to sort and merge here: each side's raw count (a shared edge may count
        # twice), for the vote only. It returned (0, 0): every such line voted outside, and a
        # point inside 129 nested shells was outside.
        ahead, _, _, _, _ = walk(nodes, node_bits, block_tri, blocks, ox, oy, oz, dx, dy, dz, np.float32(0.0),
                                 np.float32(np.inf), COLLECT, stack, stack_t, entries, answers, bt, btri, bu, bv, 0)
        return ahead, n - ahead, True
    ambiguous = False
    for i in range(n):
        if bu[i] == 0 or bv[i] == 0 or bu[i] + bv[i] >= 1 or abs(bt[i]) < gap:
            ambiguous = True
    sort_hits(bt, btri, bu, bv, n)
    kept = merge_crossings(bt, btri, bu, bv, n, gap)
    ahead = 0
    for i in range(kept):
        if bt[i] > 0:
            ahead += 1
    return ahead, kept - ahead, ambiguous or kept != n


@njit(cache=True, parallel=True)
def contains_kernel(nodes, node_bits, block_tri, blocks, points, center, scale, lo, hi, directions, gap,
                    out):
    """out (bool[n]): is each world point (f64[n,3]) inside the closed mesh. center (f64[3]),
    scale: the mesh's frame; lo, hi (f64[3]): the mesh's box in that frame (points outside it, or
    NaN, are outside without a cast). directions: f32[D,3] unit cast directions."""
    n = points.shape[0]
    chunk = 64
    for c in prange((n + chunk - 1) // chunk):
        stack, stack_t, entries, answers = new_stack()
        bt, btri, bu, bv = new_hit_buffers(CAP)
        for i in range(c * chunk, min(n, (c + 1) * chunk)):
            out[i] = False
            lx = (points[i, 0] - center[0]) / scale
            ly = (points[i, 1] - center[1]) / scale
            lz = (points[i, 2] - center[2]) / scale
            if not (lo[0] <= lx <= hi[0] and lo[1] <= ly <= hi[1] and lo[2] <= lz <= hi[2]):
                continue
            ox, oy, oz = np.float32(lx), np.float32(ly), np.float32(lz)
            votes = 0
            casts = 0
            decided = False
            for k in range(directions.shape[0]):
                ahead, behind, unclear = _line(nodes, node_bits, block_tri, blocks, ox, oy, oz,
                                               directions[k, 0], directions[k, 1], directions[k, 2],
                                               stack, stack_t, entries, answers, bt, btri, bu, bv, gap)
                p_forward = ahead % 2
                p_backward = behind % 2
                votes += p_forward + p_backward
                casts += 2
                if not unclear and p_forward == p_backward:
                    out[i] = p_forward == 1
                    decided = True
                    break
                if p_forward != p_backward and (ahead == 0 or behind == 0):
                    # trimesh's free-space rule: parities that disagree where one way meets no
                    # surface at all (an open mesh's hole) say outside.
                    decided = True
                    break
            if not decided:
                out[i] = 2 * votes > casts
