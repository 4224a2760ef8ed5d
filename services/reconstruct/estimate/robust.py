"""Robust scale of fitting errors: the median, MAD and σ (eq. 21–22), and the paper's pre-filter (§5.3)."""

from __future__ import annotations

import math

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.signal.compiled import kernel

__all__ = ["MAD_K", "fast_median", "mad", "mad_of", "mad_sigma", "median", "prefilter_mask"]

#: The constant of eq. (22): σ = k·MAD for normally distributed errors.
MAD_K = 1.4826


@kernel
def fast_median(x: np.ndarray) -> float:
    """``np.median`` of a non-empty 1-D float array, bit for bit, without its dispatch.

    The middle order statistic, or the mean ``(a + b) / 2`` of the two middle
    ones, as :func:`numpy.median` computes them (order statistics are exact,
    whichever way they are found); NaN in, NaN out.  A kernel: the corner
    model's kernels take medians too.
    """
    n = x.shape[0]
    for i in range(n):
        if np.isnan(x[i]):
            return np.nan
    # The order statistics by selection (a partition about the middle), not a full sort: cheaper.
    k = n // 2
    p = np.partition(x, k)
    if n % 2:
        return p[k]
    below = p[0]  # the (k − 1)-th order statistic: the largest of the partition's lower part
    for i in range(1, k):
        if p[i] > below:
            below = p[i]
    return (below + p[k]) / 2.0


def median(x: np.ndarray) -> float:
    """``np.median`` of a 1-D float array, bit for bit (:func:`fast_median`); NaN for an empty one."""
    return fast_median(x) if x.size else math.nan


def mad(e: np.ndarray) -> float:
    """Median absolute deviation ``median(|e_i − μ|)``, μ the median, eq. (21)."""
    e = np.asarray(e, dtype=np.float64).ravel()
    if e.size == 0:
        raise ConfigError("MAD of an empty set")
    return mad_of(e)


@kernel
def mad_of(e: np.ndarray) -> float:
    """:func:`mad` of a non-empty 1-D array."""
    return fast_median(np.abs(e - fast_median(e)))


def mad_sigma(e: np.ndarray) -> float:
    """σ = 1.4826 · MAD, eq. (22)."""
    return MAD_K * mad(e)


def prefilter_mask(e: np.ndarray, fraction: float = 0.1) -> np.ndarray:
    """The paper's pre-filter (§5.3): keep ``|e_i| ≤ fraction · max |e|``.

    Parameters
    ----------
    e : (N,) array
        Fitting errors of eq. (20) (any unit; only ratios matter).
    fraction : float
        The paper uses 10 %.
    """
    if not 0 < fraction <= 1:
        raise ConfigError(f"pre-filter fraction must be in (0, 1], got {fraction}")
    a = np.abs(np.asarray(e, dtype=np.float64))
    return a <= fraction * a.max()
