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

from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.quality import UNRELIABLE
from lelsonar.reconstruct.estimate.robust import median
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import piston_power
from lelsonar.reconstruct.estimate.surfaces.measurement import (
    Measured,
    measure_region,
    mirror_normalised,
    step_medians,
)
from lelsonar.reconstruct.estimate.surfaces.regions import capsule_subregion
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.stack import capsule_x, stack_fits, stack_profile, two_targets

__all__ = [
    "off_fan_sines",
    "off_fan_corner",
    "off_fan_tilt",
    "taken_back",
    "off_fan_weak",
    "separate_targets",
    "split_stack",
]


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

    The slope fitted over the steps' capsule pairs (:func:`~.stack.stack_fits`) is that at the middle ``x_m``
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


def off_fan_corner(m: Measured, top: float, ref: float, beam_k: float, opts: SurfaceOptions) -> str:
    """Why a target every capsule hears may be a corner off the fan ("": its echo taken back is a diffraction's).

    Its ranges' slope along the stack puts it ``t`` off the fan at the array's centre (:func:`~.stack.stack_tilt`'s
    tilt, exact for a point or a line across the stack), where the beam heard it at ``D(ψ)²`` of its peak: its upper
    estimate over the piston's power 3 σ farther out (:func:`~.beam_pattern.piston_power`, no understatement) still
    under ``weak_echo`` of the sweep's strongest is a diffraction's.

    Parameters
    ----------
    m : Measured
    top : float
        The region's strength, an upper estimate (mirror-normalised; NaN: unknown).
    ref : float
        The sweep's strongest mirror-normalised echo.
    beam_k : float
        The sweep's beam curvature in ``log A`` across γ, 1/rad².
    opts : SurfaceOptions
    """
    if math.isfinite(m.tilt_stderr):
        power = piston_power(abs(m.tilt) + 3.0 * m.tilt_stderr, beam_k)
        if power > 0 and math.isfinite(top) and math.isfinite(ref) and top / power < opts.weak_echo * ref:
            return ""
    return f"its ranges' slope along the stack puts it {math.degrees(m.tilt):+.0f}° off the fan: maybe a corner"


def separate_targets(
    measured: list[Measured],
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
    step: float,
) -> tuple[list[Measured], set[int]]:
    """The regions with each target part of the stack hears apart, and the indices of those targets.

    * A region of a run whose capsules hear two targets at ranges apart by more than the stack's length
      (:attr:`~.regions.Region.part`) is the nearer one's, heard by no more capsules than the farther one: it
      leaves the regions, and the pass over the readings no region holds takes it up with every capsule's
      readings of it (a target off the fan beside the stack).  Else it is a region of the fan.
    * A region whose range profile along the stack bends as no one target's does (:func:`~.stack.stack_profile`:
      two targets at one range on either side of the stack, two jambs of a doorway) splits into the capsules
      that hear each (:func:`~.stack.two_targets`), each a target part of the stack hears.  Where no two
      convex sides explain it, its tilt is anywhere within the beam's half-width and its verdict says why.

    Each target part of the stack hears is tilted off the fan as its capsules' slope says (:func:`off_fan_tilt`).
    """
    out: list[Measured] = []
    partial: set[int] = set()
    for m in measured:
        if m.region.part and _nearer_minority(m, distance, opts):
            continue
        targets = split_stack(m, gamma, distance, amplitude, geometry, opts, step)
        if targets is None:
            out.append(m)
            continue
        for t in targets:
            if t is not m:
                partial.add(len(out))
            out.append(t)
    return out, partial


def split_stack(
    m: Measured,
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
    step: float,
) -> list[Measured] | None:
    """A region that holds two targets along the stack (:func:`~.stack.two_targets`) as the targets part of the
    stack hears, each tilted off the fan as its capsules' slope says; None when it holds one.

    Where no two targets explain it, the region itself, its tilt anywhere within the beam's half-width and its
    verdict saying why.
    """
    r = m.region
    x = capsule_x(geometry)
    profile = stack_profile(x, r.rows, r.capsules, m.ranges)
    if profile is None:
        heard = np.unique(r.capsules)
        heard = heard[np.argsort(x[heard], kind="stable")]
        profile = (heard, np.zeros(0), np.zeros(0))
    split = two_targets(profile, _apart(m, profile[0], x, distance, opts), opts.curvature_sigmas)
    if split is None:
        return None
    if isinstance(split, str):
        reach = opts.beyond_cut / math.sqrt(3.0)
        return [replace(m, tilt_stderr=reach, findings=(*m.findings, (UNRELIABLE, f"two targets: {split}")))]
    out = []
    for side in split:
        sub = capsule_subregion(r, side)
        if sub.steps.size >= opts.min_steps:
            out.append(_off_fan(measure_region(sub, gamma, distance, amplitude, geometry, opts, step=step), opts))
    return out


def _apart(m: Measured, heard: np.ndarray, x: np.ndarray, distance: np.ndarray, opts: SurfaceOptions) -> np.ndarray:
    """Per two neighbours of ``heard`` (stack order), whether a capsule between them that the region does not hold
    hears something farther than the region's range at most of its steps (and nothing nearer)."""
    r = m.region
    own = median(m.ranges)
    block = distance[r.steps]
    out = np.zeros(max(heard.size - 1, 0), dtype=bool)
    for j in range(heard.size - 1):
        lo, hi = sorted((float(x[heard[j]]), float(x[heard[j + 1]])))
        for c in np.flatnonzero((x > lo) & (x < hi)):
            v = block[:, c]
            with np.errstate(invalid="ignore"):
                farther = np.count_nonzero(v > own + opts.range_tolerance)
                nearer = np.count_nonzero(v < own - opts.range_tolerance)
            out[j] |= nearer == 0 and 2 * farther > v.size
    return out


def _off_fan(m: Measured, opts: SurfaceOptions) -> Measured:
    """A target part of the stack hears, tilted as its capsules' slope says (:func:`off_fan_tilt`)."""
    tilt, tilt_se = off_fan_tilt(m, opts)
    return replace(m, tilt=tilt, tilt_stderr=tilt_se)


def _nearer_minority(m: Measured, distance: np.ndarray, opts: SurfaceOptions) -> bool:
    """Whether the region's target is nearer, by more than the range tolerance, than what its steps' other
    capsules hear, and heard by no more capsules than they are at its median step (a first-echo receiver hears
    the nearer target first, so the rest hear another one)."""
    r = m.region
    mine = np.zeros((r.steps.size, distance.shape[1]), dtype=bool)
    mine[np.searchsorted(r.steps, r.rows), r.capsules] = True
    block = distance[r.steps]
    rest = ~mine & np.isfinite(block)
    others = block[rest]
    if not others.size or float(np.median(mine.sum(axis=1) - rest.sum(axis=1))) > 0:
        return False
    return float(np.median(m.ranges)) < float(np.median(others)) - opts.range_tolerance
