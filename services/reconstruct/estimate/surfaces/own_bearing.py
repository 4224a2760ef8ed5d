"""What a corner or an edge placed by its own echo can claim of its bearing.

* :func:`continued_ends`: an end of a region where the same capsules go on hearing the same range on the next
  step is no fade of its echo: the rest of it lies past the region, so that end says nothing of where its
  target lies (as an end cut by a nearer echo).
* :func:`peak_past_fade`: an amplitude peak farther from an end where the echo fades than one beam pattern's
  fall to that end's amplitude allows is not that echo's alone; its σ covers the difference.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.reconstruct.estimate.surfaces.beam_pattern import log_amplitude_noise, log_echoes_in_order
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured

__all__ = ["CONTINUED", "continued_ends", "peak_past_fade"]

#: In the reasons of a region whose echo goes on past an end in another region.
CONTINUED = "its echo goes on past its region"


def continued_ends(
    m: Measured, regions: list[Measured], tolerance: float, distance: np.ndarray | None = None
) -> tuple[Measured, str]:
    """The region with each end cut where its echo goes on past it, and the reason to add ("": none).

    A region's end is where its echo fades under the threshold, or where a nearer echo hides it (cut).  Where
    one of its capsules hears, on the step just past that end, a range within ``tolerance`` (one target's
    ranges' scatter) of its own reading at the end, the echo has done neither: it goes on, split off by what
    the other capsules hear.  That end is no fade, as a cut end is not.

    Parameters
    ----------
    m : Measured
        The region as its own echoes measured it.
    regions : list of Measured
        Every region of the sweep (``m`` among them): what holds the readings past its ends, without ``distance``.
    tolerance : float
        m.
    distance : (n_steps, n_capsules) array, optional
        The sweep's ranges (NaN: none); read in place of ``regions`` where given.

    Returns
    -------
    The region (its ends so cut) and the reason ("" where neither end goes on).
    """
    r = m.region
    if r.steps.size == 0:
        return m, ""
    first, last = int(r.steps[0]), int(r.steps[-1])

    def goes_on(end: int, past: int) -> bool:
        """Whether a capsule at step ``past`` hears a range within ``tolerance`` of its own reading at ``end``."""
        at_end = r.rows == end
        own = dict(zip(r.capsules[at_end].tolist(), m.ranges[at_end].tolist(), strict=True))
        if distance is not None:
            if not 0 <= past < distance.shape[0]:
                return False
            return any(abs(float(distance[past, c]) - d) <= tolerance for c, d in own.items())
        for k in regions:
            if k is m or k.region is r:
                continue
            there = k.region.rows == past
            for c, d in zip(k.region.capsules[there].tolist(), k.ranges[there].tolist(), strict=True):
                if c in own and abs(d - own[c]) <= tolerance:
                    return True
        return False

    before = not r.cut_before and goes_on(first, first - 1)
    after = not r.cut_after and goes_on(last, last + 1)
    if not (before or after):
        return m, ""
    region = replace(r, cut_before=r.cut_before or before, cut_after=r.cut_after or after)
    side = "both ends" if before and after else ("its first step" if before else "its last step")
    why = f"{CONTINUED}: past {side} its capsules go on hearing its range, so no fade ends it there"
    return replace(m, region=region), why


def peak_past_fade(m: Measured, gamma: np.ndarray, beam_k: float, *, sigmas: float = 3.0) -> tuple[Measured, str]:
    """An amplitude peak no one beam pattern reaches from where its echo fades: the σ covers how far past.

    One target's echo follows ``D(γ − β)²``; the piston falls at least as fast as its parabola ``P − k (γ − β)²``
    off the top (:func:`~.beam_pattern.peak_at_bearing`), so at an end where the echo fades (not cut) its log
    amplitude lies at least ``k (γ_end − β)²`` under the peak: the target is within
    ``w = √((log A_top − log A_end + sigmas·√2·σ) / k)`` of that end (σ the log amplitudes' noise,
    :func:`~.beam_pattern.log_amplitude_noise`; ``A_top`` the region's largest, at most the peak).  A vertex
    farther than ``w`` plus a step from it is bent by another echo summing into the window at a like range, and
    nothing says by how much: the bearing's σ grows by the excess.

    Parameters
    ----------
    m : Measured
        The region, its bearing its amplitude peak's.
    gamma : (n_steps,) array
        The sweep's γ, rad.
    beam_k : float
        The beam's curvature in log amplitude, 1/rad² (:class:`~.strength.EchoScale`).
    sigmas : float

    Returns
    -------
    The region with that σ and the reason to add ("": the peak is within reach of every fading end, or the
    region is clipped, or it has fewer than 4 steps with an amplitude).
    """
    r = m.region
    if m.bearing_source != "amplitude peak" or m.clipped or not (math.isfinite(beam_k) and beam_k > 0):
        return m, ""
    if r.cut_before and r.cut_after:
        return m, ""
    g, la = log_echoes_in_order(gamma[r.steps], m.step_amplitude)
    if g.size < 4:
        return m, ""
    top = float(la.max())
    noise = sigmas * math.sqrt(2.0) * log_amplitude_noise(la)
    worst, at, reach = 0.0, 0.0, 0.0
    for cut, end, la_end in ((r.cut_before, g[0], la[0]), (r.cut_after, g[-1], la[-1])):
        if cut:
            continue
        w = math.sqrt(max(top - float(la_end) + noise, 0.0) / beam_k)
        excess = abs(m.bearing - float(end)) - w - m.step
        if excess > worst:
            worst, at, reach = excess, float(end), w
    if not worst > 0:
        return m, ""
    why = (
        f"its amplitude peak ({math.degrees(m.bearing):.1f}°) lies {math.degrees(worst):.1f}° farther from where "
        f"its echo fades (γ {math.degrees(at):.1f}°) than one beam pattern's fall allows ({math.degrees(reach):.1f}°): "
        "another echo sums into its amplitudes: its bearing anywhere its region's reach allows"
    )
    return replace(m, bearing_stderr=math.hypot(m.bearing_stderr, worst)), why
