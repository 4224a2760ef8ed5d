"""What a corner's or an edge's own echoes admit of the kind and place its classification gave it.

A pair corner is their double bounce only where its own range, slope along the stack, bearing and strength admit
their line's point (:func:`pair_denied`); an end placed on a plane's trace is there only where its echo does not
fade toward that placement (:func:`falls_toward`); a double bounce with a surface across the fan is told from its
plane's own mirror only by its extra range (:func:`like_its_mirror`).  Where they do not admit it, the feature
says so (the reasons these constants start) and its kind is not settled.
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.surfaces.beam_pattern import (
    log_amplitude_noise,
    log_echoes_in_order,
    peak_at_bearing,
)
from lelsonar.reconstruct.estimate.surfaces.evidence import wrap
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, mirror_normalised
from lelsonar.reconstruct.estimate.surfaces.placement import RANGE_FLOOR
from lelsonar.reconstruct.estimate.surfaces.results import UNSETTLED
from lelsonar.reconstruct.estimate.surfaces.strength import EchoScale

__all__ = [
    "ALIKE",
    "DOUBLE_BOUNCE_HEADROOM",
    "NOT_ITS_END",
    "NOT_THEIR_LINE",
    "falls_toward",
    "like_its_mirror",
    "pair_denied",
]

#: A double bounce travels as far as a mirror's echo at the corner's range and is that mirror's times the two
#: walls' reflectivities, so no stronger than the sweep's strongest mirror; one amplitude window may sum it with
#: another echo of like strength, at most doubling it.  Past this many times the sweep's strongest echo it is not.
DOUBLE_BOUNCE_HEADROOM = 2.0

#: In the reasons of a corner at two planes' double-bounce range whose own echoes deny their line.
NOT_THEIR_LINE = "not placed on the line of the two planes at its range"

#: In the reasons of a plane's double bounce with a surface across the fan too near the plane's own mirror.
ALIKE = "not told from its plane's own echo"

#: In the reasons of an end whose echo fades toward where its plane's trace would put it.
NOT_ITS_END = "not its plane's end"


def falls_toward(gamma: np.ndarray, amplitude: np.ndarray, bearing: float, *, sigmas: float = 3.0) -> float:
    """How far (in log amplitude) a region's echo falls toward ``bearing`` past its span, beyond what the
    amplitude noise allows (0: it does not).

    One target's echo follows ``D(γ − β)²`` across γ, which falls monotonically away from ``β`` over the main
    lobe; the scanner turns in place, so the target's view of it (its range, and a corner's retro-reflecting
    aperture) stays the same across the sweep.  Over a span wholly on one side of ``β`` the echo therefore
    rises toward ``β``: its strongest step is the one nearest ``β`` up to the noise.  The span's largest log
    amplitude over the larger of its two steps nearest ``β`` by more than ``sigmas`` σ of a two-step difference
    contradicts a target at ``β``; σ is the log amplitudes' own (:func:`~.beam_pattern.log_amplitude_noise`).

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        The region's steps' γ (rad) and each step's echo amplitude (NaN: none).
    bearing : float
        rad: where the target is supposed to lie.
    sigmas : float

    Returns
    -------
    The excess fall, log amplitude (0 where the echo does not fall toward ``bearing``, where ``bearing`` lies
    inside the span, or where fewer than 4 steps have an amplitude).
    """
    g, la = log_echoes_in_order(gamma, amplitude)
    if g.size < 4:
        return 0.0
    centre = 0.5 * float(g[0] + g[-1])
    bearing = centre + wrap(bearing - centre)
    if g[0] <= bearing <= g[-1]:
        return 0.0
    sigma = log_amplitude_noise(la)
    near = float(la[-2:].max()) if bearing > g[-1] else float(la[:2].max())
    excess = float(la.max()) - near - sigmas * math.sqrt(2.0) * sigma
    return max(excess, 0.0)


def like_its_mirror(m: Measured, own: Measured, pj: Measured) -> str:
    """Why a plane's double bounce with a surface across the fan is not told from that plane's own echo ("":
    it is).

    The line across the fan ``z`` off it answers from ``√(h² + z²)``, ``z²/(2h)`` behind the plane's mirror at
    depth ``h``; its slope along the stack is also what the plane's own mirror shows where the plane leans
    along the stack (a wall's yaw seen by a vertical fan), at the plane's own depth.  Only the extra range
    tells them apart: under 3 σ of the two depths' difference (the region's, the plane's), the echo may be
    either, so its kind is not settled and it is placed where its own echo comes from.
    """
    z = pj.depth * math.tan(m.tilt)
    extra = math.hypot(pj.depth, z) - pj.depth
    se = math.hypot(own.depth_stderr, pj.depth_stderr)
    if not (math.isfinite(extra) and math.isfinite(se)) or extra > 3.0 * se:
        return ""
    return (
        f"{ALIKE}: its double bounce with a surface {z:+.2f} m along the stack answers {1000 * extra:.1f} mm behind "
        f"the plane's mirror, within 3 σ of the two depths ({1000 * 3 * se:.1f} mm), as the plane's own echo "
        f"leaning along the stack does; {UNSETTLED}"
    )


def _across_ray(bearing: float) -> np.ndarray:
    """The unit vector across the ray at ``bearing`` in the fan (the direction a bearing error moves a point)."""
    return np.array([0.0, -math.sin(bearing), math.cos(bearing)])


def pair_denied(own: Measured, point: np.ndarray, covariance: np.ndarray, scale: EchoScale) -> str:
    """Why a region's own echoes deny that it is the double bounce of a line through ``point`` ("": they do not).

    Two planes meeting at the region's range say nothing of whether its echo comes from their line: another
    corner or edge at that range echoes the same.  What the region measured itself must admit the line's point:

    * **range**: a double bounce off their line comes back from its point nearest the array, ``|X|`` away: the
      region's own depth apart from it by more than 3 σ of both (the depth's, at least one reading's noise; the
      line's along the ray through the planes' covariance), and by more than one target's ranges scatter within a
      region (``range_tolerance``), is another target's echo.
    * **tilt**: the ranges' slope along the capsule stack is the x component of the unit vector from the echo's
      point to the array, whatever the target (:mod:`.placement`); the line's point leans off the fan by
      ``asin(X_x/|X|)``.  Apart by more than 3 σ of both (the region's slope fit; the line's lean through the
      planes' covariance), the echo comes from elsewhere.
    * **bearing**: the region's own bearing (its region's centre or its amplitude peak: where the beam points
      at its echo's source, whatever the target) apart from the line's point's by more than 3 σ of both (its
      own; the line's across the ray through the planes' covariance).  Only from a region not cut on both
      sides: a nearer echo bends the amplitude where it cuts the region, and on both sides it leaves no
      stretch of the echo's own to place its peak.
    * **strength**: with the line's bearing outside the region's span, the region hears it on the beam's
      flank only; its echo taken back there through the beam pattern (:func:`~.beam_pattern.peak_at_bearing`,
      a lower bound of the peak) is a double bounce's only up to :data:`DOUBLE_BOUNCE_HEADROOM` times the
      sweep's strongest echo.

    Parameters
    ----------
    own : Measured
        The region as its own echoes measured it (before its kind placed it).
    point, covariance : (3,) and (3, 3) arrays
        The line's point nearest the array and its covariance, m, m².
    scale : EchoScale
        The sweep's echo references.

    Returns
    -------
    The reason, or "".
    """
    rho = float(np.linalg.norm(point))
    if not rho > 0:
        return ""
    u = point / rho
    own_se = max(RANGE_FLOOR, own.depth_stderr) if math.isfinite(own.depth_stderr) else RANGE_FLOOR
    range_se = math.hypot(own_se, math.sqrt(max(float(u @ covariance @ u), 0.0)))
    bound = max(3 * range_se, scale.opts.range_tolerance)
    if abs(own.depth - rho) > bound:
        return (
            f"{NOT_THEIR_LINE}: its echo comes from {own.depth:.3f} m, their line's point nearest the array is "
            f"{rho:.3f} m away (more than {100 * bound:.1f} cm)"
        )
    lean = math.asin(max(-1.0, min(1.0, float(u[0]))))
    bearing = math.atan2(float(u[2]), float(u[1]))
    if math.isfinite(own.tilt) and math.isfinite(own.tilt_stderr) and own.tilt_stderr > 0:
        ct, st = math.cos(lean), math.sin(lean)
        e_t = np.array([ct, -st * math.cos(bearing), -st * math.sin(bearing)])
        lean_se = math.sqrt(max(float(e_t @ covariance @ e_t), 0.0)) / rho
        se = math.hypot(own.tilt_stderr, lean_se)
        if abs(own.tilt - lean) > 3 * se:
            return (
                f"{NOT_THEIR_LINE}: its ranges slope along the capsule stack as a target "
                f"{math.degrees(own.tilt):+.1f}° off the fan, their line's point {math.degrees(lean):+.1f}° "
                f"(3 σ: {math.degrees(3 * se):.1f}°)"
            )
    if own.bearing_source != "undetermined" and not (own.region.cut_before and own.region.cut_after):
        line_se = math.sqrt(max(float(_across_ray(bearing) @ covariance @ _across_ray(bearing)), 0.0)) / rho
        se = math.hypot(own.bearing_stderr, line_se)
        gap = abs(wrap(own.bearing - bearing))
        if gap > 3 * se:
            return (
                f"{NOT_THEIR_LINE}: its own {own.bearing_source} puts its echo's source at "
                f"{math.degrees(own.bearing):.1f}°, their line's point at {math.degrees(bearing):.1f}° "
                f"(3 σ: {math.degrees(3 * se):.1f}°)"
            )
    g0, g1 = own.span
    outside = bearing < g0 - own.step or bearing > g1 + own.step
    if outside and math.isfinite(scale.mirror) and math.isfinite(scale.beam_k):
        at = peak_at_bearing(scale.gamma[own.region.steps], own.step_amplitude, bearing, scale.beam_k)
        traced = float("nan") if at is None else mirror_normalised(at[0], own.depth, scale.opts)
        if traced > DOUBLE_BOUNCE_HEADROOM * scale.mirror:
            return (
                f"{NOT_THEIR_LINE}: heard at γ {math.degrees(g0):.1f}…{math.degrees(g1):.1f}°, its echo taken back "
                f"to their line at {math.degrees(bearing):.1f}° would be {traced / scale.mirror:.1f}× the sweep's "
                "strongest, more than a double bounce gives"
            )
    return ""
