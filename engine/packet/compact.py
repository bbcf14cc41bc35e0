"""Rays stay in their ancestor's packet: the next batch of a kind, built tile by tile.

Overbeck et al. keep a packet's shadow and secondary rays in the packet of the camera tile they
descend from, compacted, so nothing is ever re-sorted. Here a parent batch is already in packet
order (``engine.packet.layout``: one packet per screen tile, lanes ordered by their position
inside the tile, padding at the end). A child batch takes, tile by tile, the flagged lanes of
one or more *sources* -- a source is one parent batch with, per lane, a flag and the child's
origin, direction, tmax and weight -- and merges them by position inside the tile; lanes at the
same position keep the order of the sources, then their lane order. That is exactly the layout
``layout.make_batch`` gives the concatenated candidates with its stable sort, without the sort
and without the concatenated copy. Children start at tmin 0.

``compact_into_packets`` plans the packets (``plan_packets``: which parent packet holds each
tile, how many children each tile gets) and fills them (``fill_packets``), both in parallel over
tiles. Sources come as tuples of arrays, one entry per source: 1 for shadow rays, 1, 2 or 4 for
the secondary kinds of a generation. numba compiles a kernel once per tuple length, so the tuples
are padded to ``PADDED_SOURCES`` with empty sources (no packet, no lane), which plan and fill
nothing: one compiled copy of each kernel instead of three (a cold default render compiled them
for 12.6 s).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from engine.core.triangle import HUGE_INV


@njit(cache=True, inline="always")
def inverse_component(d):
    """1/d for one f32 direction component, 0 mapped to +-HUGE_INV by its sign (never inf):
    ``engine.core.triangle.safe_inverse`` for one number."""
    tiny = np.float32(1.0) / HUGE_INV
    return np.float32(1.0) / (np.float32(math.copysign(tiny, d)) if d == 0 else d)


@njit(cache=True, inline="always")
def write_dead_lane(out, origin, org, dirs, inv, tmin, tmax, pixel, weight):
    """Lane ``out`` made a dead lane (tmax < tmin, pixel -1, zero weight) that pads a packet to
    whole 2x2 SIMD rays: it starts at ``origin`` (f32[3], a live lane's, so it shares the
    packet's frustum) and points along +z."""
    for a in range(3):
        org[out, a] = origin[a]
        dirs[out, a] = np.float32(1.0 if a == 2 else 0.0)
        inv[out, a] = inverse_component(dirs[out, a])
        weight[out, a] = np.float32(0.0)
    tmin[out] = np.float32(1.0)
    tmax[out] = np.float32(0.0)
    pixel[out] = -1


@njit(cache=True, inline="always")
def position_in_tile(pixel, width, n):
    """Where pixel ``pixel`` sits in its n x n tile's packet order (0 .. n*n-1): 2x2 blocks row
    by row, lanes (0,0), (1,0), (0,1), (1,1) inside a block."""
    y, x = divmod(pixel, width)
    return (((y % n) // 2) * (n // 2) + (x % n) // 2) * 4 + (y % 2) * 2 + x % 2


@njit(cache=True, inline="always")
def tile_of(pixel, width, n):
    """The n x n tile (row by row) that ``pixel`` lies in."""
    y, x = divmod(pixel, width)
    return (y // n) * (-(-width // n)) + x // n


@njit(cache=True, inline="always")
def next_flagged(flags, i, end):
    """The first lane >= i below ``end`` whose flag is set, else ``end``."""
    while i < end and not flags[i]:
        i += 1
    return i


def new_array(name, rows, tail=(), dtype=np.float32):
    """The default ``allocate``: a new uninitialised array of shape (rows, *tail)."""
    return np.empty((rows,) + tuple(tail), dtype)


#: Sources per compaction as the kernels see them: the most a Whitted generation passes (the
#: reflection batch of a generation whose parents are a reflection and a refraction batch).
PADDED_SOURCES = 4


def padded_sources(columns):
    """The 7 source columns of ``compact_into_packets``, each a tuple of S arrays, padded to
    max(S, PADDED_SOURCES) entries with empty sources: offsets [0] (no packet) and no lane. Each
    pad is made from the column's first array (a zero-length view; offsets: a zero of the same
    type), so every entry of a column has the same numba type and the tuple stays one that a
    run-time index can pick from."""
    missing = max(PADDED_SOURCES - len(columns[0]), 0)
    if not missing:
        return tuple(tuple(column) for column in columns)
    offsets, *lanes = columns
    pads = (np.zeros_like(offsets[0][:1]),) + tuple(column[0][:0] for column in lanes)
    return tuple(tuple(column) + (pad,) * missing for column, pad in zip(columns, pads))


def compact_into_packets(n, width, height, offsets_t, pixel_t, flag_t, org_t, dir_t, tmax_t, weight_t,
                         allocate=new_array):
    """The child batch of the flagged lanes of S sources, in packet order.

    Source s: parent packets offsets_t[s] (i32[K_s+1], one packet per tile, first lane live),
    ancestral pixels pixel_t[s] (i32[R_s]), flags flag_t[s] (bool[R_s], only live lanes
    flagged), and per lane the child's origin org_t[s] and direction dir_t[s] (f32[R_s,3]),
    tmax_t[s] (f32[R_s]) and weight weight_t[s] (f32[R_s,3]). n: the packet size, the parents'
    image width x height. ``allocate(name, rows, tail, dtype)`` gives the output arrays (a
    renderer passes reused buffers).

    Returns (offsets i32[K+1], org, dir, inv_dir f32[C,3], tmin, tmax f32[C], pixel i32[C],
    weight f32[C,3], source i32[C], lane i64[C]): C lanes, every packet a multiple of four long,
    padding lanes dead (tmin 1 > tmax 0, pixel -1, weight 0, source and lane -1, origin of the
    packet's first ray, direction +z); source and lane say which parent lane a child came from.
    """
    offsets_t, pixel_t, flag_t, org_t, dir_t, tmax_t, weight_t = padded_sources(
        (offsets_t, pixel_t, flag_t, org_t, dir_t, tmax_t, weight_t))
    tile_packet, counts, starts, offsets = plan_packets(n, width, height, offsets_t, pixel_t, flag_t)
    total = int(offsets[-1])
    out = (allocate("org", total, (3,)), allocate("dir", total, (3,)), allocate("inv_dir", total, (3,)),
           allocate("tmin", total), allocate("tmax", total), allocate("pixel", total, (), np.int32),
           allocate("weight", total, (3,)), allocate("source", total, (), np.int32),
           allocate("lane", total, (), np.int64))
    fill_packets(n, width, tile_packet, counts, starts, offsets_t, pixel_t, flag_t, org_t, dir_t, tmax_t, weight_t,
                 *out)
    return (offsets,) + out


@njit(cache=True, parallel=True)
def plan_packets(n, width, height, offsets_t, pixel_t, flag_t):
    """Where each tile's children go: (tile_packet i64[S, tiles] the parent packet of each tile
    per source or -1, counts i64[tiles] flagged lanes per tile, starts i64[tiles] each tile's
    first child lane, offsets i32[K+1] the child packets, tiles with children only)."""
    n_sources = len(offsets_t)
    tiles_x = -(-width // n)
    n_tiles = tiles_x * (-(-height // n))
    tile_packet = np.full((n_sources, n_tiles), -1, np.int64)
    for s in range(n_sources):
        offsets, pixel = offsets_t[s], pixel_t[s]
        for k in prange(offsets.shape[0] - 1):
            tile_packet[s, tile_of(pixel[offsets[k]], width, n)] = k
    counts = np.zeros(n_tiles, np.int64)
    for t in prange(n_tiles):
        c = 0
        for s in range(n_sources):
            k = tile_packet[s, t]
            if k >= 0:
                flags, offsets = flag_t[s], offsets_t[s]
                for i in range(offsets[k], offsets[k + 1]):
                    c += flags[i]
        counts[t] = c
    # Packet offsets: a serial prefix sum over the tiles (a few thousand).
    starts = np.empty(n_tiles, np.int64)
    n_packets = 0
    total = 0
    for t in range(n_tiles):
        starts[t] = total
        if counts[t] > 0:
            n_packets += 1
            total += (counts[t] + 3) // 4 * 4
    out_offsets = np.empty(n_packets + 1, np.int32)
    j = 0
    for t in range(n_tiles):
        if counts[t] > 0:
            out_offsets[j] = starts[t]
            j += 1
    out_offsets[n_packets] = total
    return tile_packet, counts, starts, out_offsets


@njit(cache=True, inline="always")
def write_child(out, s, i, src_org, src_dir, src_tmax, src_weight, src_pixel, org, dirs, inv, tmin, tmax, pix, weight,
                source, lane):
    """Child lane ``out`` from lane i of source s (its arrays src_*)."""
    for a in range(3):
        org[out, a] = src_org[i, a]
        dirs[out, a] = src_dir[i, a]
        inv[out, a] = inverse_component(src_dir[i, a])
        weight[out, a] = src_weight[i, a]
    tmin[out] = np.float32(0.0)
    tmax[out] = src_tmax[i]
    pix[out] = src_pixel[i]
    source[out] = s
    lane[out] = i


@njit(cache=True, parallel=True)
def fill_packets(n, width, tile_packet, counts, starts, offsets_t, pixel_t, flag_t, org_t, dir_t, tmax_t, weight_t,
                 org, dirs, inv, tmin, tmax, pix, weight, source, lane):
    """Write the children planned by ``plan_packets`` into org .. lane (see
    ``compact_into_packets``), in parallel over tiles."""
    n_sources = len(offsets_t)
    for t in prange(counts.shape[0]):
        if counts[t] == 0:
            continue
        cursor = np.zeros(n_sources, np.int64)
        end = np.zeros(n_sources, np.int64)
        live, only = 0, 0
        for s in range(n_sources):
            k = tile_packet[s, t]
            if k >= 0:
                offsets = offsets_t[s]
                end[s] = offsets[k + 1]
                cursor[s] = next_flagged(flag_t[s], offsets[k], end[s])
                if cursor[s] < end[s]:
                    live += 1
                    only = s
        out = starts[t]
        if live == 1:
            # One source with children in this tile (every shadow batch): its flagged lanes in
            # lane order, which is their order in the tile, without the merge below.
            flags, src_org, src_dir, src_tmax = flag_t[only], org_t[only], dir_t[only], tmax_t[only]
            src_weight, src_pixel = weight_t[only], pixel_t[only]
            for i in range(cursor[only], end[only]):
                if flags[i]:
                    write_child(out, only, i, src_org, src_dir, src_tmax, src_weight, src_pixel, org, dirs, inv,
                                tmin, tmax, pix, weight, source, lane)
                    out += 1
        while live > 1:
            # The source whose next flagged lane sits first in the tile; ties go to the lower
            # source, which keeps the stable order of the concatenated sources.
            best, best_key = -1, n * n
            for s in range(n_sources):
                if cursor[s] < end[s]:
                    key = position_in_tile(pixel_t[s][cursor[s]], width, n)
                    if key < best_key:
                        best, best_key = s, key
            if best < 0:
                break
            i = cursor[best]
            write_child(out, best, i, org_t[best], dir_t[best], tmax_t[best], weight_t[best], pixel_t[best], org,
                        dirs, inv, tmin, tmax, pix, weight, source, lane)
            out += 1
            cursor[best] = next_flagged(flag_t[best], i + 1, end[best])
        first = starts[t]
        while out % 4:
            write_dead_lane(out, org[first], org, dirs, inv, tmin, tmax, pix, weight)
            source[out] = -1
            lane[out] = -1
            out += 1
