"""NumPy's pairwise summation, to the bit, as compiled kernels.

Sums that decide between hypotheses (costs, means, a step's energy) are added in the order ``np.sum`` adds
them, so that a kernel and the NumPy it stands for agree exactly and a decision never flips on rounding.
"""

from __future__ import annotations

import numpy as np

from lelsonar.signal.compiled import kernel


@kernel
def pairwise_sum(x: np.ndarray, lo: int, n: int) -> float:
    """``np.sum`` of ``x[lo:lo + n]``, the same roundings: NumPy's pairwise summation.

    Halves (the first a multiple of 8) summed apart down to blocks of at most 128, each summed in 8
    lanes.  Costs compared across hypotheses decide which pair of walls wins; summing as NumPy does
    keeps those decisions where they were.  The halving runs on an explicit stack (a recursive kernel
    does not survive Numba's cache).
    """
    if n <= 128:
        return pairwise_block(x, lo, n)
    los = np.empty(64, dtype=np.intp)
    ns = np.empty(64, dtype=np.intp)
    second = np.zeros(64, dtype=np.bool_)  # whether the child above this frame is its second half
    left = np.empty(64)
    sp = 0
    los[0], ns[0] = lo, n
    while True:
        if ns[sp] > 128:  # descend into the first half
            n2 = ns[sp] // 2
            n2 -= n2 % 8
            second[sp] = False
            los[sp + 1], ns[sp + 1] = los[sp], n2
            sp += 1
            continue
        v = pairwise_block(x, los[sp], ns[sp])
        while True:  # hand v up: a first half waits for its second, a second half completes its parent
            sp -= 1
            if sp < 0:
                return v
            if not second[sp]:
                n2 = ns[sp] // 2
                n2 -= n2 % 8
                left[sp] = v
                second[sp] = True
                los[sp + 1], ns[sp + 1] = los[sp] + n2, ns[sp] - n2
                sp += 1
                break
            v = left[sp] + v


@kernel
def pairwise_block(x: np.ndarray, lo: int, n: int) -> float:
    """A leaf of :func:`pairwise_sum`: at most 128 terms, in order below 8, else in 8 lanes and the rest."""
    if n < 8:
        s = 0.0
        for i in range(lo, lo + n):
            s += x[i]
        return s
    r0, r1, r2, r3 = x[lo], x[lo + 1], x[lo + 2], x[lo + 3]
    r4, r5, r6, r7 = x[lo + 4], x[lo + 5], x[lo + 6], x[lo + 7]
    i = 8
    while i < n - n % 8:
        r0 += x[lo + i]
        r1 += x[lo + i + 1]
        r2 += x[lo + i + 2]
        r3 += x[lo + i + 3]
        r4 += x[lo + i + 4]
        r5 += x[lo + i + 5]
        r6 += x[lo + i + 6]
        r7 += x[lo + i + 7]
        i += 8
    s = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        s += x[lo + i]
        i += 1
    return s
