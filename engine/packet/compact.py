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

``compact_into_packets`` plans the packets (``plan_packets``: the tiles that hold a parent
packet, found by merging the sources' packets, which are in tile order; which packet of each
source each tile holds and how many children it gets) and fills them (``fill_packets``), both
in parallel over runs of those tiles: the work follows the parents' packets, never the image's
tile count. Sources come as tuples of arrays, one entry per source: 1 for shadow rays, 1, 2 or
4 for the secondary kinds of a generation. numba compiles a kernel once per tuple length, so the tuples
are padded to ``PADDED_SOURCES`` with empty sources (no packet, no lane), which plan and fill
nothing: one compiled copy of each kernel instead of three (a cold default render compiled them
for 12.6 s).
"""
from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from engine.core.scratch import new_array  # noqa: F401  (the default ``allocate``, imported from here too)
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


#: Runs of planned tiles per thread in ``fill_packets``: several, so that a thread whose runs
#: hold fewer children takes more of them and the threads finish together.
RUNS_PER_THREAD = 4

#: Ranges of the image's tiles that ``plan_packets`` merges in parallel: many, as a late
#: generation's packets gather in a few parts of the image.
PLAN_RUNS = 64

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
    # The plan's arrays come from ``allocate`` too, sized by the parents' packets, not the image's
    # tiles: with 2x2 packets a 1024x1024 image has 262,144 tiles, and planning every one of
    # them in every call (1.4 ms even for a generation of a few hundred packets) made planning
    # 39 ms of the 2x2 SIMD frame against 3.5 ms at 16x16.
    n_sources = len(offsets_t)
    n_tiles = -(-width // n) * -(-height // n)
    n_packets_in = sum(offsets.shape[0] - 1 for offsets in offsets_t)
    cap = max(min(n_tiles, n_packets_in), 1)
    packet_tiles = allocate("packet_tiles", max(n_packets_in, 1), (), np.int32)
    packet_counts = allocate("packet_counts", max(n_packets_in, 1), (), np.int32)
    tile_packet = allocate("tile_packet", n_sources * cap, (), np.int32).reshape(n_sources, cap)
    counts = allocate("tile_counts", cap, (), np.int64)
    starts = allocate("tile_starts", cap, (), np.int64)
    packet_offsets = allocate("packet_offsets", cap + 1, (), np.int32)
    n_runs = min(n_tiles, PLAN_RUNS)
    m, n_packets = plan_packets(n, width, n_tiles, n_runs, offsets_t, pixel_t, flag_t, packet_tiles, packet_counts,
                                tile_packet, counts, starts, packet_offsets)
    fill_runs = min(m, RUNS_PER_THREAD * numba.get_num_threads())
    offsets = packet_offsets[:n_packets + 1]
    total = int(offsets[-1])
    out = (allocate("org", total, (3,)), allocate("dir", total, (3,)), allocate("inv_dir", total, (3,)),
           allocate("tmin", total), allocate("tmax", total), allocate("pixel", total, (), np.int32),
           allocate("weight", total, (3,)), allocate("source", total, (), np.int32),
           allocate("lane", total, (), np.int64))
    fill_packets(n, width, fill_runs, tile_packet, counts[:m], starts[:m], offsets_t, pixel_t, flag_t, org_t, dir_t,
                 tmax_t, weight_t, *out)
    return (offsets,) + out


@njit(cache=True, inline="always")
def merge_step(packet_tiles, first, head, end, n_sources):
    """The smallest tile among the sources' next packets (packet_tiles[first[s] + head[s]] for
    head[s] < end[s]), or -1 when every source is done."""
    tile = -1
    for s in range(n_sources):
        if head[s] < end[s]:
            here = packet_tiles[first[s] + head[s]]
            if tile < 0 or here < tile:
                tile = here
    return tile


@njit(cache=True, parallel=True)
def plan_packets(n, width, n_tiles, n_runs, offsets_t, pixel_t, flag_t, packet_tiles, packet_counts, tile_packet,
                 counts, starts, out_offsets):
    """Where the children go, tile by tile, written into the caller's arrays. The tiles planned
    are those holding a packet of some source, in tile order: M of them. packet_tiles,
    packet_counts i32[sum of the sources' packet counts]: scratch; tile_packet i32[S, >= M] the
    packet of each planned tile per source or -1, counts i64[>= M] its flagged lanes, starts
    i64[>= M] its first child lane, out_offsets i32[>= M+1] the child packets (tiles with
    children only) in its first K+1 entries. Returns (M, K).

    The work follows the packets, not the image's tiles (262,144 at 2x2 and 1024x1024, most of
    them without a packet in a late generation): each source's packets are in tile order, so
    the planned tiles are a merge of the sources' packet tiles, done in parallel over n_runs
    ranges of tiles (each run finds its first packet per source by binary search), once to
    count a run's tiles and once to write them."""
    n_sources = len(offsets_t)
    first = np.zeros(n_sources + 1, np.int64)  # source s's packet tiles: packet_tiles[first[s]:first[s + 1]]
    for s in range(n_sources):
        first[s + 1] = first[s] + offsets_t[s].shape[0] - 1
    # Each packet's tile and flagged lanes, source by source (the sources' arrays taken out of
    # their tuples once per source, not per tile in the loops below).
    disorder = 0
    for s in range(n_sources):
        offsets, pixel, flags = offsets_t[s], pixel_t[s], flag_t[s]
        base = first[s]
        for k in prange(offsets.shape[0] - 1):
            packet_tiles[base + k] = tile_of(pixel[offsets[k]], width, n)
            c = 0
            for i in range(offsets[k], offsets[k + 1]):
                c += flags[i]
            packet_counts[base + k] = c
        for k in prange(1, offsets.shape[0] - 1):
            disorder += packet_tiles[base + k] <= packet_tiles[base + k - 1]
    if disorder:
        raise ValueError("compact_into_packets: a source's packets are not in tile order")
    # Per run and source, the packets whose tiles lie in the run's range [lo, hi).
    run_head = np.empty((n_runs + 1, n_sources), np.int64)
    for r in prange(n_runs + 1):
        bound = r * n_tiles // n_runs
        for s in range(n_sources):
            lo, hi = 0, first[s + 1] - first[s]
            while lo < hi:
                mid = (lo + hi) // 2
                if packet_tiles[first[s] + mid] < bound:
                    lo = mid + 1
                else:
                    hi = mid
            run_head[r, s] = lo
    run_tiles = np.zeros(n_runs + 1, np.int64)
    for r in prange(n_runs):
        head = run_head[r].copy()
        m = 0
        while True:
            tile = merge_step(packet_tiles, first, head, run_head[r + 1], n_sources)
            if tile < 0:
                break
            for s in range(n_sources):
                if head[s] < run_head[r + 1, s] and packet_tiles[first[s] + head[s]] == tile:
                    head[s] += 1
            m += 1
        run_tiles[r + 1] = m
    for r in range(n_runs):
        run_tiles[r + 1] += run_tiles[r]
    run_lanes = np.zeros(n_runs + 1, np.int64)
    run_packets = np.zeros(n_runs + 1, np.int64)
    for r in prange(n_runs):
        head = run_head[r].copy()
        lanes, packets = 0, 0
        for t in range(run_tiles[r], run_tiles[r + 1]):
            tile = merge_step(packet_tiles, first, head, run_head[r + 1], n_sources)
            c = 0
            for s in range(n_sources):
                if head[s] < run_head[r + 1, s] and packet_tiles[first[s] + head[s]] == tile:
                    tile_packet[s, t] = head[s]
                    c += packet_counts[first[s] + head[s]]
                    head[s] += 1
                else:
                    tile_packet[s, t] = -1
            counts[t] = c
            lanes += (c + 3) // 4 * 4
            packets += c > 0
        run_lanes[r + 1] = lanes
        run_packets[r + 1] = packets
    for r in range(n_runs):  # each run's first child lane and packet
        run_lanes[r + 1] += run_lanes[r]
        run_packets[r + 1] += run_packets[r]
    for r in prange(n_runs):
        total, j = run_lanes[r], run_packets[r]
        for t in range(run_tiles[r], run_tiles[r + 1]):
            starts[t] = total
            if counts[t] > 0:
                out_offsets[j] = total
                j += 1
                total += (counts[t] + 3) // 4 * 4
    out_offsets[run_packets[n_runs]] = run_lanes[n_runs]
    return run_tiles[n_runs], run_packets[n_runs]


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
def fill_packets(n, width, n_runs, tile_packet, counts, starts, offsets_t, pixel_t, flag_t, org_t, dir_t, tmax_t,
                 weight_t, org, dirs, inv, tmin, tmax, pix, weight, source, lane):
    """Write the children planned by ``plan_packets`` into org .. lane (see
    ``compact_into_packets``), in parallel over n_runs runs of the M planned tiles (counts,
    starts: their first M entries)."""
    n_sources = len(offsets_t)
    n_tiles = counts.shape[0]
    # Tiles in runs, each with its cursors made once: per tile they were two heap arrays, up to
    # 262,144 of each per call with 2x2 packets. Runs of neighbouring tiles, not interleaved
    # ones: 2x2 tiles write 4 lanes each, and interleaved, two threads wrote the same lines.
    for r in prange(n_runs):
        cursor = np.zeros(n_sources, np.int64)
        end = np.zeros(n_sources, np.int64)
        for t in range(r * n_tiles // n_runs, (r + 1) * n_tiles // n_runs):
            fill_tile(t, n, width, tile_packet, counts, starts, offsets_t, pixel_t, flag_t, org_t, dir_t, tmax_t,
                      weight_t, org, dirs, inv, tmin, tmax, pix, weight, source, lane, cursor, end)


@njit(cache=True, inline="always")
def fill_tile(t, n, width, tile_packet, counts, starts, offsets_t, pixel_t, flag_t, org_t, dir_t, tmax_t, weight_t,
              org, dirs, inv, tmin, tmax, pix, weight, source, lane, cursor, end):
    """The children of planned tile t (``fill_packets``); cursor, end i64[S]: scratch."""
    n_sources = len(offsets_t)
    if counts[t] > 0:
        for s in range(n_sources):
            cursor[s] = 0
            end[s] = 0
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
