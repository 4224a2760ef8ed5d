"""How strong a region's echo is against its sweep's own references: a mirror's, a diffraction's or unknown.

The references come from the sweep itself (:func:`echo_scale`): its strongest echo, range-corrected (a mirror's
or a corner's), the beam's curvature in log amplitude (what extrapolates the peak of a region cut before its
peak) and the receiver's full scale (where a peak clips).  The tests (:class:`EchoScale`): an echo's upper
estimate well under the reference diffracts (weak); its observed peak, a lower bound, at or over it is a
mirror's or a corner's (strong); a plane's end is weighed against that plane's own mirror echo where it can be.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lelsonar.reconstruct.estimate.corner.wall import ECHO_WINDOW_RANGE
from lelsonar.reconstruct.estimate.robust import median
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import (
    PLATEAU,
    extrapolated_peak,
    log_amplitude_curvature,
    peak_at_bearing,
)
from lelsonar.reconstruct.estimate.surfaces.evidence import stack_dihedral
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, mirror_normalised
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions

__all__ = ["EchoScale", "echo_scale"]


@dataclass(frozen=True, eq=False)
class EchoScale:
    """One sweep's echo references and the strength tests made against them.

    Attributes
    ----------
    gamma : (n_steps,) array
        The sweep's measured rotation of each step, rad.
    opts : SurfaceOptions
    mirror : float
        The sweep's strongest echo, range-corrected (NaN: fewer than two regions have a strength).
    beam_k : float
        The beam's curvature in log amplitude, median over the regions with an unclipped peak (NaN: none).
    beam_low : float
        The flattest top one echo shows in this sweep: flatter, a second echo widens it.
    full_scale : float
        The receiver's full scale: the sweep's largest peak, V.
    """

    gamma: np.ndarray
    opts: SurfaceOptions
    mirror: float
    beam_k: float
    beam_low: float
    full_scale: float

    def upper_strength(self, m: Measured) -> float:
        """The region's strength if its peak is inside it, else an upper estimate of it (NaN: none)."""
        if m.peak_inside and m.clipped and m.peak >= (1.0 - PLATEAU) * self.full_scale:
            return float("nan")  # a clipped peak is only a lower bound of its echo: no upper estimate
        if m.peak_inside:
            return m.strength
        if not math.isfinite(self.beam_k):
            return float("nan")
        peak = extrapolated_peak(
            self.gamma[m.region.steps],
            m.step_amplitude,
            self.beam_k,
            before=self.opts.beyond_cut if m.region.cut_before else 0.0,
            after=self.opts.beyond_cut if m.region.cut_after else 0.0,
        )
        return float("nan") if peak is None else mirror_normalised(peak, m.depth, self.opts)

    def weak(self, m: Measured, ref: float | None = None) -> bool:
        """The region's upper estimate under ``weak_echo`` × ``ref`` (default: the sweep's strongest)."""
        ref = self.mirror if ref is None else ref
        top = self.upper_strength(m)
        return math.isfinite(ref) and math.isfinite(top) and top < self.opts.weak_echo * ref

    def strong(self, m: Measured, ref: float | None = None) -> bool:
        """The region's observed peak, a lower bound of its own, at or over ``weak_echo`` × ``ref``."""
        ref = self.mirror if ref is None else ref
        return math.isfinite(ref) and math.isfinite(m.strength) and m.strength >= self.opts.weak_echo * ref

    def end_strength(self, m: Measured, mj: Measured, *, confirmed: bool = False) -> tuple[str, str]:
        """Whether a plane's end (or its line across the fan) echoes weakly, strongly or unknown, and why.

        Against the plane's own mirror echo (same material, a like range) where its peak is clean, else the
        sweep's strongest.  In order: the region's own peak is a lower bound (strong); where a step lies on
        the beam's top, the beam pattern taken back from its steps to the bearing the geometry puts it at (see
        peak_at_bearing) is close to the peak (strong or weak); the upper estimate from its flank's own slope
        (weak); that beam pattern taken back from farther out, a lower bound (strong).  ``confirmed``: the
        readings themselves confirm the bearing (one line explains every range), so that lower bound comes
        before the flank's slope, whose few steps' noise can put its vertex anywhere.
        """
        opts = self.opts
        mirror = self.mirror
        ref = mj.strength if mj.exact and math.isfinite(mj.strength) else mirror
        # (By identity: the plane whose echo is the sweep's strongest is weighed as the sweep's strongest.)
        of = "its plane's mirror echo" if ref is not mirror else "the sweep's strongest"
        if not math.isfinite(ref):
            return "unknown", ""
        if self.strong(m, ref):
            return "strong", f"with an echo as strong as {of}"
        at = peak_at_bearing(self.gamma[m.region.steps], m.step_amplitude, m.bearing, self.beam_k)
        traced = float("nan") if at is None else mirror_normalised(at[0], m.depth, opts)
        share = f"{100 * traced / ref:.0f} % of {of} at the bearing the geometry puts it at"
        strong_there = f"with an echo as strong as {of} once the beam pattern is taken back there ({share})"
        if confirmed and traced >= opts.weak_echo * ref:
            return "strong", strong_there
        if at is not None and at[1] <= math.log(2.0):
            # A step on the beam's top: the estimate is close to the peak either way.
            if traced >= opts.weak_echo * ref:
                return "strong", strong_there
            return "weak", f"with a weak (diffracted) echo: {share}"
        if self.weak(m, ref):
            return "weak", f"with a weak (diffracted) echo: under {of} × {opts.weak_echo:.2f}"
        if traced >= opts.weak_echo * ref:
            return "strong", strong_there
        return "unknown", ""


