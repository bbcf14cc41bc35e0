"""The ``auto`` traversal's choice: which strategy walks a packet, from cheap measures of it.

Overbeck, Ramamoorthi and Mark (2008) find Ranged faster on coherent packets (one box test
usually decides a node) and Partition faster once coherence falls (Ranged's index range fills
with rays that miss). The ``auto`` kernel of ``engine.packet.walk`` asks ``choose_packet``
for every packet in a pass before the walk, and then walks each strategy's packets with the
strategy a compile-time constant.

The measures (``packet_measures``) are taken on a sample of the packet's lanes: SAMPLED_LANES
of them, evenly spaced from its first lane to its last (every lane of a smaller packet). In an
n x n camera packet, stored row by row, a stride of n + 1 lanes walks the diagonal, whose ends
are two opposite corners: the sample's boxes are the whole packet's. Measuring every lane cost
5.6 ns a ray, 16% of a Ranged walk of erw6's camera rays; the sample costs about 130 ns a
packet, 2 ns a ray of a 8 x 8 packet and 0.5 of a 16 x 16 one. Over the sample's live rays:

- ``live``: the fraction of the sampled lanes that are live (tmin <= tmax);
- ``footprint``: how many BVH leaves wide the packet is: (diagonal of the box around its
  origins + diagonal of the box around its normalised directions * reach) / the scene's
  typical leaf width (``scene_scales``), where ``reach`` is the mean segment length, each
  clipped to the scene diagonal. The directions' box diagonal is about the chord of
  the packet's direction cone (2 sin of its half-angle), so a camera packet's footprint grows
  with its angle; a reflection packet off a curved surface, or a shadow packet whose origins
  lie on surfaces far apart, has a large one. In leaf widths rather than scene diagonals: the
  same angle spans many more leaves of a 500k-triangle scene than of an 800-triangle room,
  and Ranged pays for every ray of its range that misses a leaf.
- ``valid``: whether the packet has a frustum (the packet's ``Frusta.valid``).

The rule (``choose_packet``), with the thresholds of ``LIMITS`` (fitted by
``tools/fit_auto.py``; ``engine/packet/auto_thresholds.json``):

    no frustum                                       -> INVALID_CHOICE (a strategy number)
    live >= MIN_LIVE and footprint <= MASKED_MAX     -> MASKED
    live >= MIN_LIVE and footprint <= RANGED_MAX     -> RANGED
    otherwise                                        -> PARTITION

limits: f64[N_LIMITS] indexed by RANGED_MAX, MASKED_MAX, MIN_LIVE, INVALID_CHOICE.

A batch is chosen from a sample (``engine.packet.walk.choose_batch``): ``batch_choice`` asks the
rule for SAMPLED_PACKETS packets (MAJORITY_SAMPLED_PACKETS when the batch is not to be split, see
``batch_choice``), one in each of as many equal runs of the batch's packets (``sampled_packet``),
serially (about 0.3 us a 16x16 packet).
A sample that agrees gives the whole batch its strategy. A split sample either gives the whole
batch the strategy most sampled packets got or has every packet chosen by the rule in a parallel
pass (``per_packet``; the ``auto`` plugin chooses per packet only in batches of at least its
``split_min_packets``). Either way a packet may be walked by another strategy than the rule
alone would give it. Why: a per-packet pass cost 0.10 ms on erw6's 1,024 8x8 camera packets at
256x256 (one thread) against a 1.37 ms Ranged walk, and on small scenes a batch walked by two
strategies in two passes lost to the better single strategy by up to 18% (the README's auto
section has the tables).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from engine.packet.strategies import MASKED, PARTITION, RANGED

RANGED_MAX, MASKED_MAX, MIN_LIVE, INVALID_CHOICE = range(4)

N_LIMITS = 4
#: Lanes of a packet the measures look at (see the module doc): 16 is the diagonal of a 16 x 16
#: packet (a stride of 17) and every lane of a 4 x 4 one.
SAMPLED_LANES = 16
#: Packets ``batch_choice`` asks the rule for in a batch (every packet of a smaller batch). 64
#: rather than 32 (session 32): on the 1024x1024 frames of the fit's four scenes (16x16 packets,
#: 30 batches of 2,388-4,096 packets), a sample of 32 at ``sampled_packet``'s offsets read two
#: batches that a 25% share splits (the kitchen's reflections and refractions: 32% and 31% of
#: their packets not the majority's) as 19% each, so they went whole; 64 read every such batch
#: above 25% (``docs/auto-measurements.md``).
SAMPLED_PACKETS = 64
#: Packets sampled in a batch that is not to be split (``batch_choice``'s per_packet False: it
#: goes whole to its sample's majority, which 32 packets tell as well): 64 took 21 us a batch on
#: erw6's 256x256 shadow batch of 256 16x16 packets (0.3 us a packet), 3% of its Ranged walk.
MAJORITY_SAMPLED_PACKETS = 32
#: The golden ratio's fractional part: the offset of run j's sampled packet inside its run.
GOLDEN_FRACTION = (math.sqrt(5.0) - 1.0) / 2.0
#: A direction whose squared length is within this of 1 is taken as unit (float32 unit vectors
#: are within a few 1e-7): the measure then skips its square root and division.
UNIT_SLACK = 1e-6
#: The names of the limits, in order (the keys of the thresholds file and the plugin's options).
LIMIT_NAMES = ("ranged_max_footprint", "masked_max_footprint", "min_live", "invalid_frustum")


@njit(cache=True, inline="always")
def packet_measures(org, dirs, tmin, tmax, start, n, scales):
    """(live, footprint) of rays start .. start+n (org, dirs f32[R,3]; tmin, tmax f32[R]) in a
    scene of ``scales`` (diagonal, typical leaf width) (``scene_scales``), measured on the
    lanes ``sampled_lane`` picks; see the module doc. (0, 0) with no live ray sampled."""
    diagonal, width = scales
    live = 0
    reach = 0.0
    o_lo_x, o_lo_y, o_lo_z = np.inf, np.inf, np.inf
    o_hi_x, o_hi_y, o_hi_z = -np.inf, -np.inf, -np.inf
    d_lo_x, d_lo_y, d_lo_z = np.inf, np.inf, np.inf
    d_hi_x, d_hi_y, d_hi_z = -np.inf, -np.inf, -np.inf
    sampled = min(n, SAMPLED_LANES)
    for j in range(sampled):
        r = sampled_lane(start, n, j)
        if not tmin[r] <= tmax[r]:
            continue
        dx, dy, dz = float(dirs[r, 0]), float(dirs[r, 1]), float(dirs[r, 2])
        norm2 = dx * dx + dy * dy + dz * dz
        norm = 1.0
        if not abs(norm2 - 1.0) <= UNIT_SLACK:  # unit already (the renderer's rays): no root, no division
            norm = math.sqrt(norm2)
            if not norm > 0.0:
                continue
            scale = 1.0 / norm
            dx, dy, dz = dx * scale, dy * scale, dz * scale
        live += 1
        d_lo_x, d_lo_y, d_lo_z = min(d_lo_x, dx), min(d_lo_y, dy), min(d_lo_z, dz)
        d_hi_x, d_hi_y, d_hi_z = max(d_hi_x, dx), max(d_hi_y, dy), max(d_hi_z, dz)
        ox, oy, oz = float(org[r, 0]), float(org[r, 1]), float(org[r, 2])
        o_lo_x, o_lo_y, o_lo_z = min(o_lo_x, ox), min(o_lo_y, oy), min(o_lo_z, oz)
        o_hi_x, o_hi_y, o_hi_z = max(o_hi_x, ox), max(o_hi_y, oy), max(o_hi_z, oz)
        reach += min((float(tmax[r]) - float(tmin[r])) * norm, diagonal)
    if live == 0:
        return 0.0, 0.0
    origins = math.sqrt((o_hi_x - o_lo_x) ** 2 + (o_hi_y - o_lo_y) ** 2 + (o_hi_z - o_lo_z) ** 2)
    directions = math.sqrt((d_hi_x - d_lo_x) ** 2 + (d_hi_y - d_lo_y) ** 2 + (d_hi_z - d_lo_z) ** 2)
    return live / sampled, (origins + directions * reach / live) / width


@njit(cache=True, inline="always")
def sampled_lane(start, n, j):
    """The j-th of the min(n, SAMPLED_LANES) lanes measured of rays start .. start+n: evenly
    spaced, the first and the last lane among them."""
    if n <= SAMPLED_LANES:
        return start + j
    return start + (j * (n - 1)) // (SAMPLED_LANES - 1)


@njit(cache=True, inline="always")
def scene_scales(bmin, bmax):
    """(diagonal of the BVH's root box, typical leaf width) of a BVH (bmin, bmax f32[N,3]); the
    leaf width is the diagonal over the square root of the leaf count ((N + 1) / 2 in a tree of
    two-child nodes): the leaves tile the scene's surfaces, not its volume."""
    dx = float(bmax[0, 0]) - float(bmin[0, 0])
    dy = float(bmax[0, 1]) - float(bmin[0, 1])
    dz = float(bmax[0, 2]) - float(bmin[0, 2])
    diagonal = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-30)
    return diagonal, diagonal / math.sqrt((bmin.shape[0] + 1) / 2)


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
def choose_packet(org, dirs, tmin, tmax, start, n, valid, scales, limits):
    """The strategy (MASKED, RANGED or PARTITION) that walks rays start .. start+n, whose
    frustum is ``valid``, in a scene of ``scales`` (``scene_scales``), under ``limits``
    f64[N_LIMITS] (see the module doc)."""
    live, footprint = packet_measures(org, dirs, tmin, tmax, start, n, scales)
    return choose_by_measures(live, footprint, valid, limits)


