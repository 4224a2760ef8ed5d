"""A target only part of the capsule stack hears: how far off the fan it lies, and how strong its echo is there.

Whatever the target (a plane's foot, a line's or a point's nearest point), the range's slope along the stack at
capsule ``c`` is ``∂d/∂x = (x_c − x_0)/d_c = −sin ψ_c``: the angle off the fan of the echo's direction from that
capsule (Kleeman & Kuc: the receivers' differential ranges tell where a target lies across the array).  Two
capsules or more that hear it give that slope, so each capsule's angle off the fan (:func:`off_fan_sines`), the
target's tilt seen from the array's centre (:func:`off_fan_tilt`), and its echo taken back to the beam's axis
through the beam pattern (:func:`taken_back`): on the beam's flank a capsule hears ``D(ψ)²`` of the echo's peak,
so a diffracting edge seen there is weak only once that is undone (:func:`off_fan_weak`).  With one capsule
nothing says how far off the fan it lies.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.reconstruct.estimate.surfaces.beam_pattern import piston_power
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, mirror_normalised, step_medians
from lelsonar.reconstruct.estimate.surfaces.regions import stack_fits
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions

__all__ = ["off_fan_sines", "off_fan_tilt", "taken_back", "off_fan_weak"]


def _middle(m: Measured) -> tuple[float, float, float] | None:
    """``sin ψ`` at the middle of the capsules heard, its σ and that middle's ``x`` (None: no slope)."""
    x = m.positions[:, 0]
    heard = np.unique(x).size
    if heard < 2 or not m.depth > 0:
        return None
    (lin, lin_cov, _), _ = stack_fits(x, m.region.rows, m.ranges)
    s, var = float(lin[0]), float(lin_cov[0, 0])
    if not (math.isfinite(s) and math.isfinite(var) and var > 0 and abs(s) < 1):
        return None
    lo, hi = float(x.min()), float(x.max())
    # With three or more capsules the fitted slope may sit anywhere between them.
    turn = (1.0 - s * s) / m.depth
    sigma = math.sqrt(var) if heard == 2 else math.hypot(math.sqrt(var), 0.25 * turn * (hi - lo))
    return -s, sigma, 0.5 * (lo + hi)


def off_fan_sines(m: Measured) -> tuple[np.ndarray, float] | None:
    """How far off the fan a target part of the stack hears lies, seen from each of its readings' capsules:
    ``sin ψ`` per reading and its σ.

    The slope fitted over the steps' capsule pairs (:func:`~.regions.stack_fits`) is that at the middle ``x_m``
    of the capsules heard (exact for two: a point's ranges are a parabola in ``x`` to second order); from there
    ``sin ψ`` moves by ``(1 − sin²ψ)/ρ`` per m along the stack.  With three or more capsules the fitted slope may
    sit anywhere between them: a quarter of that change over the capsules' extent is added to its σ.

    Parameters
    ----------
    m : Measured
        The region: its readings' capsule positions and ranges, its depth.

    Returns
    -------
    (``sin ψ`` per reading of the region, its σ), or None when fewer than two capsules hear the target or no
    step holds two of them (the slope is not determined).
    """
    middle = _middle(m)
    if middle is None:
        return None
    s, sigma, mid = middle
    return s - (m.positions[:, 0] - mid) * (1.0 - s * s) / m.depth, sigma


def off_fan_tilt(m: Measured, opts: SurfaceOptions) -> tuple[float, float]:
    """The tilt off the fan, seen from the array's centre, of a target part of the stack hears, and its σ.

    The stack slope is that at the middle ``x_m`` of the capsules heard (:func:`off_fan_sines`), not at the
    array's centre: a point ``x_0`` across the stack is at ``sin t = (x_0 − x_m)/ρ`` from there and ``x_0/ρ``
    from the centre, so the centre's ``sin t`` is the middle's plus ``x_m (1 − sin²t)/ρ``.  With one capsule (or
    no slope) the target lies anywhere within the beam's half-width (``beyond_cut``): the tilt stays the
    region's, its σ that reach's uniform one beside the slope's own.

    Returns
    -------
    (tilt rad, σ rad)
    """
    middle = _middle(m)
    if middle is None:
        reach = opts.beyond_cut / math.sqrt(3.0)
        se = m.tilt_stderr
        return m.tilt, (math.hypot(se, reach) if math.isfinite(se) else reach)
    s, sigma, mid = middle
    sin_t = max(-1.0, min(1.0, s + mid * (1.0 - s * s) / m.depth))
    return math.asin(sin_t), sigma / max(math.sqrt(1.0 - sin_t * sin_t), 1e-3)


def taken_back(
    m: Measured, amplitude: np.ndarray, beam_k: float, opts: SurfaceOptions
) -> tuple[Measured, float] | None:
    """A target part of the stack hears, its echo taken back from off the fan to the beam's axis.

    On the beam's flank each capsule hears the target at ``D(ψ_c)²`` of its peak (``ψ_c`` from
    :func:`off_fan_sines`): each reading's amplitude over that, with ``ψ_c`` 3 σ farther off the fan, through
    the piston (:func:`~.beam_pattern.piston_power`, which falls at least as fast as the beam's parabola)
    overstates the peak, so the region's strength from them is an upper estimate of its echo's in the fan.

    Parameters
    ----------
    m : Measured
    amplitude : (n_steps, n_capsules) array
        The sweep's echo amplitudes, V.
    beam_k : float
        The sweep's beam curvature in ``log A`` across γ, 1/rad².
    opts : SurfaceOptions

    Returns
    -------
    (the region with its amplitudes taken back, the largest angle off the fan used, rad), or None when fewer
    than two capsules hear it, the slope is not determined or some capsule may see it past the first null.
    """
    sines = off_fan_sines(m)
    if sines is None:
        return None
    far = np.minimum(1.0, np.abs(sines[0]) + 3 * sines[1])
    power = np.array([piston_power(math.asin(float(v)), beam_k) for v in far])
    if not np.all(power > 0):
        return None
    r = m.region
    table = np.full(amplitude.shape, np.nan)
    table[r.rows, r.capsules] = amplitude[r.rows, r.capsules] / power
    per_step = step_medians(r, table)
    if not np.isfinite(per_step).any():
        return None
    peak = float(np.nanmax(per_step))
    back = replace(m, step_amplitude=per_step, peak=peak, strength=mirror_normalised(peak, m.depth, opts))
    return back, math.asin(float(far.max()))


def off_fan_weak(top: float, ref: float, psi: float, opts: SurfaceOptions) -> str:
    """Why a target part of the stack hears diffracts, its echo taken back from off the fan (:func:`taken_back`),
    or "" where it could be as strong as a mirror's.

    A diffracting edge's echo is a small share of a mirror's at its range, a concave corner's as strong as one
    (``weak_echo``): an upper estimate of the echo's peak under that share is an edge's.

    Parameters
    ----------
    top : float
        The taken-back region's strength, an upper estimate (mirror-normalised; NaN: unknown).
    ref : float
        The sweep's strongest mirror-normalised echo (a mirror's or a corner's).
    psi : float
        The largest angle off the fan the echo was taken back from, rad.
    opts : SurfaceOptions
    """
    if not (math.isfinite(top) and math.isfinite(ref) and ref > 0 and top < opts.weak_echo * ref):
        return ""
    return (
        f"echo at most {100 * top / ref:.0f} % of the sweep's strongest once taken back from up to "
        f"{math.degrees(psi):.0f}° off the fan (its ranges' slope along the stack, 3 σ out): diffraction"
    )
