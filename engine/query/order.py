"""Rays put in an order the walks like: neighbours start near each other and point the same way.

Two orders, each a key per ray sorted by ``engine.core.radix.radix_argsort`` (stable, parallel):

- ``ray_order`` (``order="morton"``): for the per-ray walk, so that consecutive rays on a thread
  touch the same BVH nodes (cache-warm). The key (u64): direction octant (3 bits) above a 30-bit
  Morton code of the origin in the mesh's local frame (10 bits per axis over [-2, 2]^3, clamped)
  interleaved with 3 x 4 bits of the unit direction; a bad ray (NaN, inf, zero direction) sorts
  last.
- ``coherent_order``: for the packet walk, which needs each run of ``PACKET_RAYS`` consecutive
  rays to be a tight bundle. Its key is a Morton code over the six coordinates of a ray (local
  origin, unit direction) scaled to the batch's own box, with the bits shared among the
  coordinates that vary in the batch: rays from one eye in a shuffled order spend all 63 bits
  on their three direction components (21 each), where the fixed key above gives them 4 bits a
  component and leaves thousands of rays to a cell, in their shuffled order.
"""
import numpy as np
from numba import njit, prange

from engine.core.radix import radix_argsort
from engine.core.scratch import new_array

ORIGIN_BITS, DIRECTION_BITS = 10, 4
#: ``ray_order``'s key of a bad ray: above every good key (45 bits), so it sorts last and the
#: radix sort's passes over the unused high bytes are skipped.
BAD_RAY_KEY = np.uint64((1 << (3 * (ORIGIN_BITS + DIRECTION_BITS) + 3)) - 1)
#: ``coherent_order``: at most this many bits of key, shared among the coordinates that vary.
COHERENT_KEY_BITS = 63
#: A coordinate varies when its extent over the batch exceeds this (local frame: the mesh is
#: about 1 across; unit directions).
MIN_EXTENT = 1e-9


@njit(cache=True)
def spread_bits(q, bits, stride):
    """The low ``bits`` bits of q (u64), bit b moved to bit stride * b: one coordinate of a
    Morton code interleaving ``stride`` coordinates."""
    out = np.uint64(0)
    for b in range(bits):
        out |= ((q >> np.uint64(b)) & np.uint64(1)) << np.uint64(stride * b)
    return out


@njit(cache=True, parallel=True)
def ray_keys_kernel(origins, directions, center, scale, keys):
    """keys[i] (u64) for world rays origins, directions: f64[n,3]; center f64[3], scale: the
    mesh's frame."""
    top_o = (1 << ORIGIN_BITS) - 1
    top_d = (1 << DIRECTION_BITS) - 1
    for i in prange(origins.shape[0]):
        norm = np.sqrt(directions[i, 0] ** 2 + directions[i, 1] ** 2 + directions[i, 2] ** 2)
        ok = norm > 0.0 and np.isfinite(norm)
        for a in range(3):
            ok = ok and np.isfinite(origins[i, a])
        if not ok:
            keys[i] = BAD_RAY_KEY
            continue
        code = np.uint64(0)
        octant = np.uint64(0)
        for a in range(3):
            x = ((origins[i, a] - center[a]) / scale + 2.0) * 0.25
            x = min(max(x, 0.0), 1.0)  # far origins clamp to the box's faces
            qo = int(x * top_o + 0.5)
            y = (directions[i, a] / norm + 1.0) * 0.5
            qd = min(max(int(y * top_d + 0.5), 0), top_d)
            code |= spread_bits(np.uint64(qo), ORIGIN_BITS, 3) << np.uint64(3 * DIRECTION_BITS + 2 - a)
            code |= spread_bits(np.uint64(qd), DIRECTION_BITS, 3) << np.uint64(2 - a)
            if np.signbit(directions[i, a]):
                octant |= np.uint64(1) << np.uint64(2 - a)
        keys[i] = code | (octant << np.uint64(3 * (ORIGIN_BITS + DIRECTION_BITS)))


def ray_order(origins, directions, center, scale) -> np.ndarray:
    """i64[n]: the order to walk world rays (f64[n,3] each) in: grouped by octant and Morton key
    in the frame (center f64[3], scale), bad rays last."""
    keys = np.empty(origins.shape[0], np.uint64)
    ray_keys_kernel(origins, directions, center, float(scale), keys)
    return radix_argsort(keys)