@njit(cache=True, parallel=True)
def measure_packets(bmin, bmax, org, dirs, tmin, tmax, offsets, live_out, footprint_out):
    """Every packet's measures (for the fit and ``packetrt show``): live_out, footprint_out
    f64[K] for the packets offsets i32[K+1] of the rays, in a scene of BVH boxes bmin, bmax."""
    scales = scene_scales(bmin, bmax)
    for k in prange(offsets.shape[0] - 1):
        start = offsets[k]
        live_out[k], footprint_out[k] = packet_measures(org, dirs, tmin, tmax, start, offsets[k + 1] - start,
                                                        scales)


@njit(cache=True, inline="always")
def sampled_packet(j, n_sampled, n_packets):
    """The packet ``batch_choice`` asks the rule for as its j-th of ``n_sampled`` (<= n_packets):
    one in run j of the n_sampled runs that split the packets evenly (packets j K / n .. (j + 1)
    K / n, rounded down), at the fraction frac((j + 1) x golden ratio) of the run.

    Not the run's first packet, as until session 32: a batch's packets follow its camera tiles
    row by row, and at 1024x1024 in 16x16 packets (64 tiles a row, 4,096 packets, 32 sampled)
    the first packet of each run of 128 was a tile of the image's left column, which then decided
    the whole batch (the museum's reflection batch: 71% of its packets Ranged's, 16% of that
    sample). The golden ratio's multiples spread the sampled tiles over the columns as well as
    the rows, and the same batch always gives the same sample."""
    first = (j * n_packets) // n_sampled
    run = ((j + 1) * n_packets) // n_sampled - first  # at least 1: n_sampled <= n_packets
    return first + int((((j + 1) * GOLDEN_FRACTION) % 1.0) * run)


