"""Each step's slope of range along the capsule stack (:func:`step_slopes`), in one compiled pass.

The flanks of a region (:mod:`~lelsonar.reconstruct.estimate.surfaces.flanks`) are told apart by it; a region
has a few dozen steps of a few capsules each, so the pass is one kernel call, not some twenty NumPy calls.
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.surfaces.measurement import Measured
from lelsonar.signal.compiled import kernel
from lelsonar.signal.summation import pairwise_sum

__all__ = ["step_slopes"]

#: The largest finite float64: where ``np.nan_to_num`` puts +inf.
_FMAX = float(np.finfo(np.float64).max)


def step_slopes(m: Measured, min_readings: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each of the region's steps' slope of range along the capsule stack, ``∂d/∂x``, its σ and ``Σ(x − x̄)²``.

    A plane gives every step its one slope, ``−n_x`` (its tilt); a line across the stack (a wall's foot on
    the floor, a box's top edge) a slope that follows the capsules' offset from it.  The σ is the range
    noise (pooled over the steps' residuals about their own lines, so whatever target a step holds) over
    ``√Σ(x − x̄)²`` of that step's capsules.

    Parameters
    ----------
    m : Measured
    min_readings : int
        The fewest readings a step needs for a slope (two give a line, three a residual too).

    Returns
    -------
    slopes, sigmas, sxx : (k,) arrays over ``region.steps``: the slopes and their σ (NaN under
    ``min_readings`` readings, σ NaN without residual dof anywhere), and each step's ``Σ(x − x̄)²``, m².
    """
    r = m.region
    pos = np.searchsorted(r.steps, r.rows)
    x = np.ascontiguousarray(m.positions[:, 0], dtype=np.float64)
    d = np.ascontiguousarray(m.ranges, dtype=np.float64)
    return _step_slopes(pos, x, d, r.steps.size, max(min_readings, 2))


@kernel
def _step_slopes(
    pos: np.ndarray, x: np.ndarray, d: np.ndarray, k: int, min_readings: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`step_slopes` of readings at step places ``pos``, capsule positions ``x`` and ranges ``d``.

    Each step's sums are added in the readings' order (as ``np.bincount`` adds its weights) and the pooled
    residuals' squares as ``np.sum`` adds them (:func:`~lelsonar.signal.summation.pairwise_sum`): the numbers
    of the same formulas in NumPy, to the bit.
    """
    n_read = pos.size
    n = np.zeros(k)
    sx = np.zeros(k)
    sd = np.zeros(k)
    for i in range(n_read):
        n[pos[i]] += 1.0
        sx[pos[i]] += x[i]
        sd[pos[i]] += d[i]
    mx = sx / n
    md = sd / n
    sxx = np.zeros(k)
    sxd = np.zeros(k)
    for i in range(n_read):
        dx = x[i] - mx[pos[i]]
        sxx[pos[i]] += dx * dx
        sxd[pos[i]] += dx * (d[i] - md[pos[i]])
    slopes = np.full(k, np.nan)
    dof = 0.0
    for s in range(k):
        if n[s] >= min_readings and sxx[s] > 0:
            slopes[s] = sxd[s] / sxx[s]
        dof += max(n[s] - 2.0, 0.0)
    sigmas = np.full(k, np.nan)
    if not dof > 0:
        return slopes, sigmas, sxx
    # The residuals about each step's own line (a step without a slope: about its mean), squared where the step
    # has residual dof (a slope's NaN as 0, its ±inf as ±the largest float, as np.nan_to_num).
    squares = np.zeros(n_read)
    for i in range(n_read):
        if n[pos[i]] > 2:
            b = slopes[pos[i]]
            if math.isnan(b):
                b = 0.0
            elif math.isinf(b):
                b = math.copysign(_FMAX, b)
            resid = d[i] - md[pos[i]] - b * (x[i] - mx[pos[i]])
            squares[i] = resid * resid
    noise = math.sqrt(pairwise_sum(squares, 0, n_read) / dof)
    for s in range(k):
        if math.isfinite(slopes[s]):
            sigmas[s] = noise / math.sqrt(sxx[s])
    return slopes, sigmas, sxx
