"""Incoherent rays put in an order the walk likes: neighbours start near each other and point
the same way, so consecutive rays on a thread touch the same BVH nodes (cache-warm).

The key (u64): direction octant (3 bits) above a 30-bit Morton code of the local origin (10 bits
per axis over [-2, 2]^3, clamped) interleaved with 3 x 4 bits of the unit direction. Keys are
computed and sorted in numba, in parallel: each thread sorts a run, then runs are merged pairwise
(each round's merges in parallel).
"""
import numpy as np
from numba import get_num_threads, njit, prange

ORIGIN_BITS, DIRECTION_BITS = 10, 4


@njit(cache=True)
def _spread3(q, bits):
    """The low ``bits`` bits of q, bit b moved to bit 3 b."""
    out = np.uint64(0)
    for b in range(bits):
        out |= ((q >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b)
    return out


@njit(cache=True, parallel=True)
def ray_keys_kernel(org, dirs, valid, keys):
    """keys[i] (u64) for local rays org, dirs: f32[n,3] (unit dirs); invalid rays sort last."""
    top_o = (1 << ORIGIN_BITS) - 1
    top_d = (1 << DIRECTION_BITS) - 1
    for i in prange(org.shape[0]):
        if not valid[i]:
            keys[i] = np.uint64(0xFFFFFFFFFFFFFFFF)
            continue
        code = np.uint64(0)
        octant = np.uint64(0)
        for a in range(3):
            x = (np.float64(org[i, a]) + 2.0) * 0.25
            qo = min(max(int(x * top_o + 0.5), 0), top_o)
            y = (np.float64(dirs[i, a]) + 1.0) * 0.5
            qd = min(max(int(y * top_d + 0.5), 0), top_d)
            code |= _spread3(np.uint64(qo), ORIGIN_BITS) << np.uint64(3 * DIRECTION_BITS + 2 - a)
            code |= _spread3(np.uint64(qd), DIRECTION_BITS) << np.uint64(2 - a)
            if np.signbit(dirs[i, a]):
                octant |= np.uint64(1) << np.uint64(2 - a)
        keys[i] = code | (octant << np.uint64(3 * (ORIGIN_BITS + DIRECTION_BITS)))


@njit(cache=True)
def _merge(keys, src, dst, lo, mid, hi):
    """Merge the sorted runs src[lo:mid], src[mid:hi] (indices into keys) into dst[lo:hi]."""
    i, j, k = lo, mid, lo
    while i < mid and j < hi:
        if keys[src[j]] < keys[src[i]]:
            dst[k] = src[j]
            j += 1
        else:
            dst[k] = src[i]
            i += 1
        k += 1
    while i < mid:
        dst[k] = src[i]
        i += 1
        k += 1
    while j < hi:
        dst[k] = src[j]
        j += 1
        k += 1


@njit(cache=True, parallel=True)
def parallel_argsort(keys, runs):
    """i64[n]: a stable order of keys (u64[n]), sorted as ``runs`` runs in parallel, then merged."""
    n = keys.shape[0]
    size = (n + runs - 1) // runs
    a = np.empty(n, np.int64)
    for r in prange(runs):
        lo = min(r * size, n)
        hi = min(lo + size, n)
        part = np.argsort(keys[lo:hi], kind="mergesort")
        for k in range(hi - lo):
            a[lo + k] = lo + part[k]
    b = np.empty(n, np.int64)
    width = size
    while width < n:
        pairs = (n + 2 * width - 1) // (2 * width)
        for p in prange(pairs):
            lo = p * 2 * width
            _merge(keys, a, b, lo, min(lo + width, n), min(lo + 2 * width, n))
        a, b = b, a
        width *= 2
    return a


def ray_order(org, dirs, valid) -> np.ndarray:
    """i64[n]: the order to walk local rays in (valid rays first, grouped by octant and Morton key)."""
    keys = np.empty(org.shape[0], np.uint64)
    ray_keys_kernel(org, dirs, valid, keys)
    runs = max(1, min(get_num_threads(), org.shape[0] // 4096))
    return parallel_argsort(keys, runs)
