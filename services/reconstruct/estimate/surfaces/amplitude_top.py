"""The top of a sweep's echo amplitudes across γ, and the small least-squares fit of a parabola to it.

A target's echo peaks where the beam faces it; its top (the readings over half the largest, or a clipped
plateau) is what :mod:`.beam_pattern` fits a parabola in ``log A`` to.  Finding it is one compiled pass over
the readings where γ rises step by step, as a sweep's does, and NumPy's sort otherwise; the fit's helpers give
NumPy's own numbers (``lstsq``, ``matrix_rank``, ``pinv``) for a three-column design.

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import numpy as np

from lelsonar.signal.compiled import kernel

__all__ = [
    "PLATEAU",
    "NO_TOP",
    "PLATEAU_TOP",
    "TOP",
    "UNSORTED",
    "Top",
    "sorted_top",
    "rising_top",
    "top_in_order",
    "quadratic_design",
    "lstsq_full_rank",
    "matrix_rank",
    "pinv",
]

#: Amplitudes within this share of the largest are the receiver clipping: a plateau, not a peak.
PLATEAU = 0.001
_EPS = float(np.finfo(np.float64).eps)

#: What :func:`rising_top` and :func:`sorted_top` found: too few readings or no top, a clipped plateau, a top
#: (and, of :func:`rising_top` alone, readings whose γ do not rise: left to :func:`sorted_top`).
NO_TOP, PLATEAU_TOP, TOP, UNSORTED = 0, 1, 2, -1

Top = tuple[int, np.ndarray, int, int, np.ndarray, np.ndarray]


def sorted_top(gamma: np.ndarray, amplitude: np.ndarray) -> Top:
    """:func:`_peak_bearing`'s readings (finite, positive amplitudes) in γ order and what their top is: the kind,
    the sorted γ, a plateau's first and last index and its γ (as ``gt``), or the top's γ and amplitudes (the
    amplitudes within :data:`PLATEAU` of the largest, at least three: a plateau; else those over half of it,
    at least five: the top)."""
    ok = np.isfinite(amplitude) & (amplitude > 0)
    if np.count_nonzero(ok) < 5:
        return NO_TOP, gamma, 0, 0, gamma, amplitude
    g, a = gamma[ok], amplitude[ok]
    order = np.argsort(g)
    g, a = g[order], a[order]
    top_value = a.max()
    flat = np.flatnonzero(a >= (1.0 - PLATEAU) * top_value)
    if flat.size >= 3:
        return PLATEAU_TOP, g, int(flat[0]), int(flat[-1]), g[flat], a[flat]
    top = a >= 0.5 * top_value
    if np.count_nonzero(top) < 5:
        return NO_TOP, g, 0, 0, g, a
    return TOP, g, 0, 0, g[top], a[top]


@kernel
def rising_top(gamma: np.ndarray, amplitude: np.ndarray, plateau: float) -> Top:
    """:func:`sorted_top` in one pass where the readings' γ strictly rise (their order is γ's, argsort's
    identity); of kind ``UNSORTED`` where they do not (the caller sorts)."""
    n = 0
    for i in range(amplitude.size):
        if np.isfinite(amplitude[i]) and amplitude[i] > 0:
            n += 1
    g = np.empty(n)
    a = np.empty(n)
    j = 0
    for i in range(amplitude.size):
        if np.isfinite(amplitude[i]) and amplitude[i] > 0:
            g[j] = gamma[i]
            a[j] = amplitude[i]
            j += 1
    if n < 5:
        return NO_TOP, g, 0, 0, g, a
    top_value = a[0]
    for i in range(1, n):
        if not g[i] > g[i - 1]:
            return UNSORTED, g, 0, 0, g, a
        if a[i] > top_value:
            top_value = a[i]
    at_flat = (1.0 - plateau) * top_value
    n_flat, first, last = 0, 0, 0
    for i in range(n):
        if a[i] >= at_flat:
            if n_flat == 0:
                first = i
            last = i
            n_flat += 1
    if n_flat >= 3:
        gf = np.empty(n_flat)
        af = np.empty(n_flat)
        j = 0
        for i in range(first, last + 1):
            if a[i] >= at_flat:
                gf[j] = g[i]
                af[j] = a[i]
                j += 1
        return PLATEAU_TOP, g, first, last, gf, af
    half = 0.5 * top_value
    n_top = 0
    for i in range(n):
        if a[i] >= half:
            n_top += 1
    if n_top < 5:
        return NO_TOP, g, 0, 0, g, a
    gt = np.empty(n_top)
    at = np.empty(n_top)
    j = 0
    for i in range(n):
        if a[i] >= half:
            gt[j] = g[i]
            at[j] = a[i]
            j += 1
    return TOP, g, 0, 0, gt, at


@kernel
def top_in_order(
    gamma: np.ndarray, amplitude: np.ndarray, plateau: float, allow_plateau: bool
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`log_amplitude_curvature`'s top in the readings' order: the γ and amplitudes of the finite, positive
    amplitudes over half the largest, at least five of them, and (unless ``allow_plateau``) fewer than three
    within ``plateau`` of the largest; empty arrays otherwise."""
    n = 0
    top_value = 0.0
    for i in range(amplitude.size):
        if np.isfinite(amplitude[i]) and amplitude[i] > 0:
            if n == 0 or amplitude[i] > top_value:
                top_value = amplitude[i]
            n += 1
    if n < 5:
        return np.empty(0), np.empty(0)
    half = 0.5 * top_value
    at_flat = (1.0 - plateau) * top_value
    n_top, n_flat = 0, 0
    for i in range(amplitude.size):
        if np.isfinite(amplitude[i]) and amplitude[i] > 0:
            if amplitude[i] >= half:
                n_top += 1
            if amplitude[i] >= at_flat:
                n_flat += 1
    if n_top < 5 or (not allow_plateau and n_flat >= 3):
        return np.empty(0), np.empty(0)
    gt = np.empty(n_top)
    at = np.empty(n_top)
    j = 0
    for i in range(amplitude.size):
        if np.isfinite(amplitude[i]) and amplitude[i] > 0 and amplitude[i] >= half:
            gt[j] = gamma[i]
            at[j] = amplitude[i]
            j += 1
    return gt, at