def echo_scale(measured: list[Measured], gamma: np.ndarray, opts: SurfaceOptions) -> EchoScale:
    """The sweep's echo references, from its own measured regions.

    Parameters
    ----------
    measured : list of Measured
        Every region of the sweep.
    gamma : (n_steps,) array
        Measured rotation of each step, rad.
    opts : SurfaceOptions

    Returns
    -------
    EchoScale
    """
    g = gamma
    # The strongest echo of the sweep, range-corrected, is a mirror's or a corner's (a clipped or cut one's is
    # a lower bound of its own, so the largest is still no edge's unless the sweep saw only edges); an echo
    # far below it diffracts.  A median would not do: in a cluttered sweep most regions may be edges.  A
    # plane whose double bounce with a surface across the fan answers beside it inside the amplitude window
    # holds both echoes' sum in its amplitude, no one echo's: it is the reference only if nothing else is.
    strengths = [m.strength for m in measured if math.isfinite(m.strength)]
    own = [m.strength for m in measured if math.isfinite(m.strength) and not summed_echo(m, measured, opts)]
    mirror = (max(own) if own else max(strengths)) if len(strengths) >= 2 else float("nan")
    # The beam's curvature in log amplitude, from this sweep's own regions with an unclipped peak: what puts the peak
    # of a region cut before its peak (an upper estimate of its strength, see extrapolated_peak).
    ks = [
        k
        for m in measured
        if m.exact
        for k in [log_amplitude_curvature(g[m.region.steps], m.step_amplitude)]
        if k is not None
    ]
    beam_k = median(np.asarray(ks, dtype=np.float64)) if ks else float("nan")
    # The flattest top one echo shows in this sweep (3 σ of its regions' spread under their median, robust):
    # flatter, a second echo widens it.
    beam_low = (
        beam_k - 3 * 1.4826 * median(np.abs(np.asarray(ks, dtype=np.float64) - beam_k)) if len(ks) >= 3 else beam_k
    )

    # The receiver clips at one level, its full scale: the sweep's largest peak.  A plateau well under it is the
    # amplitude's quantisation on a weak echo, whose peak stands.
    full_scale = max((m.peak for m in measured if math.isfinite(m.peak)), default=float("nan"))
    return EchoScale(gamma=g, opts=opts, mirror=mirror, beam_k=beam_k, beam_low=beam_low, full_scale=full_scale)


def summed_echo(m: Measured, measured: list[Measured], opts: SurfaceOptions) -> bool:
    """Whether the region's amplitude sums its own echo with its double bounce with a surface across the fan.

    A wall's corner with the floor below a horizontal fan answers ``z²/(2h)`` behind the wall's mirror (``z``
    the array's height, ``h`` the wall's depth): inside the amplitude window
    (:data:`~lelsonar.reconstruct.estimate.corner.wall.ECHO_WINDOW_RANGE`) beyond a metre or so, and nearly
    on the beam's axis far away, where it is as strong as a mirror.  The region beside ``m`` (within the
    steps a run may bridge) that is that double bounce (:func:`~.evidence.stack_dihedral`), deeper by no more
    than the window's reach, shows it.
    """
    reach = (opts.max_gap + 2) * m.step
    for k in measured:
        if k is m or not 0.0 < k.depth - m.depth <= ECHO_WINDOW_RANGE:
            continue
        if k.span[0] > m.span[1] + reach or k.span[1] < m.span[0] - reach:
            continue
        if stack_dihedral(k, [m], opts) is not None:
            return True
    return False