@njit(cache=True)
def batch_choice(bmin, bmax, org, dirs, tmin, tmax, offsets, valid, limits, only, per_packet, choices,
                 min_share=0.0):
    """The strategy a whole batch is given, from ``choose_packet``'s answers for SAMPLED_PACKETS
    packets spread over it, MAJORITY_SAMPLED_PACKETS unless ``per_packet`` (``sampled_packet``;
    offsets i32[K+1], frusta valid bool[K]; every packet when K is smaller): the one most of them
    got (a tie to the lower strategy number), or, when ``per_packet``, the one all of them got,
    or at least all but a share under ``min_share`` (a split too thin to pay for itself needs no
    per-packet pass: 0.87 ms for the kitchen's 4,096 16x16 shadow packets, 2.5% of their walk).

    Returns (that strategy, the packets given it), with choices i8[K] filled, or (-1, 0) when no
    packet was sampled or, per packet, the sample is split. only: i8[K], and packets k with
    only[k] < 0 are left out of the sample and get -1, or empty (every packet).

    One jitted call: with the votes counted and the choices filled in numpy, a batch given whole
    took 19 us more than Ranged's walk of erw6's 256 16x16 camera packets (3%), 7 us once jitted
    (session 21). Session 32 measured auto at 29 us a batch over Ranged on erw6's 256x256 frame
    (two batches of 256 16x16 packets), 11 us of them in this call."""
    n_packets = offsets.shape[0] - 1
    scales = scene_scales(bmin, bmax)
    n_sampled = min(n_packets, SAMPLED_PACKETS if per_packet else MAJORITY_SAMPLED_PACKETS)
    votes = np.zeros(3, np.int64)  # by strategy number: MASKED, RANGED, PARTITION
    for j in range(n_sampled):
        k = sampled_packet(j, n_sampled, n_packets)
        if only.shape[0] > 0 and only[k] < 0:
            continue
        start = offsets[k]
        votes[choose_packet(org, dirs, tmin, tmax, start, offsets[k + 1] - start, valid[k], scales, limits)] += 1
    top = 0
    for s in range(1, 3):
        if votes[s] > votes[top]:
            top = s
    total = votes[0] + votes[1] + votes[2]
    if votes[top] == 0 or (per_packet and total - votes[top] >= max(min_share * total, 1e-9)):
        return -1, 0
    given = 0
    for k in range(n_packets):
        if only.shape[0] > 0 and only[k] < 0:
            choices[k] = -1
        else:
            choices[k] = top
            given += 1
    return top, given