def quadratic_design(u: np.ndarray) -> np.ndarray:
    """The columns ``1, u, u²`` (as ``np.stack([np.ones_like(u), u, u * u], axis=1)`` makes them)."""
    m = np.empty((u.size, 3))
    m[:, 0] = 1.0
    m[:, 1] = u
    m[:, 2] = u * u
    return m


def lstsq_full_rank(m: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    """``np.linalg.lstsq(m, y)``'s solution, None where ``m`` is rank-deficient by ``np.linalg.matrix_rank``.

    The rank is asked only where lstsq's own singular values leave it in doubt: both decompositions are
    backward stable (each singular value within a small multiple of eps·σ_max of the exact one), so a smallest
    over 1e-8 of the largest is full rank by either, far above matrix_rank's max(shape)·eps cut-off.
    """
    coef, _, _, sv = np.linalg.lstsq(m, y, rcond=None)
    if not float(sv.min()) > 1e-8 * float(sv.max()) and matrix_rank(m) < m.shape[1]:
        return None
    return coef


def matrix_rank(m: np.ndarray) -> int:
    """``np.linalg.matrix_rank`` of a 2-D array: its singular values over ``max(shape)·eps`` of the largest."""
    s = np.linalg.svd(m, compute_uv=False)
    return int(np.count_nonzero(s > float(s.max()) * (max(m.shape) * _EPS)))


def pinv(a: np.ndarray) -> np.ndarray:
    """``np.linalg.pinv`` of a real 2-D array (its default cut-off), the same numbers: its SVD and products."""
    u, s, vt = np.linalg.svd(a, full_matrices=False)
    large = s > 1e-15 * s.max()
    s = np.divide(1, s, where=large, out=s)
    s[~large] = 0
    return np.matmul(np.transpose(vt), np.multiply(s[..., np.newaxis], np.transpose(u)))
