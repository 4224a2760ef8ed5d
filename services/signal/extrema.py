"""The extremes of a run of float32 samples, exact, in vector lanes.

A float maximum must keep NaN's comparisons (a NaN is neither larger nor smaller than anything), so a compiler
without ``fastmath`` leaves it one sample at a time, each comparison waiting on the one before.  The samples'
bit patterns, mapped so that their order as integers is the numbers' order, compare as integers instead, which
runs side by side; the result is mapped back, the same number.  A NaN's pattern falls outside every number's:
where one shows, the run is compared as floats, one sample at a time, as before.
"""

from __future__ import annotations

import numpy as np

from lelsonar.signal.compiled import float32_from_bits, kernel

#: +infinity's bit pattern shifted left once (the sign shifted out): a magnitude's pattern beyond it is a NaN's.
_INF_MAGNITUDE = np.uint32(0xFF000000)


@kernel
def float32_of_bits(pattern):
    """The float32 number whose bit pattern is ``pattern`` (an integer below 2^32, not a NaN's), as a float."""
    return float32_from_bits(pattern)


@kernel
def largest_magnitude(row, a, b):
    """The largest |w| of the float32 ``row[a:b]`` (a < b) as a float: ``max(abs(w))`` taken one sample at a time
    from ``row[a]`` on (a NaN there is the result; a NaN after it is never larger)."""
    run = row[a:b]  # (indexed from 0: loads side by side, where an index that may be negative is gathered)
    patterns = run.view(np.uint32)
    top = np.uint32(0)
    for j in range(run.size):
        top = max(top, np.uint32(patterns[j] << np.uint32(1)))  # the magnitude's order
    if top > _INF_MAGNITUDE:  # a NaN
        peak = abs(run[0])
        for j in range(1, run.size):
            v = abs(run[j])
            if v > peak:
                peak = v
        return float(peak)
    return float32_of_bits(top >> np.uint32(1))


@kernel
def extent(row, a, b):
    """The smallest and the largest sample of the float32 ``row[a:b]`` (a < b) as floats, ``min`` and ``max``
    taken one sample at a time from ``row[a]`` on where the run holds a NaN.  (Of a zero and a negative zero either
    may be given: they are the same number.)

    A pattern with its sign bit set is flipped whole, others get the sign bit: as unsigned integers, then, the
    patterns are in the numbers' order."""
    run = row[a:b]  # (indexed from 0, as in :func:`largest_magnitude`)
    patterns = run.view(np.uint32)
    low = np.uint32(0xFFFFFFFF)
    high = np.uint32(0)
    for j in range(run.size):
        p = patterns[j]
        key = np.uint32(p ^ (np.uint32(np.uint32(0) - (p >> np.uint32(31))) | np.uint32(0x80000000)))
        low = min(low, key)
        high = max(high, key)
    # -inf's key is 0x007FFFFF, +inf's 0xFF800000: a NaN's is below the one or above the other.
    if low < np.uint32(0x007FFFFF) or high > np.uint32(0xFF800000):
        lo = hi = run[0]
        for j in range(run.size):
            lo, hi = min(lo, run[j]), max(hi, run[j])
        return float(lo), float(hi)
    return float32_of_bits(_unkey(low)), float32_of_bits(_unkey(high))


@kernel
def _unkey(key):
    """The bit pattern whose :func:`extent` key is ``key``."""
    return np.uint32(key ^ (np.uint32(0x80000000) if key >> np.uint32(31) else np.uint32(0xFFFFFFFF)))
