"""Construction of packet frusta, shared by the frustum plugins (Overbeck et al. 2008, Section 4).

Every frustum here is built the paper's way, around a dominant axis w (one along which every
ray of the packet travels with the same strict sign s): on two planes across w -- a near one
at w' = s*w = wn and a far one at w' = wf -- the rays' crossing points fill the rectangles
[u0, u1] x [v0, v1] (u, v the other two axes), and the four side planes join the rectangles'
matching edges. Since u and v are linear in w' along a ray, every ray's part between the two
planes lies inside the side planes.

- Pinhole and point-light packets share one end point, the apex: the near rectangle is that
  point and the far one is the rays' direction slopes at unit distance (``apex_frustum``).
- Reflection and refraction packets have scattered origins: the near plane is placed at the
  origins' nearest w', the far one beyond the scene box (``slab_frustum``), so every part of
  a ray that can meet geometry lies between them.

All of this is float64. Each plane is then moved outwards by a margin -- FRUSTUM_SLACK times
the coordinate scale plus the ray length involved, plus any slack the caller knows of -- so
that the float32 plane tests and the float32 watertight triangle test, whose errors grow with
those magnitudes, can never disagree with the frustum: culling stays conservative.
A packet with no such axis, no live ray or degenerate rays gets no frustum (valid False).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Relative widening of every frustum. The watertight test decides the edge signs exactly for
#: the triangle as transformed into the ray's sheared frame, whose float32 rounding moves each
#: corner by at most about 12 ulp of its distance from the ray origin (< 1e-6 of the ray length);
#: the float32 planes and their evaluation err by a few ulp of the coordinate scale. 2^-16 (1.5e-5)
#: of (scale + ray length) is over ten times both.
FRUSTUM_SLACK = 2.0 ** -16


#: The extent of no vector yet, for ``grow_extent``.
EMPTY_EXTENT = (np.inf, np.inf, np.inf, -np.inf, -np.inf, -np.inf, 0.0, 0.0, 0.0)


@njit(cache=True, inline="always")
def grow_extent(lo_x, lo_y, lo_z, hi_x, hi_y, hi_z, sum_x, sum_y, sum_z, x, y, z):
    """The extent (lo x, y, z, hi x, y, z, sum x, y, z) of some vectors (from EMPTY_EXTENT),
    grown by the vector (x, y, z). The builders grow it in the pass that gathers their vectors,
    so picking the axis costs no pass of its own. They keep it in nine scalars, not a tuple:
    a tuple carried around the loop stays in memory (1.4-1.6x slower builds)."""
    return (min(lo_x, x), min(lo_y, y), min(lo_z, z), max(hi_x, x), max(hi_y, y), max(hi_z, z),
            sum_x + x, sum_y + y, sum_z + z)


@njit(cache=True, inline="always")
def dominant_axis(e):
    """Dominant axis of the vectors whose extent is e (``grow_extent``): (axis, sign) with
    sign * g[axis] > 0 for every vector g, the one (of those) along which their sum is longest;
    (-1, 0.0) when no axis has one strict sign for all of them (or a vector is not finite). Any
    such axis gives a correct frustum; the longest sum keeps the (u, v) slopes, and so the
    frustum, small."""
    if not (abs(e[6]) + abs(e[7]) + abs(e[8]) < np.inf):
        return -1, 0.0
    best_axis, best_sign, best_sum = _better_axis(-1, 0.0, 0.0, 0, e[0], e[3], e[6])
    best_axis, best_sign, best_sum = _better_axis(best_axis, best_sign, best_sum, 1, e[1], e[4], e[7])
    best_axis, best_sign, best_sum = _better_axis(best_axis, best_sign, best_sum, 2, e[2], e[5], e[8])
    return best_axis, best_sign


@njit(cache=True, inline="always")
def _better_axis(best_axis, best_sign, best_sum, axis, lo, hi, total):
    """``dominant_axis``'s step: axis (its vectors' components within lo .. hi, summing to total)
    replaces the best so far when every component has one strict sign and the sum is longer."""
    if (lo > 0.0 or hi < 0.0) and abs(total) > best_sum:
        return axis, (1.0 if lo > 0.0 else -1.0), abs(total)
    return best_axis, best_sign, best_sum


@njit(cache=True)
def side_planes(axis, sign, wn, wf, near_rect, far_rect, margin, out):
    """The four side planes joining the rectangles near_rect at w' = wn and far_rect at w' = wf
    (each a tuple u0, u1, v0, v1; w' = sign * coordinate[axis]; wf > wn) into out (f32[4,4]
    rows nx, ny, nz, d, inward), each moved outwards by ``margin``."""
    span = wf - wn
    for p in range(4):
        comp = (axis + 1 + p // 2) % 3  # u for planes 0, 1; v for 2, 3
        c = 1.0 if p % 2 == 0 else -1.0  # lower bound: coord >= edge; upper: coord <= edge
        slope = (far_rect[p] - near_rect[p]) / span
        # c * (coord - near - slope * (w' - wn)) >= 0, normalised.
        norm = math.sqrt(1.0 + slope * slope)
        for a in range(3):
            out[p, a] = 0.0
        out[p, comp] = c / norm
        out[p, axis] = -c * slope * sign / norm
        out[p, 3] = -c * (near_rect[p] - slope * wn) / norm + margin


@njit(cache=True)
def abs_max3(x, y, z):
    return max(abs(x), max(abs(y), abs(z)))


@njit(cache=True)
def bounds_scale(bounds):
    """Largest coordinate magnitude of the scene box (f32[2,3])."""
    s = 0.0
    for j in range(2):
        s = max(s, abs_max3(bounds[j, 0], bounds[j, 1], bounds[j, 2]))
    return s


@njit(cache=True)
def farthest_corner(px, py, pz, bounds):
    """Distance from (px, py, pz) to the farthest corner of the scene box (f32[2,3])."""
    dx = max(abs(bounds[0, 0] - px), abs(bounds[1, 0] - px))
    dy = max(abs(bounds[0, 1] - py), abs(bounds[1, 1] - py))
    dz = max(abs(bounds[0, 2] - pz), abs(bounds[1, 2] - pz))
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True)
def apex_frustum(apex, g, m, extent, scale, reach, extra, out):
    """Frustum from the point apex (f64[3]) along the m vectors g[:m] (f64[>=m,3]) of extent
    ``extent`` (``grow_extent``): the rays apex + s g[i], s >= 0. ``scale`` is the largest
    coordinate magnitude involved, ``reach`` the longest ray length that matters, ``extra``
    slack the caller adds. Writes out (f32[4,4]); returns False (out untouched) when there is
    no dominant axis."""
    axis, sign = dominant_axis(extent)
    if axis < 0:
        return False
    u = (axis + 1) % 3
    v = (axis + 2) % 3
    lo_u = np.inf
    hi_u = -np.inf
    lo_v = np.inf
    hi_v = -np.inf
    for i in range(m):
        inv_w = sign / g[i, axis]
        lo_u = min(lo_u, g[i, u] * inv_w)
        hi_u = max(hi_u, g[i, u] * inv_w)
        lo_v = min(lo_v, g[i, v] * inv_w)
        hi_v = max(hi_v, g[i, v] * inv_w)
    apex_planes(apex, axis, sign, lo_u, hi_u, lo_v, hi_v, scale, reach, extra, out)
    return True


@njit(cache=True)
def apex_planes(apex, axis, sign, lo_u, hi_u, lo_v, hi_v, scale, reach, extra, out):
    """``apex_frustum``'s planes from the slope bounds lo_u .. hi_v of its vectors along
    ``axis`` (sign: their sign along it) into out (f32[4,4])."""
    u = (axis + 1) % 3
    v = (axis + 2) % 3
    near_rect = (apex[u], apex[u], apex[v], apex[v])
    far_rect = (apex[u] + lo_u, apex[u] + hi_u, apex[v] + lo_v, apex[v] + hi_v)
    wn = sign * apex[axis]
    side_planes(axis, sign, wn, wn + 1.0, near_rect, far_rect,
                FRUSTUM_SLACK * (scale + reach) + extra, out)


@njit(cache=True, inline="always")
def slab_far(axis, sign, wn, w_start_far, scale, bounds):
    """The far plane w' = wf of a slab frustum: beyond the scene box (f32[2,3]) and the farthest
    start w_start_far; wn: the nearest start, scale: the largest coordinate magnitude."""
    wf = max(max(sign * bounds[0, axis], sign * bounds[1, axis]), w_start_far)
    if not wf > wn:
        # Every start lies on one plane with the whole scene behind it: any positive span will do.
        wf = wn + 1.0 + scale
    return wf


@njit(cache=True, inline="always")
def slab_crossings(px, py, pz, gx, gy, gz, axis, sign, wn, wf):
    """Where the ray from start (px, py, pz) along (gx, gy, gz) (f64) crosses a slab frustum's
    near plane w' = wn and far plane w' = wf across ``axis`` (w' = sign * coordinate): (u, v on
    the near plane, u, v on the far plane, the squared length of the ray between the planes).
    Shared by ``slab_frustum`` and the ray-by-ray tail of the eight-ray builder, whose vector
    pass (``engine.packet.frustum8.slab_rects_blocks8``) computes the same expressions."""
    p = (px, py, pz)
    g = (gx, gy, gz)
    u = (axis + 1) % 3
    v = (axis + 2) % 3
    w0 = sign * p[axis]
    inv_w = sign / g[axis]
    tn = (wn - w0) * inv_w
    tf = (wf - w0) * inv_w
    return (p[u] + tn * g[u], p[v] + tn * g[v], p[u] + tf * g[u], p[v] + tf * g[v],
            (tf - tn) * (tf - tn) * (gx * gx + gy * gy + gz * gz))


@njit(cache=True)
def slab_frustum(p0, g, m, extent, bounds, out):
    """Frustum around m rays with scattered starts p0[:m] and directions g[:m] (f64[>=m,3], of
    extent ``extent``: ``grow_extent``) whose geometry lies in the scene box ``bounds``
    (f32[2,3]): near plane through the nearest start, far plane beyond the box. Writes out
    (f32[4,4]); False when there is no dominant axis."""
    axis, sign = dominant_axis(extent)
    if axis < 0:
        return False
    scale = bounds_scale(bounds)
    wn = np.inf
    w_start_far = -np.inf
    for i in range(m):
        w = sign * p0[i, axis]
        wn = min(wn, w)
        w_start_far = max(w_start_far, w)
        scale = max(scale, abs_max3(p0[i, 0], p0[i, 1], p0[i, 2]))
    wf = slab_far(axis, sign, wn, w_start_far, scale, bounds)
    un0 = vn0 = uf0 = vf0 = np.inf
    un1 = vn1 = uf1 = vf1 = -np.inf
    reach2 = 0.0
    for i in range(m):
        un, vn, uf, vf, length2 = slab_crossings(p0[i, 0], p0[i, 1], p0[i, 2], g[i, 0], g[i, 1], g[i, 2], axis,
                                                 sign, wn, wf)
        un0, un1, vn0, vn1 = min(un0, un), max(un1, un), min(vn0, vn), max(vn1, vn)
        uf0, uf1, vf0, vf1 = min(uf0, uf), max(uf1, uf), min(vf0, vf), max(vf1, vf)
        reach2 = max(reach2, length2)
    near_rect = (un0, un1, vn0, vn1)
    far_rect = (uf0, uf1, vf0, vf1)
    side_planes(axis, sign, wn, wf, near_rect, far_rect, FRUSTUM_SLACK * (scale + math.sqrt(reach2)), out)
    return True
