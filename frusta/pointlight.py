"""``pointlight``: frusta for shadow rays towards one point light.

Overbeck, Ramamoorthi, Mark 2008, Section 4: shadow rays to a point light share the light as a
common point, so their frustum is the pinhole frustum seen from the light. In packetrt a shadow
ray starts at the surface and runs towards the light, stopping at tmax just short of it, so the
light is recovered as the end point org + tmax dir of the packet's first live ray. From it,
along the dominant axis of the vectors light -> segment start, the extremal (u, v) slopes at unit
distance give the four corner rays and the side planes through the light. The planes are widened
by the spread of the end points around the light (the rays stop a little short, by different
amounts) on top of the margin of ``engine.packet.frustum_build``.

Invalid (no culling) when the rays do not meet at one point (end points more than END_SPREAD of
the shortest ray from the first one, or an infinite tmax), have no common dominant axis sign, are
degenerate (a ray starting at the light), or none is live.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from engine.packet.frustum_build import abs_max3, apex_frustum, bounds_scale
from engine.packet.kernels import longest_packet
from engine.packet.plugin import PacketFrustum
from engine.core.registry import register_frustum

#: How far the end points may scatter around the first one, relative to the shortest ray, for
#: the rays to count as meeting at one light.
END_SPREAD = 1e-2


@njit(cache=True, parallel=True)
def pointlight_frusta(org, dirs, tmin, tmax, offsets, bounds, n_chunks, planes, valid):
    """Fill planes (f32[K,4,4]) and valid (bool[K]) for shadow rays org, dirs (f32[R,3]), tmin,
    tmax (f32[R]) in packets offsets (i32[K+1]); bounds: the scene box f32[2,3]."""
    n_packets = offsets.shape[0] - 1
    scene_scale = bounds_scale(bounds)
    for chunk in prange(n_chunks):
        g = np.empty((longest_packet(offsets), 3))
        light = np.empty(3)
        for k in range(chunk, n_packets, n_chunks):
            valid[k] = False
            # The light: the end point of the first live ray (the others' spread is measured below).
            m = 0
            for r in range(offsets[k], offsets[k + 1]):
                if tmin[r] <= tmax[r]:
                    for a in range(3):
                        light[a] = org[r, a] + np.float64(tmax[r]) * dirs[r, a]
                    m = 1
                    break
            if m == 0:
                continue
            if not (math.isfinite(light[0]) and math.isfinite(light[1]) and math.isfinite(light[2])):
                continue  # a ray without an end (infinite tmax) meets no light
            # Squared lengths: one root per packet, not per ray.
            spread2 = 0.0
            shortest2 = np.inf
            reach2 = 0.0
            scale = max(scene_scale, abs_max3(light[0], light[1], light[2]))
            m = 0
            for r in range(offsets[k], offsets[k + 1]):
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
                shortest2 = min(shortest2, length2)
                reach2 = max(reach2, length2)
                scale = max(scale, abs_max3(org[r, 0], org[r, 1], org[r, 2]))
                m += 1
            if not spread2 <= END_SPREAD * END_SPREAD * shortest2:
                continue
            spread = math.sqrt(spread2)
            valid[k] = apex_frustum(light, g, m, scale, math.sqrt(reach2), spread, planes[k])


@register_frustum("pointlight")
class PointLightFrustum(PacketFrustum):
    """Shadow rays towards one point light: four planes through the light and the extremal rays."""

    kernel = pointlight_frusta
