"""The frustum builders' one kernel: what each builder takes from a packet's rays, then the
construction of ``engine.packet.frustum_build`` (Overbeck et al. 2008, Section 4).

``build_frusta(builder, ...)`` deals the packets to the threads in interleaved decks, as the
packet walk does, and per packet gathers its live rays as the builder needs them:

- ``PINHOLE`` (``frusta/pinhole.py``): primary rays sharing one origin, the apex; the frustum
  spans their directions from it. None when the live rays do not share one origin.
- ``POINTLIGHT`` (``frusta/pointlight.py``): shadow rays that end at one light, the first live
  ray's end point org + tmax dir (every end point within END_SPREAD times the shortest ray of
  it); the frustum spans, from the light, the vectors back to the segment starts, widened by
  the end points' spread.
- ``GENERAL`` (``frusta/general.py``): reflection and refraction rays with scattered segment
  starts; the slab frustum between a near plane before the starts and a far one beyond the
  scene.
- ``PINHOLE_OR_GENERAL`` (the mesh queries of ``engine.query.coherent``, whose rays may or may
  not come from one point): ``PINHOLE`` where the packet's live rays share one origin, else
  ``GENERAL``.

A packet with no live ray, or whose rays fail its builder's condition, gets no frustum
(valid False). The builder is a run-time number, tested once per packet (nothing next to the
pass over its rays): one disk-cached kernel serves all three.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from engine.core.lanes8 import rows_of_three
from engine.packet import frustum8
from engine.packet.frustum_build import (EMPTY_EXTENT, FRUSTUM_SLACK, abs_max3, apex_frustum, apex_planes,
                                         bounds_scale, dominant_axis, farthest_corner, grow_extent, side_planes,
                                         slab_crossings, slab_far, slab_frustum)
from engine.packet.frustum8 import gather_blocks8, slab_gather_blocks8, slab_rects_blocks8, slopes_blocks8
from engine.packet.kernels import longest_packet

PINHOLE, POINTLIGHT, GENERAL, PINHOLE_OR_GENERAL = range(4)
assert (frustum8.PINHOLE, frustum8.POINTLIGHT) == (PINHOLE, POINTLIGHT)

#: How far the end points of a shadow packet may scatter around the first one, relative to the
#: shortest ray, for the rays to count as meeting at one light.
END_SPREAD = 1e-2


@njit(cache=True, inline="always")
def first_live_ray(tmin, tmax, lo, hi):
    """The first of rays lo .. hi-1 with tmin <= tmax, or -1."""
    for r in range(lo, hi):
        if tmin[r] <= tmax[r]:
            return r
    return -1


@njit(cache=True, inline="always")
def packet_light(org, dirs, tmin, tmax, lo, hi, light):
    """The light a shadow packet's rays meet, taken as the end point org + tmax dir of its first
    live ray, into light (f64[3]); False when no ray is live or that end is not finite (a ray
    without an end meets no light)."""
    first_live = first_live_ray(tmin, tmax, lo, hi)
    if first_live < 0:
        return False
    for a in range(3):
        light[a] = org[first_live, a] + np.float64(tmax[first_live]) * dirs[first_live, a]
    return math.isfinite(light[0]) and math.isfinite(light[1]) and math.isfinite(light[2])


@njit(cache=True, inline="always")
def apex_vector(mode, org, dirs, tmin, r, ax, ay, az):
    """Ray r's vector g from the apex (ax, ay, az), float64: its direction (PINHOLE) or its
    segment start minus the light (POINTLIGHT), as the scalar builders gather it."""
    if mode == POINTLIGHT:
        t = np.float64(tmin[r])
        return (org[r, 0] + t * dirs[r, 0] - ax, org[r, 1] + t * dirs[r, 1] - ay, org[r, 2] + t * dirs[r, 2] - az)
    return np.float64(dirs[r, 0]), np.float64(dirs[r, 1]), np.float64(dirs[r, 2])


@njit(cache=True, inline="always")
def gather_apex(mode, org, dirs, tmin, tmax, lo, hi, ax, ay, az):
    """The first pass of an apex frustum over rays lo .. hi-1, eight at a time
    (``engine.packet.frustum8.gather_blocks8``) and the rest one by one: (live rays, whether a
    live ray misses the apex (PINHOLE), the extent of their vectors g as nine scalars, and for
    POINTLIGHT the largest squared end-point spread, the shortest and longest squared g, the
    largest origin coordinate)."""
    blocks = (hi - lo) // 8
    m, away, e0, e1, e2, e3, e4, e5, e6, e7, e8, spread2, shortest2, reach2, scale = gather_blocks8(
        mode, org, dirs, tmin, tmax, lo, blocks, ax, ay, az)
    foreign = away != 0
    r = lo + 8 * blocks
    while r < hi:
        if tmin[r] <= tmax[r]:
            gx, gy, gz = apex_vector(mode, org, dirs, tmin, r, ax, ay, az)
            e0, e1, e2, e3, e4, e5, e6, e7, e8 = grow_extent(e0, e1, e2, e3, e4, e5, e6, e7, e8, gx, gy, gz)
            if mode == PINHOLE and (org[r, 0] != ax or org[r, 1] != ay or org[r, 2] != az):
                foreign = True
            if mode == POINTLIGHT:
                t = np.float64(tmax[r])
                ex = org[r, 0] + t * dirs[r, 0] - ax
                ey = org[r, 1] + t * dirs[r, 1] - ay
                ez = org[r, 2] + t * dirs[r, 2] - az
                spread2 = max(spread2, ex * ex + ey * ey + ez * ez)
                length2 = gx * gx + gy * gy + gz * gz
                shortest2 = min(shortest2, length2)
                reach2 = max(reach2, length2)
                scale = max(scale, abs_max3(org[r, 0], org[r, 1], org[r, 2]))
            m += 1
        r += 1
    return m, foreign, e0, e1, e2, e3, e4, e5, e6, e7, e8, spread2, shortest2, reach2, scale


@njit(cache=True, inline="always")
def apex_slopes(mode, org, dirs, tmin, tmax, lo, hi, ax, ay, az, axis, sign):
    """The second pass of an apex frustum: (lo u, hi u, lo v, hi v), the bounds of the live rays'
    slopes along ``axis`` (``apex_frustum``'s loop), eight rays at a time
    (``engine.packet.frustum8.slopes_blocks8``) and the rest one by one."""
    u = (axis + 1) % 3
    v = (axis + 2) % 3
    blocks = (hi - lo) // 8
    lo_u, hi_u, lo_v, hi_v = slopes_blocks8(mode, org, dirs, tmin, tmax, lo, blocks, ax, ay, az, axis, sign)
    r = lo + 8 * blocks
    while r < hi:
        if tmin[r] <= tmax[r]:
            g = apex_vector(mode, org, dirs, tmin, r, ax, ay, az)
            inv_w = sign / g[axis]
            lo_u = min(lo_u, g[u] * inv_w)
            hi_u = max(hi_u, g[u] * inv_w)
            lo_v = min(lo_v, g[v] * inv_w)
            hi_v = max(hi_v, g[v] * inv_w)
        r += 1
    return lo_u, hi_u, lo_v, hi_v


@njit(cache=True, inline="always")
def eight_at_a_time(org, dirs, lo, hi):
    """Whether a packet's frustum passes go eight rays at a time: a packet of at least eight
    rays whose rows are 12 contiguous bytes."""
    return hi - lo >= 8 and rows_of_three(org) and rows_of_three(dirs)


@njit(cache=True)
def pinhole_frustum8(org, dirs, tmin, tmax, lo, hi, bounds, scene_scale, apex, plane):
    """``pinhole_frustum`` in two passes eight rays at a time, without the gathered vectors.
    Called, not inlined: once per packet, and numba's inliner copied it into every builder branch
    (``build_frusta`` compiled in 16.8 s instead of 6.8)."""
    first_live = first_live_ray(tmin, tmax, lo, hi)
    if first_live < 0:
        return False
    apex[0], apex[1], apex[2] = org[first_live, 0], org[first_live, 1], org[first_live, 2]
    m, foreign, e0, e1, e2, e3, e4, e5, e6, e7, e8, _, _, _, _ = gather_apex(
        PINHOLE, org, dirs, tmin, tmax, lo, hi, apex[0], apex[1], apex[2])
    if foreign:
        return False
    scale = max(scene_scale, abs_max3(apex[0], apex[1], apex[2]))
    reach = farthest_corner(apex[0], apex[1], apex[2], bounds)
    axis, sign = dominant_axis((e0, e1, e2, e3, e4, e5, e6, e7, e8))
    if axis < 0:
        return False
    lo_u, hi_u, lo_v, hi_v = apex_slopes(PINHOLE, org, dirs, tmin, tmax, lo, hi, apex[0], apex[1], apex[2],
                                         axis, sign)
    apex_planes(apex, axis, sign, lo_u, hi_u, lo_v, hi_v, scale, reach, 0.0, plane)
    return True


@njit(cache=True)
def pointlight_frustum8(org, dirs, tmin, tmax, lo, hi, scene_scale, light, plane):
    """``pointlight_frustum`` in two passes eight rays at a time, without the gathered vectors."""
    if not packet_light(org, dirs, tmin, tmax, lo, hi, light):
        return False
    m, _, e0, e1, e2, e3, e4, e5, e6, e7, e8, spread2, shortest2, reach2, origins = gather_apex(
        POINTLIGHT, org, dirs, tmin, tmax, lo, hi, light[0], light[1], light[2])
    scale = max(max(scene_scale, abs_max3(light[0], light[1], light[2])), origins)
    if not spread2 <= END_SPREAD * END_SPREAD * shortest2:
        return False
    axis, sign = dominant_axis((e0, e1, e2, e3, e4, e5, e6, e7, e8))
    if axis < 0:
        return False
    lo_u, hi_u, lo_v, hi_v = apex_slopes(POINTLIGHT, org, dirs, tmin, tmax, lo, hi, light[0], light[1], light[2],
                                         axis, sign)
    apex_planes(light, axis, sign, lo_u, hi_u, lo_v, hi_v, scale, math.sqrt(reach2), math.sqrt(spread2), plane)
    return True


@njit(cache=True, inline="always")
def pinhole_frustum(org, dirs, tmin, tmax, lo, hi, bounds, scene_scale, g, apex, plane):
    """Frustum of rays lo .. hi-1 from one eye into plane (f32[4,4]); False when there is none.
    Scratch: g f64[>= hi-lo, 3] the live directions, apex f64[3]."""
    if eight_at_a_time(org, dirs, lo, hi):
        return pinhole_frustum8(org, dirs, tmin, tmax, lo, hi, bounds, scene_scale, apex, plane)
    m = 0
    e0, e1, e2, e3, e4, e5, e6, e7, e8 = EMPTY_EXTENT
    for r in range(lo, hi):
        if not tmin[r] <= tmax[r]:
            continue
        if m == 0:
            apex[0], apex[1], apex[2] = org[r, 0], org[r, 1], org[r, 2]
        elif org[r, 0] != apex[0] or org[r, 1] != apex[1] or org[r, 2] != apex[2]:
            return False
        x, y, z = np.float64(dirs[r, 0]), np.float64(dirs[r, 1]), np.float64(dirs[r, 2])
        g[m, 0], g[m, 1], g[m, 2] = x, y, z
        e0, e1, e2, e3, e4, e5, e6, e7, e8 = grow_extent(e0, e1, e2, e3, e4, e5, e6, e7, e8, x, y, z)
        m += 1
    if m == 0:
        return False
    scale = max(scene_scale, abs_max3(apex[0], apex[1], apex[2]))
    reach = farthest_corner(apex[0], apex[1], apex[2], bounds)
    return apex_frustum(apex, g, m, (e0, e1, e2, e3, e4, e5, e6, e7, e8), scale, reach, 0.0, plane)


@njit(cache=True, inline="always")
def pointlight_frustum(org, dirs, tmin, tmax, lo, hi, scene_scale, g, light, plane):
    """Frustum of shadow rays lo .. hi-1 towards one point light into plane (f32[4,4]); False
    when there is none. Scratch: g f64[>= hi-lo, 3] the vectors light -> segment start, light
    f64[3]."""
    if eight_at_a_time(org, dirs, lo, hi):
        return pointlight_frustum8(org, dirs, tmin, tmax, lo, hi, scene_scale, light, plane)
    # The light: the end point of the first live ray (the others' spread is measured below).
    if not packet_light(org, dirs, tmin, tmax, lo, hi, light):
        return False
    # Squared lengths: one root per packet, not per ray.
    spread2 = 0.0
    shortest2 = np.inf
    reach2 = 0.0
    scale = max(scene_scale, abs_max3(light[0], light[1], light[2]))
    m = 0
    e0, e1, e2, e3, e4, e5, e6, e7, e8 = EMPTY_EXTENT
    for r in range(lo, hi):
        if not tmin[r] <= tmax[r]:
            continue
        ex = org[r, 0] + np.float64(tmax[r]) * dirs[r, 0] - light[0]
        ey = org[r, 1] + np.float64(tmax[r]) * dirs[r, 1] - light[1]
        ez = org[r, 2] + np.float64(tmax[r]) * dirs[r, 2] - light[2]
        spread2 = max(spread2, ex * ex + ey * ey + ez * ez)
        for a in range(3):
            # Vector from the light back to where the ray's segment starts.
            g[m, a] = org[r, a] + np.float64(tmin[r]) * dirs[r, a] - light[a]
        length2 = g[m, 0] * g[m, 0] + g[m, 1] * g[m, 1] + g[m, 2] * g[m, 2]
        e0, e1, e2, e3, e4, e5, e6, e7, e8 = grow_extent(e0, e1, e2, e3, e4, e5, e6, e7, e8,
                                                         g[m, 0], g[m, 1], g[m, 2])
        shortest2 = min(shortest2, length2)
        reach2 = max(reach2, length2)
        scale = max(scale, abs_max3(org[r, 0], org[r, 1], org[r, 2]))
        m += 1
    if not spread2 <= END_SPREAD * END_SPREAD * shortest2:
        return False
    return apex_frustum(light, g, m, (e0, e1, e2, e3, e4, e5, e6, e7, e8), scale, math.sqrt(reach2),
                        math.sqrt(spread2), plane)


@njit(cache=True)
def general_frustum8(org, dirs, tmin, tmax, lo, hi, bounds, plane):
    """``general_frustum`` in two passes eight rays at a time (``engine.packet.frustum8``),
    without the gathered vectors: the first takes the directions' extent and the starts' bounds
    (from which the near plane, the far plane and the coordinate scale follow), the second the
    rectangles where the rays cross the two planes. Called, not inlined, as ``pinhole_frustum8``."""
    blocks = (hi - lo) // 8
    m, e0, e1, e2, e3, e4, e5, e6, e7, e8, p_lo_x, p_lo_y, p_lo_z, p_hi_x, p_hi_y, p_hi_z, largest = \
        slab_gather_blocks8(org, dirs, tmin, tmax, lo, blocks)
    for r in range(lo + 8 * blocks, hi):
        if not tmin[r] <= tmax[r]:
            continue
        gx, gy, gz = np.float64(dirs[r, 0]), np.float64(dirs[r, 1]), np.float64(dirs[r, 2])
        t = np.float64(tmin[r])
        px, py, pz = org[r, 0] + t * gx, org[r, 1] + t * gy, org[r, 2] + t * gz
        e0, e1, e2, e3, e4, e5, e6, e7, e8 = grow_extent(e0, e1, e2, e3, e4, e5, e6, e7, e8, gx, gy, gz)
        p_lo_x, p_lo_y, p_lo_z = min(p_lo_x, px), min(p_lo_y, py), min(p_lo_z, pz)
        p_hi_x, p_hi_y, p_hi_z = max(p_hi_x, px), max(p_hi_y, py), max(p_hi_z, pz)
        largest = max(largest, abs_max3(px, py, pz))
        m += 1
    if m == 0:
        return False
    axis, sign = dominant_axis((e0, e1, e2, e3, e4, e5, e6, e7, e8))
    if axis < 0:
        return False
    # The starts' nearest and farthest w' = sign * p[axis]: sign -1 turns their minimum into
    # minus the maximum, exactly.
    p_lo = p_lo_x if axis == 0 else (p_lo_y if axis == 1 else p_lo_z)
    p_hi = p_hi_x if axis == 0 else (p_hi_y if axis == 1 else p_hi_z)
    wn, w_start_far = (p_lo, p_hi) if sign > 0 else (-p_hi, -p_lo)
    scale = max(bounds_scale(bounds), largest)
    wf = slab_far(axis, sign, wn, w_start_far, scale, bounds)
    un0, un1, vn0, vn1, uf0, uf1, vf0, vf1, reach2 = slab_rects_blocks8(org, dirs, tmin, tmax, lo, blocks, axis,
                                                                        sign, wn, wf)
    for r in range(lo + 8 * blocks, hi):
        if not tmin[r] <= tmax[r]:
            continue
        t = np.float64(tmin[r])
        gx, gy, gz = np.float64(dirs[r, 0]), np.float64(dirs[r, 1]), np.float64(dirs[r, 2])
        un, vn, uf, vf, length2 = slab_crossings(org[r, 0] + t * gx, org[r, 1] + t * gy, org[r, 2] + t * gz,
                                                 gx, gy, gz, axis, sign, wn, wf)
        un0, un1, vn0, vn1 = min(un0, un), max(un1, un), min(vn0, vn), max(vn1, vn)
        uf0, uf1, vf0, vf1 = min(uf0, uf), max(uf1, uf), min(vf0, vf), max(vf1, vf)
        reach2 = max(reach2, length2)
    side_planes(axis, sign, wn, wf, (un0, un1, vn0, vn1), (uf0, uf1, vf0, vf1),
                FRUSTUM_SLACK * (scale + math.sqrt(reach2)), plane)
    return True


@njit(cache=True, inline="always")
def general_frustum(org, dirs, tmin, tmax, lo, hi, bounds, g, p0, plane):
    """Slab frustum of rays lo .. hi-1 into plane (f32[4,4]); False when there is none.
    Scratch: g, p0 f64[>= hi-lo, 3] the live directions and segment starts."""
    if eight_at_a_time(org, dirs, lo, hi):
        return general_frustum8(org, dirs, tmin, tmax, lo, hi, bounds, plane)
    m = 0
    e0, e1, e2, e3, e4, e5, e6, e7, e8 = EMPTY_EXTENT
    for r in range(lo, hi):
        if not tmin[r] <= tmax[r]:
            continue
        for a in range(3):
            g[m, a] = dirs[r, a]
            p0[m, a] = org[r, a] + np.float64(tmin[r]) * dirs[r, a]
        e0, e1, e2, e3, e4, e5, e6, e7, e8 = grow_extent(e0, e1, e2, e3, e4, e5, e6, e7, e8,
                                                         g[m, 0], g[m, 1], g[m, 2])
        m += 1
    return m > 0 and slab_frustum(p0, g, m, (e0, e1, e2, e3, e4, e5, e6, e7, e8), bounds, plane)


@njit(cache=True, parallel=True)
def build_frusta(builder, org, dirs, tmin, tmax, offsets, bounds, n_chunks, planes, valid):
    """Fill planes (f32[K,4,4]) and valid (bool[K]) by ``builder`` for rays org, dirs (f32[R,3]),
    tmin, tmax (f32[R]) in packets offsets (i32[K+1]); bounds: the scene box f32[2,3]; n_chunks
    the packet decks."""
    n_packets = offsets.shape[0] - 1
    scene_scale = bounds_scale(bounds)
    for chunk in prange(n_chunks):
        longest = longest_packet(offsets)
        g = np.empty((longest, 3))
        p0 = np.empty((longest, 3))
        point = np.empty(3)
        for k in range(chunk, n_packets, n_chunks):
            lo, hi = offsets[k], offsets[k + 1]
            if builder == PINHOLE or builder == PINHOLE_OR_GENERAL:
                valid[k] = pinhole_frustum(org, dirs, tmin, tmax, lo, hi, bounds, scene_scale, g, point, planes[k])
                if builder == PINHOLE_OR_GENERAL and not valid[k]:
                    valid[k] = general_frustum(org, dirs, tmin, tmax, lo, hi, bounds, g, p0, planes[k])
            elif builder == POINTLIGHT:
                valid[k] = pointlight_frustum(org, dirs, tmin, tmax, lo, hi, scene_scale, g, point, planes[k])
            else:
                valid[k] = general_frustum(org, dirs, tmin, tmax, lo, hi, bounds, g, p0, planes[k])
