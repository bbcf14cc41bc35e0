"""The ``auto`` traversal's choice: which strategy walks a packet, from cheap measures of it.

Overbeck, Ramamoorthi and Mark (2008) find Ranged faster on coherent packets (one box test
usually decides a node) and Partition faster once coherence falls (Ranged's index range fills
with rays that miss). The ``auto`` strategy of ``engine.packet.walk`` asks ``choose_packet``
per packet, as it is loaded, and then walks it with the answer as a compile-time constant.

The measures (``packet_measures``), over the packet's live rays only:

- ``live``: the fraction of its lanes that are live (tmin <= tmax);
- ``footprint``: how wide the packet is, relative to the scene: (diagonal of the box around
  its origins + 2 sin(cone half-angle) * reach) / scene diagonal, where the cone is the
  smallest one around the mean of the normalised directions that holds every direction and
  ``reach`` is the mean segment length clipped to the scene diagonal. A camera packet has
  footprint ~ its angular size (one origin); a reflection packet off a curved surface, or a
  shadow packet whose origins lie on surfaces far apart, a large one.
- ``valid``: whether the packet has a frustum (the packet's ``Frusta.valid``).

The rule (``choose_packet``), with the thresholds of ``LIMITS`` (fitted by
``tools/fit_auto.py``; ``engine/packet/auto_thresholds.json``):

    no frustum                                       -> INVALID_CHOICE (a strategy number)
    live >= MIN_LIVE and footprint <= MASKED_MAX     -> MASKED
    live >= MIN_LIVE and footprint <= RANGED_MAX     -> RANGED
    otherwise                                        -> PARTITION

limits: f64[N_LIMITS] indexed by RANGED_MAX, MASKED_MAX, MIN_LIVE, INVALID_CHOICE.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from engine.packet.strategies import MASKED, PARTITION, RANGED

RANGED_MAX, MASKED_MAX, MIN_LIVE, INVALID_CHOICE = range(4)
N_LIMITS = 4
#: The names of the limits, in order (the keys of the thresholds file and the plugin's options).
LIMIT_NAMES = ("ranged_max_footprint", "masked_max_footprint", "min_live", "invalid_frustum")


@njit(cache=True, inline="always")
def packet_measures(org, dirs, tmin, tmax, start, n, diagonal):
    """(live, footprint) of rays start .. start+n (org, dirs f32[R,3]; tmin, tmax f32[R]) in a
    scene whose box diagonal is ``diagonal`` (see the module doc); (0, 0) with no live ray."""
    live = 0
    mx, my, mz = 0.0, 0.0, 0.0
    lo_x, lo_y, lo_z = np.inf, np.inf, np.inf
    hi_x, hi_y, hi_z = -np.inf, -np.inf, -np.inf
    reach = 0.0
    for r in range(start, start + n):
        if not tmin[r] <= tmax[r]:
            continue
        live += 1
        dx, dy, dz = float(dirs[r, 0]), float(dirs[r, 1]), float(dirs[r, 2])
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        if norm > 0.0:
            mx += dx / norm
            my += dy / norm
            mz += dz / norm
        ox, oy, oz = float(org[r, 0]), float(org[r, 1]), float(org[r, 2])
        lo_x, lo_y, lo_z = min(lo_x, ox), min(lo_y, oy), min(lo_z, oz)
        hi_x, hi_y, hi_z = max(hi_x, ox), max(hi_y, oy), max(hi_z, oz)
        if norm > 0.0:
            reach += min((float(tmax[r]) - float(tmin[r])) * norm, diagonal)
    if live == 0:
        return 0.0, 0.0
    # The cone around the mean direction: its half-angle's cosine is the least dot product.
    mean = math.sqrt(mx * mx + my * my + mz * mz)
    least = 1.0
    if mean > 0.0:
        for r in range(start, start + n):
            if not tmin[r] <= tmax[r]:
                continue
            dx, dy, dz = float(dirs[r, 0]), float(dirs[r, 1]), float(dirs[r, 2])
            norm = math.sqrt(dx * dx + dy * dy + dz * dz)
            if norm > 0.0:
                least = min(least, (dx * mx + dy * my + dz * mz) / (norm * mean))
    else:
        least = -1.0
    least = max(-1.0, least)
    # A cone wider than a hemisphere spreads as far as a hemisphere (sine 1).
    sine = math.sqrt(max(0.0, 1.0 - least * least)) if least > 0.0 else 1.0
    spread = math.sqrt((hi_x - lo_x) ** 2 + (hi_y - lo_y) ** 2 + (hi_z - lo_z) ** 2)
    footprint = (spread + 2.0 * sine * reach / live) / max(diagonal, 1e-30)
    return live / max(n, 1), footprint


@njit(cache=True, inline="always")
def scene_diagonal(bmin, bmax):
    """The diagonal of the BVH's root box (bmin, bmax f32[N,3])."""
    dx = float(bmax[0, 0]) - float(bmin[0, 0])
    dy = float(bmax[0, 1]) - float(bmin[0, 1])
    dz = float(bmax[0, 2]) - float(bmin[0, 2])
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True, inline="always")
def choose_by_measures(live, footprint, valid, limits):
    """The strategy for a packet of measures (live, footprint, valid) under ``limits``."""
    if not valid:
        return int(limits[INVALID_CHOICE])
    if live >= limits[MIN_LIVE]:
        if footprint <= limits[MASKED_MAX]:
            return MASKED
        if footprint <= limits[RANGED_MAX]:
            return RANGED
    return PARTITION


@njit(cache=True, inline="always")
def choose_packet(org, dirs, tmin, tmax, start, n, valid, diagonal, limits):
    """The strategy (MASKED, RANGED or PARTITION) that walks rays start .. start+n, whose
    frustum is ``valid``, under ``limits`` f64[N_LIMITS] (see the module doc)."""
    live, footprint = packet_measures(org, dirs, tmin, tmax, start, n, diagonal)
    return choose_by_measures(live, footprint, valid, limits)


@njit(cache=True, parallel=True)
def measure_packets(bmin, bmax, org, dirs, tmin, tmax, offsets, live_out, footprint_out):
    """Every packet's measures (for the fit and ``packetrt show``): live_out, footprint_out
    f64[K] for the packets offsets i32[K+1] of the rays, in a scene of BVH boxes bmin, bmax."""
    diagonal = scene_diagonal(bmin, bmax)
    for k in prange(offsets.shape[0] - 1):
        start = offsets[k]
        live_out[k], footprint_out[k] = packet_measures(org, dirs, tmin, tmax, start, offsets[k + 1] - start,
                                                        diagonal)


@njit(cache=True)
def choose_packets(bmin, bmax, org, dirs, tmin, tmax, offsets, valid, limits, out):
    """out i8[K] := the strategy ``auto`` walks each packet with (as ``choose_packet``)."""
    diagonal = scene_diagonal(bmin, bmax)
    for k in range(offsets.shape[0] - 1):
        start = offsets[k]
        out[k] = choose_packet(org, dirs, tmin, tmax, start, offsets[k + 1] - start, valid[k], diagonal, limits)
