"""Incoherent rays put in an order the walk likes: neighbours start near each other and point
the same way, so consecutive rays on a thread touch the same BVH nodes (cache-warm).

The key (u64): direction octant (3 bits) above a 30-bit Morton code of the origin in the mesh's
local frame (10 bits per axis over [-2, 2]^3, clamped) interleaved with 3 x 4 bits of the unit
direction; a bad ray (NaN, inf, zero direction) sorts last. Keys are computed from the float64
world rays and sorted in numba, in parallel: each thread sorts a run, then runs are merged
pairwise (each round's merges in parallel). ``frame.local_rays`` then gathers the rays in this
order, so each thread walks a contiguous run of similar rays.
"""
import numpy as np
from numba import get_num_threads, njit, prange

ORIGIN_BITS, DIRECTION_BITS = 10, 4


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
            keys[i] = np.uint64(0xFFFFFFFFFFFFFFFF)
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


def ray_order(origins, directions, center, scale) -> np.ndarray:
    """i64[n]: the order to walk world rays (f64[n,3] each) in: grouped by octant and Morton key
    in the frame (center f64[3], scale), bad rays last."""
    keys = np.empty(origins.shape[0], np.uint64)
    ray_keys_kernel(origins, directions, center, float(scale), keys)
    runs = max(1, min(get_num_threads(), origins.shape[0] // 4096))
    return parallel_argsort(keys, runs)
