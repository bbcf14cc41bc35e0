"""``general``: frusta for reflection and refraction rays, which share no origin.

Overbeck, Ramamoorthi, Mark 2008, Section 4 (their new bound for secondary packets): along the
packet's dominant axis w, a near plane is put through the nearest segment start (so it lies
before the box of the ray origins) and a far plane beyond the scene box. Every live ray crosses
both; the extremal (u, v) of the crossings on each plane give the corner origins (on the near
plane) and corner directions (to the far plane) of four side planes, which hold every ray over
the whole stretch where it can meet geometry. Widened by the margin of ``engine.packet.frustum_build``.

Invalid (no culling) when the directions have no common dominant axis sign, a direction is
zero, or no ray is live.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from engine.packet.frustum_build import slab_frustum
from engine.packet.kernels import longest_packet
from engine.packet.plugin import PacketFrustum
from engine.core.registry import register_frustum


@njit(cache=True, parallel=True)
def general_frusta(org, dirs, tmin, tmax, offsets, bounds, n_chunks, planes, valid):
    """Fill planes (f32[K,4,4]) and valid (bool[K]) for rays org, dirs (f32[R,3]), tmin, tmax
    (f32[R]) in packets offsets (i32[K+1]); bounds: the scene box f32[2,3]."""
    n_packets = offsets.shape[0] - 1
    for chunk in prange(n_chunks):
        longest = longest_packet(offsets)
        p0 = np.empty((longest, 3))
        g = np.empty((longest, 3))
        for k in range(chunk, n_packets, n_chunks):
            valid[k] = False
            m = 0
            for r in range(offsets[k], offsets[k + 1]):
                if not tmin[r] <= tmax[r]:
                    continue
                for a in range(3):
                    g[m, a] = dirs[r, a]
                    p0[m, a] = org[r, a] + np.float64(tmin[r]) * dirs[r, a]
                m += 1
            if m > 0:
                valid[k] = slab_frustum(p0, g, m, bounds, planes[k])


@register_frustum("general")
class GeneralFrustum(PacketFrustum):
    """Reflection / refraction rays: side planes between a near plane before the origins and a far
    plane beyond the scene."""

    kernel = general_frusta
