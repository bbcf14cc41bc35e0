"""Coherent rays through the packet walk: first and any hits of a mesh query in 16x16 packets.

A per-ray walk (``engine.query.walk``) pays every node visit and box test for each ray. When a
query's rays are coherent -- camera and sensor rays, rays from one point, parallel sweeps -- the
renderer's packet walk (Overbeck et al. 2008, ``engine.packet.walk``) shares those among the rays
of a packet, as the render path does. ``coherence`` measures a batch in one parallel pass, in the
caller's order: blocks of ``PACKET_RAYS`` consecutive rays, each block's spread of unit directions
(1 - |mean of the unit directions|: 0 for parallel rays, about 2/3 for rays spread over a
hemisphere) and of origins (largest distance from the block's first origin, in units of the
mesh's size). A batch whose median block stays under ``MAX_DIRECTION_SPREAD`` and
``MAX_ORIGIN_SPREAD`` goes to ``packet_first_hits``: the rays, moved into the mesh's local frame
exactly as the per-ray walk moves them (``engine.query.frame.local_ray``), are cut in the
intersector's order (the caller's, or ``order="morton"``) into packets of ``PACKET_RAYS`` rays,
given frusta and walked by Ranged. A packet whose rays share one origin gets the pinhole frustum
the render path gives camera rays, any other the general one (``PINHOLE_OR_GENERAL``): on 447 x
447 camera rays of the bunny (two threads) the pinhole frusta are cheaper to build and cull
more, and a query took 9.7 ms against 10.5-11.2 with general frusta. The answers are the per-ray
walk's, bit for bit: the same float32 rays, triangles, watertight test and tie rule.

Camera rays given row by row are walked in 8 x 8 tiles, as the render path walks them: a tile
of 64 rays has a quarter of the perimeter of a 64-ray strip of a row, and its packet visits
fewer nodes. ``row_length`` finds the image's width from the jumps of the directions at the row
breaks (and checks it on every sampled break); ``tile_order`` then packs the rays tile by tile,
an index computation rather than a sort. On 447 x 447 camera rays (two threads, median of 21
interleaved queries) first hits took 12.8 ms in tiles against 13.9 ms in strips on the kitchen,
10.5 against 10.8 on the bunny. Rays of no recognisable width keep the caller's order, in strips.

Why the caller's order when it is coherent, and not a sort: on camera rays given row by row
(447 x 447, one core, packets of 256) the walk ran at 8.41 / 6.59 Mrays/s (bunny / kitchen) in
input order against 8.43 / 7.00 after the Morton sort, which itself cost more than the
difference (16 ms of a 42 ms bunny query). The per-ray walk ran 7.70 / 2.93 on the same rays,
trimesh's embreex backend 5.27 / 2.83.

When the order hides the coherence (``packing``). The same camera rays shuffled still passed
the block test (every block as wide as the view, under the threshold on the bunny's narrow one)
and took the packet walk in packets spanning the whole view: 25.4 / 32.9 ms a query (bunny /
kitchen, 199,809 rays, two threads, Zen 5), slower than embreex (18.9 / 35.5 ms). So a batch
whose blocks are not much tighter than the batch as a whole (``ORDERED_FRACTION``), or are
loose, but whose origins are tight as a whole (rays from one eye or sensor) is sorted first
(``engine.query.order.coherent_order``: a Morton key over the coordinates that vary, scaled to
the batch, and a parallel radix sort; about 2-4 ms for 200,000 rays) and walked in packets of
sorted neighbours when they are tight (else one by one in the caller's order): 11.0 / 12.2 ms.
Batches whose origins spread are never sorted (see ``packing``).
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from engine.core.lanes8 import rows_contiguous, rows_of_three
from engine.core.triangle import HUGE_INV
from engine.packet.compact import new_array
from engine.packet.frustum_builders import PINHOLE_OR_GENERAL, build_frusta
from engine.packet.plugin import deck_count
from engine.packet.strategies import RANGED
from engine.packet.walk import walk_packets
from engine.query.frame import local_ray
from engine.query.local8 import local_rays8
from engine.query.walk import safe_inverse1

#: Rays per packet. Rays come in the caller's order, often image rows, and a packet of 64 is a
#: short strip of a row: on 447 x 447 camera rays, one core, first hits ran at 9.14 / 7.40
#: Mrays/s (bunny / kitchen) in packets of 64, 8.33 / 7.04 of 128, 7.58 / 6.15 of 256.
PACKET_RAYS = 64
#: Below this many rays the per-ray walk is used whatever the coherence (packing costs more).
MIN_RAYS = 4096
#: Median block spreads up to which a batch counts as coherent (see the module doc).
MAX_DIRECTION_SPREAD = 0.05
MAX_ORIGIN_SPREAD = 0.05
#: Side of the square tiles camera rays are packed in (TILE * TILE == PACKET_RAYS).
TILE = 8
#: Image widths ``row_length`` looks for: a row must fit in its sample of 2 * MAX_ROW rays.
MAX_ROW = 8192
#: A row break is a step between consecutive unit directions this many times the median step.
ROW_BREAK = 4.0
#: Steps whose median is the typical step (see ``row_length``).
TYPICAL_STEPS = 2048
#: Blocks measured at most (evenly spaced): the median of a few hundred is as good a verdict as
#: that of all of them, and measuring every block cost 0.9 ms of a 15 ms kitchen query (447^2
#: camera rays, two threads).
SAMPLED_BLOCKS = 256


@njit(cache=True, inline="always")
def spread_terms(origins, directions, i, first):
    """(good, ux, uy, uz, away2): ray i's unit direction and the squared distance of its origin
    from ray ``first``'s, the terms of a spread; good False for a zero or non-finite direction."""
    norm = np.sqrt(directions[i, 0] ** 2 + directions[i, 1] ** 2 + directions[i, 2] ** 2)
    if not (norm > 0.0 and np.isfinite(norm)):
        return False, 0.0, 0.0, 0.0, 0.0
    inverse = 1.0 / norm  # a measure, not an answer: one division a ray, not three
    dx = origins[i, 0] - origins[first, 0]
    dy = origins[i, 1] - origins[first, 1]
    dz = origins[i, 2] - origins[first, 2]
    return True, directions[i, 0] * inverse, directions[i, 1] * inverse, directions[i, 2] * inverse, \
        dx * dx + dy * dy + dz * dz