@njit(cache=True, inline="always")
def ray_coordinates(origins, directions, i, center, inverse_scale):
    """(ok, x, y, z, dx, dy, dz): ray i's local origin and unit direction (f64); ok False (and
    zeros) for a bad ray (a NaN/inf component or a zero direction)."""
    norm = np.sqrt(directions[i, 0] ** 2 + directions[i, 1] ** 2 + directions[i, 2] ** 2)
    x = (origins[i, 0] - center[0]) * inverse_scale
    y = (origins[i, 1] - center[1]) * inverse_scale
    z = (origins[i, 2] - center[2]) * inverse_scale
    if not (norm > 0.0 and np.isfinite(norm) and np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    inverse = 1.0 / norm  # a key, not an answer: one division a ray
    return True, x, y, z, directions[i, 0] * inverse, directions[i, 1] * inverse, directions[i, 2] * inverse


@njit(cache=True, inline="always")
def coordinate(k, x, y, z, dx, dy, dz):
    """Coordinate k (0-2 the origin's, 3-5 the direction's) of a ray."""
    if k < 3:
        return x if k == 0 else (y if k == 1 else z)
    return dx if k == 3 else (dy if k == 4 else dz)


@njit(cache=True)
def sampled_bounds(origins, directions, center, inverse_scale, samples, low, high):
    """low, high (f64[6]): the smallest and largest local origin and unit direction components
    of the good rays among ``samples`` evenly spaced ones (+inf / -inf for none). A key clamps
    the rays outside them to the box's faces, so a sample is enough."""
    n = origins.shape[0]
    for k in range(6):
        low[k] = np.inf
        high[k] = -np.inf
    step = max(1, n // max(samples, 1))
    for i in range(0, n, step):
        ok, x, y, z, dx, dy, dz = ray_coordinates(origins, directions, i, center, inverse_scale)
        if ok:
            for k in range(6):
                c = coordinate(k, x, y, z, dx, dy, dz)
                low[k] = min(low[k], c)
                high[k] = max(high[k], c)


def _spread_table(stride: int) -> np.ndarray:
    """u64[256]: each byte's bits moved to every ``stride``-th bit (``spread_bits`` of a byte)."""
    table = np.array([sum(((b >> k) & 1) << (stride * k) for k in range(8)) for b in range(256)], np.uint64)
    table.flags.writeable = False
    return table


#: ``_spread_table`` of every stride a key can have (1 to 6 coordinates), made once: made per
#: query in Python it cost 0.4 ms.
SPREAD_TABLES = tuple(_spread_table(stride) for stride in range(7))


def spread_table(stride: int) -> np.ndarray:
    """u64[256]: each byte's bits moved to every ``stride``-th bit (1 <= stride <= 6)."""
    return SPREAD_TABLES[stride]


@njit(cache=True, parallel=True)
def coherent_keys_kernel(origins, directions, center, inverse_scale, low, cells, axes, bits, table, keys):
    """keys[i] (u64): ray i's coordinates ``axes`` (i64[m], the ones that vary) quantised to
    ``bits`` bits each (at most 24) over [low, low + extent] (cells[k] = (2^bits - 1) / extent of
    axis k, clamped to the box) and interleaved, axis axes[j] at bit j of each group of m, by
    byte through ``table`` (``spread_table(m)``). A bad ray gets the m * bits low bits all set,
    as high as a good key can be, so it sorts after them (the sort is stable)."""
    m = axes.shape[0]
    top = (1 << bits) - 1
    bad = (np.uint64(1) << np.uint64(m * bits)) - np.uint64(1)
    for i in prange(origins.shape[0]):
        ok, x, y, z, dx, dy, dz = ray_coordinates(origins, directions, i, center, inverse_scale)
        if not ok:
            keys[i] = bad
            continue
        code = np.uint64(0)
        for j in range(m):
            k = axes[j]
            c = coordinate(k, x, y, z, dx, dy, dz)
            q = np.uint64(min(max(int((c - low[k]) * cells[k] + 0.5), 0), top))
            spread = table[q & np.uint64(255)]
            # Higher bytes only where there are any: a shift by 64 or more (8 * m with many
            # axes) is undefined in LLVM even when the byte is zero.
            if bits > 8:
                spread |= table[(q >> np.uint64(8)) & np.uint64(255)] << np.uint64(8 * m)
            if bits > 16:
                spread |= table[(q >> np.uint64(16)) & np.uint64(255)] << np.uint64(16 * m)
            code |= spread << np.uint64(j)
        keys[i] = code


#: Rays ``coherent_order`` takes the batch's box from.
BOUND_SAMPLES = 4096


def coherent_order(origins: np.ndarray, directions: np.ndarray, center: np.ndarray, scale: float,
                   allocate=new_array) -> np.ndarray:
    """i64[n]: world rays (f64[n,3] each) ordered by the batch-scaled Morton key described in the
    module doc (the mesh's frame: center f64[3], scale), bad rays last; the input order when no
    coordinate varies. allocate: for the keys and ``radix_argsort``'s arrays (default: new ones)."""
    n = origins.shape[0]
    inverse_scale = 1.0 / float(scale)
    low, high = np.empty(6), np.empty(6)
    sampled_bounds(origins, directions, center, inverse_scale, BOUND_SAMPLES, low, high)
    extent = high - low
    axes = np.flatnonzero(np.isfinite(extent) & (extent > MIN_EXTENT)).astype(np.int64)
    if axes.size == 0:
        return np.arange(n, dtype=np.int64)
    # Enough cells that a packet's rays share few of them (4^bits per pair of axes well above
    # n), and no more: each byte of key is a pass of the radix sort.
    key_bits = min(COHERENT_KEY_BITS, max(n, 1).bit_length() + 16)
    bits = max(1, min(24, key_bits // axes.size))
    cells = np.zeros(6)
    cells[axes] = ((1 << bits) - 1) / extent[axes]
    keys = allocate("order_keys", n, (), np.uint64)
    coherent_keys_kernel(origins, directions, center, inverse_scale, np.where(np.isfinite(low), low, 0.0), cells,
                         axes, bits, spread_table(axes.size), keys)
    return radix_argsort(keys, allocate)
