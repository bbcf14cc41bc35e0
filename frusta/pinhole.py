"""``pinhole``: frusta for primary rays, which all leave one eye point.

Overbeck, Ramamoorthi, Mark 2008, Section 4: the packet's frustum is bounded by its corner
rays. Here the corners are not taken from the tile's corner pixels but from the extremal rays:
along the packet's dominant axis, every live ray's direction slopes (u/w, v/w) are bounded, and
the four rays through the corners of that slope rectangle span the four side planes through
the eye. So the frustum holds every ray of the packet whatever the camera model, and is
widened by the margin of ``engine.packet.frustum_build``.

Invalid (no culling) for a packet whose live rays do not share one origin, whose directions
have no common dominant axis sign, or that has no live ray.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from engine.packet.frustum_build import apex_frustum, bounds_scale, farthest_corner
from engine.packet.kernels import longest_packet
from engine.packet.plugin import PacketFrustum
from engine.core.registry import register_frustum


@njit(cache=True, parallel=True)
def pinhole_frusta(org, dirs, tmin, tmax, offsets, bounds, n_chunks, planes, valid):
    """Fill planes (f32[K,4,4]) and valid (bool[K]) for rays org, dirs (f32[R,3]), tmin, tmax
    (f32[R]) in packets offsets (i32[K+1]); bounds: the scene box f32[2,3]."""
    n_packets = offsets.shape[0] - 1
    scene_scale = bounds_scale(bounds)
    for chunk in prange(n_chunks):
        g = np.empty((longest_packet(offsets), 3))
        apex = np.empty(3)
        for k in range(chunk, n_packets, n_chunks):
            valid[k] = False
            m = 0
            shared = True
            for r in range(offsets[k], offsets[k + 1]):
                if not tmin[r] <= tmax[r]:
                    continue
                if m == 0:
                    apex[0], apex[1], apex[2] = org[r, 0], org[r, 1], org[r, 2]
                elif org[r, 0] != apex[0] or org[r, 1] != apex[1] or org[r, 2] != apex[2]:
                    shared = False
                    break
                g[m, 0], g[m, 1], g[m, 2] = dirs[r, 0], dirs[r, 1], dirs[r, 2]
                m += 1
            if m == 0 or not shared:
                continue
            scale = max(scene_scale, max(abs(apex[0]), max(abs(apex[1]), abs(apex[2]))))
            reach = farthest_corner(apex[0], apex[1], apex[2], bounds)
            valid[k] = apex_frustum(apex, g, m, scale, reach, 0.0, planes[k])


@register_frustum("pinhole")
class PinholeFrustum(PacketFrustum):
    """Primary rays from one eye: four planes through the eye and the packet's extremal rays."""

    kernel = pinhole_frusta
