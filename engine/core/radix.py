"""A stable parallel argsort of unsigned 64-bit keys: least-significant-digit radix sort.

``radix_argsort(keys)`` returns the order (i64[n]) that sorts ``keys`` (u64[n]), equal keys in
their input order. Each pass sorts by one digit of DIGIT_BITS bits, lowest first: every thread counts the digit's
values over its own contiguous part of the batch, the counts of all parts give each (part,
value) its first output slot, and every thread then moves its part's (key, index) pairs to
their slots in order, so each pass is stable and the passes together sort. A digit that holds
one value in every key is skipped (its pass would move nothing): keys that use only the low
bits, as the ray orders' do, cost only the passes of the digits they use. 11-bit digits: a
33-bit key in three passes (2,048 slots a part stay in L1/L2); 8-bit ones took five and
1.7x as long.

Why not ``np.argsort``: numba's merge sort of 200,000 ray keys, two threads sorting a half each
and a merge, took 9.5-10.9 ms (session 35, Zen 5), longer than the packet walk the order was
for; this sort takes 1.3 ms for 45-bit keys (six passes), numpy's stable argsort 14 ms.
"""
from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from engine.core.scratch import new_array

DIGIT_BITS = 11
DIGITS = 1 << DIGIT_BITS
#: Below this many keys per thread one part is enough (waking threads costs more).
MIN_PART = 16384


@njit(cache=True, parallel=True)
def digit_counts(keys, shift, parts, counts):
    """counts[p, d] (i64[parts, DIGITS]) := how many keys of part p (contiguous, equal sizes but
    the last) have digit value d at bit ``shift``."""
    n = keys.shape[0]
    size = (n + parts - 1) // parts
    for p in prange(parts):
        for d in range(DIGITS):
            counts[p, d] = 0
        for i in range(p * size, min(n, (p + 1) * size)):
            counts[p, (keys[i] >> shift) & np.uint64(DIGITS - 1)] += 1


@njit(cache=True)
def digit_starts(counts, starts):
    """starts[p, d] := the first output slot of part p's keys of digit value d: all keys of
    smaller values, then those of value d in earlier parts. Returns whether a single value holds
    every key (the pass can be skipped)."""
    parts = counts.shape[0]
    total = 0
    single = False
    n = counts.sum()
    for d in range(DIGITS):
        in_digit = 0
        for p in range(parts):
            starts[p, d] = total + in_digit
            in_digit += counts[p, d]
        if in_digit == n:
            single = True
        total += in_digit
    return single


@njit(cache=True, parallel=True)
def scatter_digits(keys, index, shift, parts, starts, keys_out, index_out):
    """Move every (key, index) pair of each part to its slot by digit value, in order."""
    n = keys.shape[0]
    size = (n + parts - 1) // parts
    for p in prange(parts):
        slot = starts[p].copy()
        for i in range(p * size, min(n, (p + 1) * size)):
            d = (keys[i] >> shift) & np.uint64(DIGITS - 1)
            j = slot[d]
            keys_out[j] = keys[i]
            index_out[j] = index[i]
            slot[d] = j + 1


@njit(cache=True, parallel=True)
def copy_with_index(keys, keys_out, index_out):
    """keys_out := keys, index_out := 0 .. n-1 (the pairs the first pass moves)."""
    for i in prange(keys.shape[0]):
        keys_out[i] = keys[i]
        index_out[i] = i


def radix_argsort(keys: np.ndarray, allocate=new_array, parts: int | None = None) -> np.ndarray:
    """i64[n]: the stable order of ``keys`` (u64[n], left as given) from the smallest key up.
    parts: how many contiguous parts the counts and moves are split into (None: one per numba
    thread, at least MIN_PART keys each); any number gives the same order.

    Its four working arrays (keys and indices, twice; the answer is one of them) come from
    ``allocate(name, rows, tail, dtype)``: the intersectors hand in their reused scratch, since
    fresh arrays of this size page-fault on every call (200,000 keys: 4.8-5.0 ms a sort in new
    arrays in a new process, 1.3 ms in reused ones)."""
    keys = np.ascontiguousarray(keys, dtype=np.uint64)
    n = keys.shape[0]
    if parts is None:
        parts = max(1, min(numba.get_num_threads(), n // MIN_PART))
    counts = np.empty((parts, DIGITS), np.int64)
    starts = np.empty((parts, DIGITS), np.int64)
    current, keys_out = allocate("radix_keys", n, (), np.uint64), allocate("radix_keys_out", n, (), np.uint64)
    index, index_out = allocate("radix_index", n, (), np.int64), allocate("radix_index_out", n, (), np.int64)
    copy_with_index(keys, current, index)
    for shift in range(0, 64, DIGIT_BITS):
        digit_counts(current, np.uint64(shift), parts, counts)
        if digit_starts(counts, starts):
            continue
        scatter_digits(current, index, np.uint64(shift), parts, starts, keys_out, index_out)
        current, keys_out = keys_out, current
        index, index_out = index_out, index
    return index
