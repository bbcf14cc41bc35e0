"""Packet layout: image tiles -> n x n packets of 2x2 SIMD rays.

A packet is the rays of one n x n screen tile (by ancestral pixel), in this order:
the tile's 2x2 blocks row by row, and within a block the lanes (0,0), (1,0), (0,1), (1,1).
Four consecutive rays form one SIMD ray. Secondary batches use the same order, keyed by
each ray's ancestral camera pixel, so a reflection packet holds the reflections of one
camera tile. Only live rays are kept: a packet is its live rays compacted and padded to a
multiple of four with dead lanes (tmax < tmin, pixel -1), and empty packets vanish.

Several rays may share a pixel (e.g. reflections of a reflection and of a refraction);
they stay adjacent, in their input order.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from engine.core.errors import ConfigError
from engine.core.triangle import HUGE_INV
from engine.core.types import Packets, RayBatch

PACKET_SIZES = (2, 4, 8, 16, 32)


def check_packet_size(n: int, name: str = "render.packet") -> int:
    """``n`` as an int if it is one of PACKET_SIZES; else a ConfigError naming ``name`` (a float
    such as 8.0 is refused too: the kernels size their arrays with it)."""
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n not in PACKET_SIZES:
        raise ConfigError(f"{name} must be one of {', '.join(map(str, PACKET_SIZES))}, got {n!r}")
    return int(n)


@njit(cache=True, parallel=True)
def _packet_keys(pixel, width, n, tile, inside):
    tiles_x = -(-width // n)
    half = n // 2
    for i in prange(pixel.shape[0]):
        y, x = divmod(pixel[i], width)
        tile[i] = (y // n) * tiles_x + x // n
        inside[i] = (((y % n) // 2) * half + (x % n) // 2) * 4 + (y % 2) * 2 + x % 2


def packet_keys(pixel: np.ndarray, width: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(packet id, position inside the packet), both i64[M], for ancestral pixels i[M] >= 0."""
    pixel = np.ascontiguousarray(pixel, np.int64)
    tile, inside = np.empty(pixel.size, np.int64), np.empty(pixel.size, np.int64)
    _packet_keys(pixel, width, n, tile, inside)
    return tile, inside


def packet_order(pixel: np.ndarray, width: int, height: int, n: int) -> tuple[np.ndarray, Packets]:
    """Order candidate rays into packets.

    pixel: i32[M] ancestral pixel of each candidate ray (all >= 0).
    Returns (gather i64[R], packets): gather[i] is the candidate that lane i takes, or -1 for
    a padding lane; R is M rounded up per packet to whole SIMD rays.
    """
    check_packet_size(n)
    pixel = np.asarray(pixel, np.int64)
    if pixel.size == 0:
        return np.zeros(0, np.int64), Packets(np.zeros(1, np.int32), n, width, height)
    tile, inside = packet_keys(pixel, width, n)
    # One key, (tile, inside) in lexicographic order (inside < n * n). Stable: equal keys keep
    # input order. Secondary and shadow candidates come from a batch already in packet order,
    # so the key is nearly sorted, which the stable sort (timsort) handles in linear time.
    order = np.argsort(tile * (n * n) + inside, kind="stable")
    sorted_tile = tile[order]
    starts = np.flatnonzero(np.r_[True, sorted_tile[1:] != sorted_tile[:-1]])
    counts = np.diff(np.r_[starts, len(order)])
    padded = (counts + 3) // 4 * 4
    offsets = np.zeros(len(padded) + 1, np.int64)
    np.cumsum(padded, out=offsets[1:])
    gather = np.full(int(offsets[-1]), -1, np.int64)
    # Position of each sorted ray: its packet's offset plus its rank inside the packet.
    rank = np.arange(len(order)) - np.repeat(starts, counts)
    gather[np.repeat(offsets[:-1], counts) + rank] = order
    return gather, Packets(offsets.astype(np.int32), n, width, height)


@njit(cache=True, parallel=True)
def _gather_rays(gather, org, direction, tmin, tmax, pixel, weight, org_, dir_, inv_, tmin_, tmax_, pix_, w_):
    """Lane i of the outputs takes candidate gather[i]; a lane with gather[i] < 0 becomes dead
    padding (origin of candidate 0, direction +z, tmin 1 > tmax 0, pixel -1, weight 0). inv_ is
    ``engine.core.triangle.safe_inverse`` of dir_, computed the same way per component."""
    tiny = np.float32(1.0) / HUGE_INV
    one = np.float32(1.0)
    for i in prange(gather.shape[0]):
        g = gather[i]
        live = g >= 0
        src = g if live else 0
        for a in range(3):
            org_[i, a] = org[src, a]
            d = direction[src, a] if live else np.float32(1.0 if a == 2 else 0.0)
            dir_[i, a] = d
            inv_[i, a] = one / (math.copysign(tiny, d) if d == 0 else d)
            w_[i, a] = weight[src, a] if live else np.float32(0.0)
        tmin_[i] = tmin[src] if live else one
        tmax_[i] = tmax[src] if live else np.float32(0.0)
        pix_[i] = pixel[src] if live else -1


def gather_batch(kind: str, gather: np.ndarray, org, direction, tmin, tmax, pixel, weight) -> RayBatch:
    """A RayBatch in packet order from candidate arrays (f[M,3], f[M], i[M], f[M,3]).

    Lanes with gather == -1 become dead padding: tmin 1, tmax 0, pixel -1, weight 0.
    """
    r = len(gather)
    out = RayBatch(np.empty((r, 3), np.float32), np.empty((r, 3), np.float32), np.empty((r, 3), np.float32),
                   np.empty(r, np.float32), np.empty(r, np.float32), np.empty(r, np.int32),
                   np.empty((r, 3), np.float32), kind)
    if r:
        f32 = [np.ascontiguousarray(a, np.float32) for a in (org, direction, tmin, tmax, weight)]
        _gather_rays(np.ascontiguousarray(gather, np.int64), f32[0], f32[1], f32[2], f32[3],
                     np.ascontiguousarray(pixel, np.int32), f32[4], out.org, out.dir, out.inv_dir, out.tmin,
                     out.tmax, out.pixel, out.weight)
    return out


def make_batch(kind: str, org, direction, tmin, tmax, pixel, weight, width: int, height: int, n: int):
    """(RayBatch, Packets): candidate rays ordered into n x n packets by ancestral pixel."""
    gather, packets = packet_order(pixel, width, height, n)
    return gather_batch(kind, gather, org, direction, tmin, tmax, pixel, weight), packets
