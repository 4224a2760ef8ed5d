"""Where a writer's times of flight lie on their echoes: up the rising edge, as a threshold comparator fires, or
at the foot, as a board timing the onset does.

A comparator that times a threshold crossing fires where the echo's envelope reaches its threshold: a level
over the noise (a comparator set within the noise fires on the noise alone) and, on the weaker echoes, a
share of their peak — which is why its ranges walk with their strength
(:func:`~lelsonar.signal.echo_timing.range_walk`).  A board timing the onset fires at the foot of the
edge, where the envelope is the noise's.  The walk test reads the offset of constant-fraction times
from the writer's; where every echo is two echoes a few mm apart (a wall's mirror echo and the double bounce
of its foot, under a scanner near the floor), their carriers' phase moves that time with the summed peak,
and a board that times the onset looks as if it walked.  The level at the writer's own time does not
depend on where the constant fraction falls, and tells the two boards apart.
"""

from __future__ import annotations

import numpy as np

from lelsonar.reconstruct.estimate.robust import median
from lelsonar.signal.echo_timing import CARRIER, FLOOR_TIME, hilbert_transform

__all__ = ["MIN_LEVEL_SHARE", "MIN_LEVEL_SIGMA", "envelope_at", "fires_up_the_edge"]

#: Robust noise σ the envelope must stand over at the writer's times (median): the line
#: :func:`~lelsonar.signal.echo_timing.echo_onsets` asks of an echo's peak to stand out of the noise.
MIN_LEVEL_SIGMA = 8.0
#: Share of the echoes' peaks the envelope must reach at the writer's times (median): a board timing the onset
#: shows there only the envelope's mean over the carrier period it is smoothed on, ~1.5 % of the peak for a
#: 0.15 ms rise; a comparator shows its threshold, several percent of the median echo's peak where it walks.
MIN_LEVEL_SHARE = 0.03


def envelope_at(windows: np.ndarray, sample_rate: float, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each window's envelope at time ``at`` over its floor, and the floor's robust σ.

    The envelope is :func:`~lelsonar.signal.echo_timing.echo_onsets`': the analytic signal's modulus (Hilbert
    transform, zero-padded to twice the window) of the window less its first 0.1 ms' mean, smoothed over one
    carrier period; the floor is its median over those 0.1 ms, σ 1.4826 times their median absolute deviation.

    Parameters
    ----------
    windows : (N, W) array
        V, around each reading's time of flight.
    sample_rate : float
        Hz.
    at : (N,) array
        s after each window's first sample (its time of flight there), linearly interpolated between samples.

    Returns
    -------
    level : (N,) array
        V over the floor.
    sigma : (N,) array
        V.
    """
    w = np.asarray(windows, dtype=np.float64)
    n, width = w.shape
    head = max(int(round(FLOOR_TIME * sample_rate)), 4)
    if n == 0 or width < 2 * head:
        return np.full(n, np.nan), np.full(n, np.nan)
    x = w - w[:, :head].mean(axis=-1, keepdims=True)
    hilbert = hilbert_transform(x)[:, :width]
    envelope = np.hypot(x, hilbert)
    period = max(int(round(sample_rate / CARRIER)), 1)
    before = period // 2
    padded = np.pad(envelope, ((0, 0), (before, period - before - 1)), mode="edge")
    total = np.cumsum(np.pad(padded, ((0, 0), (1, 0))), axis=-1)
    smooth = (total[:, period:] - total[:, :-period]) / period
    floor = np.median(smooth[:, :head], axis=-1)
    sigma = 1.4826 * np.median(np.abs(smooth[:, :head] - floor[:, None]), axis=-1)
    t = np.clip(np.asarray(at, dtype=np.float64) * sample_rate, 0.0, width - 1.0)
    i = np.minimum(t.astype(np.int64), width - 2)
    rows = np.arange(n)
    level = smooth[rows, i] + (t - i) * (smooth[rows, i + 1] - smooth[rows, i])
    return level - floor, sigma


def fires_up_the_edge(level: np.ndarray, sigma: np.ndarray, peak: np.ndarray) -> bool:
    """Whether a writer's times of flight lie up their echoes' rising edges, as a threshold comparator's do.

    Over the echoes given (the median of each): the envelope at the writer's time stands
    :data:`MIN_LEVEL_SIGMA` robust σ over the noise and reaches :data:`MIN_LEVEL_SHARE` of the echo's peak.
    A board timing the onset fails both on weak echoes and the second on strong ones.

    Parameters
    ----------
    level, sigma : arrays
        :func:`envelope_at`'s, V.
    peak : array
        The echoes' envelope peaks over their floors, V (:func:`~lelsonar.signal.echo_timing.echo_onsets`').
    """
    lv, sg, pk = (np.asarray(v, dtype=np.float64).ravel() for v in (level, sigma, peak))
    ok = np.isfinite(lv) & (sg > 0) & (pk > 0)
    if not ok.any():
        return False
    return bool(median(lv[ok] / sg[ok]) >= MIN_LEVEL_SIGMA and median(lv[ok] / pk[ok]) >= MIN_LEVEL_SHARE)