@njit(cache=True, parallel=True)
def block_spreads(origins, directions, scale, block, step, rows, out_dir, out_org):
    """For sampled block b, the block of ``block`` consecutive rays starting at ray b * step *
    block (origins, directions f64[n,3]; scale the mesh's size), in the caller's order or, when
    rows (i64[n]) is not empty, in that order: out_dir f64[B] the direction spread, out_org
    f64[B] the origin spread. A block with a bad ray (zero or non-finite direction) counts as
    incoherent (spread 1)."""
    n = origins.shape[0]
    ordered = rows.shape[0] > 0
    for b in prange(out_dir.shape[0]):
        sx = sy = sz = 0.0
        far2 = 0.0  # squared: one square root a block, not one a ray
        bad = False
        lo = b * step * block
        hi = min(n, lo + block)
        first = rows[lo] if ordered else lo
        for k in range(lo, hi):
            good, ux, uy, uz, away2 = spread_terms(origins, directions, rows[k] if ordered else k, first)
            if not good:
                bad = True
                continue
            sx += ux
            sy += uy
            sz += uz
            far2 = max(far2, away2)
        count = hi - lo
        mean = np.sqrt(sx * sx + sy * sy + sz * sz) / count
        far = np.sqrt(far2)
        out_dir[b] = 1.0 if bad or not np.isfinite(mean) else 1.0 - mean
        out_org[b] = 1.0 if not np.isfinite(far) else far / scale


