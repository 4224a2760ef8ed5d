"""Finding the corner and splitting the scan in two (paper §4, Fig. 6).

The critical step is the step with the largest energy ratio
``R = E^γ / E0(d_m)`` (eq. 11–12).  Its four points are the only ones the paper
excludes; the other steps form the subset before the critical step and the
subset after it.  The subset at the smaller angles is plane ``a`` (face-on at
γ ≈ 0, the plane y = const in the paper's setup), the other plane ``b``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate.robust import fast_median
from lelsonar.signal.compiled import kernel
from lelsonar.signal.summation import pairwise_sum

__all__ = ["critical_step", "Split", "split_subsets"]


def critical_step(ratio: np.ndarray, peak_fraction: float = 0.0) -> int | None:
    """The critical step: where the energy ratio ``R`` peaks (paper §4, Fig. 6).

    With ``peak_fraction = 0`` this is the paper's rule, the index of the
    largest ``R``.  The corner's ``R`` is a plateau, though — it jumps when the
    double-bounce echoes take over and stays within a few % of its maximum for
    several steps — so the argmax jitters by ±3 steps with noise.  With
    ``peak_fraction = f > 0`` the step is the ``R``-weighted centroid of the
    contiguous run of steps around the argmax with ``R ≥ (1 − f)·max R``
    (weights ``R − (1 − f)·max R``), rounded: the middle of the plateau's top.

    Parameters
    ----------
    ratio : (n_steps,) array
        ``R`` of each step, from :func:`lelsonar.signal.energy.energy_ratio`.
        NaN and non-positive values are ignored (no echo, no corner).
    peak_fraction : float
        In [0, 1).  0 = argmax (the paper).

    Returns
    -------
    int or None
        ``None`` if no step has a finite, positive ``R``.  On a partial scan
        that has not reached the corner yet this is simply the best step so
        far; the caller decides whether to trust it (e.g. only once R has
        fallen again after it).
    """
    r = np.asarray(ratio, dtype=np.float64)
    if r.ndim != 1:
        raise ConfigError(f"ratio must be one value per step, got shape {r.shape}")
    if not 0.0 <= peak_fraction < 1.0:
        raise ConfigError(f"peak_fraction must be in [0, 1), got {peak_fraction}")
    k = _critical_step(r, float(peak_fraction))
    return None if k < 0 else int(k)


@kernel
def _critical_step(ratio: np.ndarray, peak_fraction: float) -> int:
    """:func:`critical_step` of a 1-D ``ratio``; −1 for None."""
    n = ratio.shape[0]
    r = np.empty(n)
    found = False
    for i in range(n):
        ok = np.isfinite(ratio[i]) and ratio[i] > 0
        r[i] = ratio[i] if ok else 0.0
        found = found or ok
    if not found:
        return -1
    k = int(np.argmax(r))
    if peak_fraction == 0.0:
        return k
    thr = (1.0 - peak_fraction) * r[k]
    lo, hi = k, k
    while lo > 0 and r[lo - 1] >= thr:
        lo -= 1
    while hi < n - 1 and r[hi + 1] >= thr:
        hi += 1
    m = hi + 1 - lo
    w = r[lo : hi + 1] - thr
    total = pairwise_sum(w, 0, m)  # (sums as np.sum's)
    if total <= 0:
        return k
    moment = pairwise_sum(np.arange(lo, hi + 1) * w, 0, m)
    return int(min(max(np.rint(moment / total), lo), hi))


@dataclass(frozen=True)
class Split:
    """The two subsets of steps (paper §4).

    Parameters
    ----------
    critical : int
        The critical step, excluded from both subsets.
    steps_a, steps_b : (k,) int arrays
        Step indices of plane ``a`` (the subset at smaller γ) and plane ``b``.
    """

    critical: int
    steps_a: np.ndarray
    steps_b: np.ndarray

    def __post_init__(self) -> None:
        for name in ("steps_a", "steps_b"):
            a = np.array(getattr(self, name), dtype=np.intp).ravel()
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        a, b = self.steps_a, self.steps_b
        # Subsets on either side of each other (split_subsets') are disjoint without intersecting them.
        overlap = a.size and b.size and not (a.max() < b.min() or b.max() < a.min()) and np.intersect1d(a, b).size
        if overlap or self.critical in a or self.critical in b:
            raise ConfigError("the subsets must be disjoint and exclude the critical step")


def split_subsets(gamma: np.ndarray, critical: int) -> Split:
    """Split the steps at the critical step (paper §4).

    The steps before ``critical`` (by index) form one subset, the steps after
    it the other; the critical step itself is excluded.  Whichever subset has
    the smaller median γ is plane ``a``, so a scan run in either direction
    gives the same labels.

    Parameters
    ----------
    gamma : (n_steps,) array
        Measured rotation of each step, rad.
    critical : int
        From :func:`critical_step`.
    """
    g = np.asarray(gamma, dtype=np.float64)
    n = g.shape[0]
    if not 0 <= critical < n:
        raise ConfigError(f"critical step {critical} outside [0, {n})")
    before = np.arange(0, critical)
    after = np.arange(critical + 1, n)
    if before.size and after.size:
        swap = _nanmedian(g[:critical]) > _nanmedian(g[critical + 1 :])
    elif before.size:
        swap = _nanmedian(g[:critical]) > g[critical]
    elif after.size:
        swap = _nanmedian(g[critical + 1 :]) < g[critical]
    else:
        swap = False
    return Split(critical, after, before) if swap else Split(critical, before, after)


def _nanmedian(x: np.ndarray) -> float:
    """``np.nanmedian`` of a 1-D array (the same number; NaN if every value is NaN), without its masked-array path."""
    x = x[~np.isnan(x)]
    return fast_median(x) if x.size else float("nan")
