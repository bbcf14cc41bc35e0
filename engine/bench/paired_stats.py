"""Ratios of two timings taken in the same repetitions: the median per-repetition ratio, a
distribution-free 95% interval for it, and the verdict it supports. Used by the ``auto`` fit's
row-by-row measurement (``engine.bench.auto_fit``) and by frames paired by repetition
(``engine.bench.paired_frames``).
"""
from __future__ import annotations

import numpy as np

#: The normal quantile of the two-sided 95% interval around a median paired ratio (``paired_ratio``).
CONFIDENCE_Z = 1.96


def paired_ratio(numerator, denominator):
    """(median, low, high) of the per-repetition ratios numerator[i] / denominator[i] (f64[n]:
    two timings taken in the same repetition, interleaved: two traversals, two frames), with a
    distribution-free 95% interval for the median: the order statistics at (1-based) ranks
    floor((n+1)/2 - 1.96 sqrt(n)/2) and ceil((n+1)/2 + 1.96 sqrt(n)/2) (the sign test's interval,
    the binomial by its normal approximation; for n = 41 the 14th and 28th).
    Pairing by repetition cancels the drift this host shows from second to second, which moves
    single ms-scale rows by 5-10% between runs."""
    ratios = np.sort(np.asarray(numerator, np.float64) / np.asarray(denominator, np.float64))
    n = len(ratios)
    half = CONFIDENCE_Z * np.sqrt(n) / 2
    low = int(max(1, np.floor((n + 1) / 2 - half))) - 1
    high = int(min(n, np.ceil((n + 1) / 2 + half))) - 1
    return float(np.median(ratios)), float(ratios[low]), float(ratios[high])


def verdict(low, high) -> str:
    """What a paired interval [low, high] of a variant's time over a baseline's says: "faster"
    (below 1 throughout), "slower" (above 1 throughout) or "same" (1 inside: equal within the
    run's noise)."""
    return "faster" if high < 1.0 else ("slower" if low > 1.0 else "same")
