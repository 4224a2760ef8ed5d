"""Whether a region's echo amplitudes across γ are one beam pattern's: its two flanks mirror images of each other.

One target's echo follows ``D(γ − β)²`` across the sweep, symmetric about its bearing β, so at every level the
two flanks cross it at ``β ± u``: the midpoint of the crossings is β at every level, the threshold's (the region's
centre, Leonard & Durrant-Whyte) as the top's.  Another target at a like range whose echo continues the region past
one end (an edge beside a wall's foot diffracting at the wall's range), or replaces one flank (a wall that ends at
its foot), bends that flank only: the midpoints wander with the level, and the region's centre is no more the
target's bearing than any of them.

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.surfaces.amplitude_top import PLATEAU
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import log_amplitude_noise, log_echoes_in_order

__all__ = ["LEVELS", "flank_asymmetry", "level_midpoints"]

#: The levels the flanks' crossings are read at, as shares of the way in ``log A`` from the higher end's amplitude to
#: the top's (the top's own steps are left out: near it the flanks are flat and their crossings the noise's).
LEVELS = np.linspace(0.1, 0.8, 8)


def level_midpoints(gamma: np.ndarray, amplitude: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the two flanks of a region's echo cross each of :data:`LEVELS`, as their midpoints and σ.

    Each flank's outermost crossing of a level is interpolated linearly in ``log A`` between the two steps that
    bracket it; a noise σ in ``log A`` moves it by ``σ / |∂ log A/∂γ|`` (the flank's log slope there, a line
    through its four nearest steps), as does the straight line's own error on a curved flank (an eighth of the
    second difference there), and a midpoint by half the two crossings' in quadrature.  A clipped top's
    plateau (amplitudes within :data:`~.amplitude_top.PLATEAU` of the largest) is the top: the levels stay under it.

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).

    Returns
    -------
    (midpoints, their σ), rad, one per level; None when fewer than six steps have an amplitude or the top lies at
    an end of the region (no two flanks).
    """
    g, la = log_echoes_in_order(gamma, amplitude)
    if g.size < 6:
        return None
    top = float(la.max())
    flat = np.flatnonzero(la >= top + math.log1p(-PLATEAU))
    first, last = int(flat[0]), int(flat[-1])
    if first == 0 or last == g.size - 1:
        return None
    low = max(float(la[0]), float(la[-1]))
    if not top > low:
        return None
    sigma = log_amplitude_noise(la)
    levels = low + LEVELS * (top - low)
    # Outermost crossings: the first step at or over each level from the left, the last from the right.
    over = la[None, :] >= levels[:, None]
    i = np.argmax(over[:, : first + 1], axis=1)
    j = g.size - 1 - np.argmax(over[:, ::-1], axis=1)
    left, sl = _crossings(g, la, i - 1, i, levels, sigma)
    right, sr = _crossings(g, la, j, j + 1, levels, sigma)
    return 0.5 * (left + right), 0.5 * np.hypot(sl, sr)


def _crossings(
    g: np.ndarray, la: np.ndarray, a: np.ndarray, b: np.ndarray, levels: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where ``log A`` crosses each level between steps ``a`` and ``b`` (linear), and each crossing's σ: the noise
    and the straight line's own error over the slope of the least-squares line through the steps ``a − 1`` to
    ``b + 1``."""
    da = la[b] - la[a]
    t = np.divide(levels - la[a], da, out=np.full(levels.size, 0.5), where=da != 0)
    at = g[a] + t * (g[b] - g[a])
    lo, hi = np.maximum(a - 1, 0), np.minimum(b + 1, g.size - 1)
    idx = lo[:, None] + np.arange(4)[None, :]
    use = idx <= hi[:, None]
    idx = np.minimum(idx, g.size - 1)
    n = use.sum(axis=1)
    gm = np.where(use, g[idx], 0.0).sum(axis=1) / n
    gn = np.where(use, g[idx] - gm[:, None], 0.0)
    gg = (gn * gn).sum(axis=1)
    slope = np.divide((gn * la[idx]).sum(axis=1), gg, out=np.zeros(levels.size), where=gg > 0)
    # A straight line between two steps misplaces the crossing of a curved flank by up to an eighth of its
    # second difference there, in log A.
    c = np.clip(a, 1, g.size - 2)
    bend = np.abs(la[c - 1] - 2.0 * la[c] + la[c + 1]) / 8.0
    span = float(g[-1] - g[0])
    with np.errstate(divide="ignore"):
        se = np.where(
            slope != 0,
            np.minimum(np.hypot(sigma, bend) / np.abs(slope), span / math.sqrt(12.0)),
            span / math.sqrt(12.0),
        )
    return at, se


def flank_asymmetry(gamma: np.ndarray, amplitude: np.ndarray, bearing: float, bearing_stderr: float) -> float:
    """How far a region's bearing may be off its target's because its two flanks are not mirror images about it, rad.

    The midpoints of the flanks' crossings (:func:`level_midpoints`) measure one bearing for one beam pattern, as
    the region's centre (and its amplitude peak) do.  Two ways they say the bearing is not that one's:

    * **their axis is off the bearing**: their mean ``m̄`` differs from the bearing ``β`` by more than 3 σ of the
      difference (the midpoints' σ taken as one, as they share the flanks' shape; the bearing's own): the ends
      are not one pattern's threshold crossings, and the bearing is off by ``m̄ − β``;
    * **they wander with the level**: their mean square about ``m̄`` beyond their own noise's is how far the
      flanks' shapes depart from one pattern's.

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).
    bearing, bearing_stderr : float
        The region's bearing and its σ, rad.

    Returns
    -------
    ``√(d² + w²)``, ``d`` the axis's offset (0 within its 3 σ) and ``w`` the wander beyond the noise, rad; 0 without
    two flanks to compare.
    """
    found = level_midpoints(gamma, amplitude)
    if found is None:
        return 0.0
    mids, sds = found
    axis = float(np.mean(mids))
    noise2 = float(np.mean(sds**2))
    offset = axis - bearing
    off2 = offset * offset if abs(offset) > 3.0 * math.sqrt(noise2 + bearing_stderr**2) else 0.0
    wander2 = max(float(np.mean((mids - axis) ** 2)) - noise2, 0.0)
    return math.sqrt(off2 + wander2)