@njit(cache=True)
def batch_spread(origins, directions, scale, samples):
    """(direction spread, origin spread) of the whole batch, as ``block_spreads`` measures a
    block, over ``samples`` rays evenly spaced through it; bad rays are left out (1.0, 1.0 when
    every sampled ray is bad)."""
    n = origins.shape[0]
    step = max(1, n // max(samples, 1))
    sx = sy = sz = 0.0
    far2 = 0.0
    first = -1
    count = 0
    for i in range(0, n, step):
        good, ux, uy, uz, away2 = spread_terms(origins, directions, i, i if first < 0 else first)
        if not (good and np.isfinite(away2)):
            continue
        first = i if first < 0 else first
        sx += ux
        sy += uy
        sz += uz
        far2 = max(far2, away2)
        count += 1
    if count == 0:
        return 1.0, 1.0
    return 1.0 - np.sqrt(sx * sx + sy * sy + sz * sz) / count, np.sqrt(far2) / scale


#: ``block_spreads``' rows for the caller's order.
NO_ROWS = np.zeros(0, np.int64)
NO_ROWS.flags.writeable = False  # shared by every query: nobody writes it
#: How a batch is packed for the packet walk (``packing``).
PACK_NONE, PACK_INPUT, PACK_SORTED = 0, 1, 2
#: Rays ``batch_spread`` samples.
BATCH_SAMPLES = 4096
#: The caller's order is kept when its blocks are at most this fraction of the whole batch's
#: spread; shuffled rays make blocks as wide as the batch.
ORDERED_FRACTION = 0.5


def block_medians(origins: np.ndarray, directions: np.ndarray, scale: float, rows=None) -> tuple:
    """(median direction spread, median origin spread) of the batch's blocks of PACKET_RAYS
    consecutive rays (SAMPLED_BLOCKS of them at most, evenly spaced), in the caller's order or,
    given rows (i64[n]), in that order."""
    blocks = -(-origins.shape[0] // PACKET_RAYS)
    step = max(1, blocks // SAMPLED_BLOCKS)
    sampled = -(-blocks // step)
    spread_dir, spread_org = np.empty(sampled), np.empty(sampled)
    block_spreads(origins, directions, float(scale), PACKET_RAYS, step, NO_ROWS if rows is None else rows,
                  spread_dir, spread_org)
    return float(np.median(spread_dir)), float(np.median(spread_org))


def coherent_blocks(spreads: tuple) -> bool:
    """Whether block spreads (``block_medians``) are tight enough for the packet walk."""
    return spreads[0] <= MAX_DIRECTION_SPREAD and spreads[1] <= MAX_ORIGIN_SPREAD


def packing(origins: np.ndarray, directions: np.ndarray, scale: float) -> int:
    """How a batch (f64[n,3] each; the mesh's size ``scale``) goes to the walks:

    - PACK_INPUT: packets in the caller's order (its blocks are tight, and tighter than the
      batch as a whole, so the order is the rays' own: image rows, scan lines);
    - PACK_SORTED: sort first (``engine.query.order.coherent_order``), then see: the blocks are
      loose or no tighter than the batch (shuffled rays), but the batch's origins are tight as
      a whole (rays from one eye or sensor), so that neighbours in the sorted order, close in
      direction, make tight packets;
    - PACK_NONE: the per-ray walk in the caller's order (every other batch: sorting rays whose
      origins spread does not pay, see below).

    Origins that spread are not sorted even when the directions are tight (parallel sweeps,
    rays from points on a surface to a far light): sorted, their blocks of 64 were as wide as
    the threshold or wider (points on the bunny toward a light: origin spread 0.053), and then
    neither the packets nor the per-ray walk in sorted order beat the per-ray walk in the
    caller's order (kitchen, 200,000 such rays, any hit: 6.8 ms in the caller's order, 13.9 in
    sorted packets, 15.7 one by one in sorted order; session 35, Zen 5).
    """
    n = origins.shape[0]
    if n < MIN_RAYS:
        return PACK_NONE
    block = block_medians(origins, directions, scale)
    whole_dir, whole_org = batch_spread(origins, directions, float(scale), BATCH_SAMPLES)
    tiny = 1e-12
    if coherent_blocks(block) and block[0] <= ORDERED_FRACTION * whole_dir + tiny \
            and block[1] <= ORDERED_FRACTION * whole_org + tiny:
        return PACK_INPUT
    if whole_org <= MAX_ORIGIN_SPREAD:
        return PACK_SORTED
    return PACK_NONE


def is_coherent(origins: np.ndarray, directions: np.ndarray, scale: float) -> bool:
    """Whether a batch (f64[n,3] each) takes the packet walk in the caller's order (``packing``)."""
    return packing(origins, directions, scale) == PACK_INPUT


@njit(cache=True)
def direction_steps(directions, count, out):
    """out[i] (f64[count]) := distance between the unit directions of rays i and i + 1
    (directions f64[>count,3]); inf where either ray has a zero or non-finite direction. Each
    ray is normalised once and carried to the next step."""
    good, x, y, z = unit_direction(directions, 0)
    for i in range(count):
        next_good, next_x, next_y, next_z = unit_direction(directions, i + 1)
        if good and next_good:
            out[i] = np.sqrt((next_x - x) ** 2 + (next_y - y) ** 2 + (next_z - z) ** 2)
        else:
            out[i] = np.inf
        good, x, y, z = next_good, next_x, next_y, next_z


@njit(cache=True, inline="always")
def unit_direction(directions, i):
    """(good, x, y, z): ray i's direction over its length; good False (and zeros) for a zero or
    non-finite direction."""
    length = np.sqrt(directions[i, 0] ** 2 + directions[i, 1] ** 2 + directions[i, 2] ** 2)
    if not (length > 0.0 and np.isfinite(length)):
        return False, 0.0, 0.0, 0.0
    inverse = 1.0 / length  # a measure for ``row_length``, not an answer: one division, not three
    return True, directions[i, 0] * inverse, directions[i, 1] * inverse, directions[i, 2] * inverse


def row_length(directions: np.ndarray) -> int:
    """The width of the image whose rays ``directions`` (f64[n,3]) are, row by row; 0 when the
    rays show no such width (TILE <= width <= MAX_ROW, at least TILE rows).

    Within a row the direction moves by about one pixel's angle a ray; at a row break it jumps
    back across the row. The first step over ROW_BREAK times the median step (of the first
    TYPICAL_STEPS) ends the first row; the width must then also end every other row of the
    sample. A bad ray (zero or non-finite direction) makes an infinite step, so a wrong guess is
    refused, never harmful: the width only decides how rays are grouped into packets."""
    n = directions.shape[0]
    count = min(n - 1, 2 * MAX_ROW)
    if count < 2 * TILE:
        return 0
    steps = np.empty(count)
    direction_steps(directions, count, steps)
    finite_step = np.isfinite(steps)
    finite = steps[finite_step]
    if finite.size < count // 2:
        return 0
    # The typical step from the first TYPICAL_STEPS finite steps: breaks are at most one step in
    # TILE, so their median is a within-row step as surely as all 16,384 steps' (0.1 ms less).
    typical = float(np.median(finite[:TYPICAL_STEPS]))
    if not typical > 0.0:
        return 0  # parallel rays: no rows to see
    # A bad ray's (infinite) steps say nothing either way: only finite steps count.
    breaks = np.flatnonzero(finite_step & (steps > ROW_BREAK * typical))
    if breaks.size == 0:
        return 0
    width = int(breaks[0]) + 1
    if not TILE <= width <= MAX_ROW or n < TILE * width:
        return 0
    expected = np.arange(width - 1, count, width)
    expected = expected[finite_step[expected]]
    return width if np.array_equal(breaks, expected) else 0


@njit(cache=True, parallel=True)
def tile_order(n, width, rows):
    """rows (i64[L], L = PACKET_RAYS * tiles): the rays of an image of ``width`` columns and
    ceil(n / width) rows, tile by tile (TILE x TILE, row by row within a tile), -1 for the lanes
    of a tile that lie outside the image."""
    height = -(-n // width)
    across = -(-width // TILE)
    for k in prange(rows.shape[0] // PACKET_RAYS):
        top = (k // across) * TILE
        left = (k % across) * TILE
        for j in range(PACKET_RAYS):
            y = top + j // TILE
            x = left + j % TILE
            ray = y * width + x
            rows[k * PACKET_RAYS + j] = ray if x < width and y < height and ray < n else -1


def tiled_rows(n: int, width: int, allocate=new_array) -> np.ndarray:
    """``tile_order`` of n rays in an image ``width`` wide: i64[L], L a multiple of PACKET_RAYS,
    from ``allocate(name, rows, tail, dtype)``."""
    height = -(-n // width)
    tiles = -(-width // TILE) * -(-height // TILE)
    rows = allocate("tiled_rows", tiles * PACKET_RAYS, (), np.int64)
    tile_order(n, width, rows)
    return rows


@njit(cache=True, parallel=True)
def packet_lanes(origins, directions, center, scale, rows, org, dirs, inv, tmin, tmax, ok):
    """Lane k takes input ray rows[k] (-1 or past the end: a dead padding lane) in the local
    frame: org, dirs, inv f32[L,3], tmin, tmax f32[L]; ok[ray] (bool[n]) False for a bad ray,
    whose lane is dead too (tmin 1 > tmax 0). Eight lanes a step where the rows allow it
    (``engine.query.local8``: the same bits), the rest lane by lane."""
    n = rows.shape[0]
    vector = origins.shape[0] > 0 and rows_contiguous(origins) and rows_contiguous(directions) \
        and origins.shape[1] == 3 and directions.shape[1] == 3 and rows_of_three(org) and rows_of_three(dirs) \
        and rows_of_three(inv)
    blocks = min(n, org.shape[0]) // 8 if vector else 0
    for b in prange(blocks):
        good = local_rays8(origins, directions, rows, 8 * b, center, scale, org, dirs, inv, tmin, tmax)
        for j in range(8):
            r = rows[8 * b + j]
            if r >= 0:
                ok[r] = (good >> j) & 1 == 1
    for k in prange(8 * blocks, org.shape[0]):
        good = False
        if k < n and rows[k] >= 0:
            r = rows[k]
            good, ox, oy, oz, dx, dy, dz = local_ray(origins, directions, r, center, scale)
            ok[r] = good
        if good:
            org[k, 0], org[k, 1], org[k, 2] = ox, oy, oz
            dirs[k, 0], dirs[k, 1], dirs[k, 2] = dx, dy, dz
            for a in range(3):
                inv[k, a] = safe_inverse1(dirs[k, a])  # of the stored float32 component
            tmin[k] = 0.0
            tmax[k] = np.inf
        else:
            for a in range(3):
                org[k, a] = 0.0
                dirs[k, a] = 0.0
                inv[k, a] = HUGE_INV
            dirs[k, 2] = 1.0
            inv[k, 2] = 1.0
            tmin[k] = 1.0
            tmax[k] = 0.0


@njit(cache=True, parallel=True)
def scatter_answers(rows, lane_prim, lane_u, lane_v, out_tri, out_u, out_v):
    """Answers of lane k to input ray rows[k] (none for -1): out_tri (i64[n], -1 miss), out_u,
    out_v."""
    for k in prange(rows.shape[0]):
        r = rows[k]
        if r < 0:
            continue
        out_tri[r] = lane_prim[k]
        out_u[r] = lane_u[k]
        out_v[r] = lane_v[k]


def packet_first_hits(bvh, tris, order_keys, origins, directions, center, scale, rows, any_hit, out_tri, out_u,
                      out_v, ok, allocate=new_array):
    """First (any_hit: some) hit of every ray through the packet walk, into out_tri (i64[n],
    -1 = miss), out_u, out_v (f32[n]) by input ray, and ok (bool[n]) as ``first_hit_kernel``
    gives them. bvh, tris: the tree and local float32 triangles (face order); order_keys: the
    tree's ``child_order_keys`` (made once with the tree); origins, directions f64[n,3] world
    rays; rows i64[L] the order to pack them in (-1: a dead lane; each ray once). The lanes,
    frusta and packet answers come from ``allocate(name, rows, tail, dtype)`` (an intersector's
    reused scratch: fresh arrays page-fault)."""
    n = rows.shape[0]
    lanes = -(-n // 4) * 4
    # Names of their own: the caller takes its answers from the same ``allocate``.
    org, dirs, inv = (allocate(name, lanes, (3,)) for name in ("packet_org", "packet_dirs", "packet_inv"))
    tmin, tmax = allocate("packet_tmin", lanes), allocate("packet_tmax", lanes)
    packet_lanes(origins, directions, center, float(scale), rows, org, dirs, inv, tmin, tmax, ok)
    offsets = np.append(np.arange(0, lanes, PACKET_RAYS, dtype=np.int32), np.int32(lanes))
    n_packets = offsets.shape[0] - 1
    bounds = np.stack([bvh.bmin[0], bvh.bmax[0]]).astype(np.float32)
    planes = allocate("packet_planes", n_packets, (4, 4))  # build_frusta fills every packet's
    valid = allocate("packet_valid", n_packets, (), np.bool_)
    decks = deck_count(n_packets)
    build_frusta(PINHOLE_OR_GENERAL, org, dirs, tmin, tmax, offsets, bounds, decks, planes, valid)
    t, prim = allocate("packet_t", lanes), allocate("packet_prim", lanes, (), np.int32)
    u, v = allocate("packet_u", lanes), allocate("packet_v", lanes)
    walk_packets(RANGED, bvh.bmin, bvh.bmax, bvh.first, bvh.count, bvh.prim, tris.v0, tris.v1, tris.v2,
                 org, inv, dirs, tmin, tmax, offsets, planes, valid, order_keys, decks, any_hit, t, prim, u, v,
                 None, None)
    scatter_answers(rows, prim, u, v, out_tri, out_u, out_v)

