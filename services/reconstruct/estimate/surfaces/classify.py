"""What each region of a sweep is: a plane, or a corner or an edge and the planes it ties to.

A region is an end or a corner when it lies on another plane's trace, at two planes' double bounce, or at one
plane's double bounce with a surface across the fan; a line across the capsule stack is no plane; an echo
much weaker than the sweep's strongest at its range is a diffraction's (an edge); anything else is a plane.
The tests are in :mod:`.evidence`, the echo's strength against the sweep's own references in :mod:`.strength`.

A region whose own bearing is undetermined and which only its depth puts on one plane's trace holds two
hypotheses: that plane's end there, or a wall of its own whose foot lies past its cut end.  Its beam flank
weighs them once the sweep's piston is known (:func:`end_or_wall`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.reconstruct.estimate.quality import DEGRADED
from lelsonar.reconstruct.estimate.surfaces.evidence import (
    across_stack,
    beyond_reach,
    end_stderr,
    feature_point,
    in_fan_range,
    pair_corner,
    pair_stderr,
    plane_ends,
    plane_line,
    reach_stderr,
    stack_dihedral,
    stack_or_pair,
    walls_of_unseen_corners,
    wrap,
)
from lelsonar.reconstruct.estimate.surfaces.features import Kind
from lelsonar.reconstruct.estimate.surfaces.flank_bearing import (
    FLANK_SOURCE,
    bearing_from_flank,
    flank_measured,
    flank_reach,
    point_angles,
)
from lelsonar.reconstruct.estimate.surfaces.measurement import (
    Measured,
    across_stack_measured,
    clean_cuts,
    unit_normal,
)
from lelsonar.reconstruct.estimate.surfaces.piston_beam import SweepBeam, sweep_beam
from lelsonar.reconstruct.estimate.surfaces.results import (
    UNSETTLED,
    SurfaceOptions,
)
from lelsonar.reconstruct.estimate.surfaces.strength import EchoScale

#: How many σ of their difference apart an end's bearing and its region's own flank bearing disprove the end.
DISPUTE_SIGMAS = 3.0


class _Flanks:
    """The beam flank of regions whose depth alone places them on a trace, with the sweep's piston fitted on its
    planes once, when first needed (:mod:`.flank_bearing`)."""

    def __init__(
        self,
        planes: list[Measured],
        gamma: np.ndarray,
        amplitude: np.ndarray | None,
        scale: EchoScale,
        opts: SurfaceOptions,
        distance: np.ndarray | None = None,
    ) -> None:
        self.planes, self.gamma, self.amplitude, self.scale, self.opts = planes, gamma, amplitude, scale, opts
        self.distance = distance
        self.beam: SweepBeam | None = None
        self.fitted = False

    def of(self, m: Measured) -> tuple[Measured, bool, tuple[float, float]] | None:
        """The region placed by its flank (a mirror's), whether its peak may lie past an end where nothing else
        answers inside its amplitude window to bend the flank (the sweep's own end, or a cut by a much nearer
        echo, :func:`~.measurement.clean_cuts`), and how far past each end it may lie; None: no flank places
        it."""
        amp = self.amplitude
        if amp is None or not self.scale.beam_k > 0 or m.bearing_source != "undetermined":
            return None
        # An echo from off the fan (its ranges slope along the stack) meets the beam at ψ² ≈ (γ − β)² + t²: its
        # flank across γ is no in-fan piston's about its bearing, so it places nothing.
        if not (math.isfinite(m.tilt_stderr) and abs(m.tilt) <= 3.0 * m.tilt_stderr):
            return None
        n_steps, n_capsules = amp.shape
        clean = (False, False) if self.distance is None else clean_cuts(m.region, self.distance, self.opts)
        strict = flank_reach(m, n_steps, n_capsules, self.opts.beyond_cut, clean)
        reach = strict
        if strict == (0.0, 0.0):
            # Cut by an echo at a like range: that echo bends the flank where they meet, so the flank may choose
            # between placements on traces but not overrule them all.
            if np.median(np.bincount(np.searchsorted(m.region.steps, m.region.rows))) < n_capsules:
                return None
            cut = self.opts.beyond_cut
            reach = (cut if m.region.cut_before else 0.0, cut if m.region.cut_after else 0.0)
            if reach == (0.0, 0.0):
                return None
        if not self.fitted:
            self.beam = sweep_beam(self.planes, self.gamma, amp, 2.0 * math.sqrt(self.scale.beam_k))
            self.fitted = True
        flank = flank_measured(m, self.gamma, amp, self.beam, self.opts.beyond_cut, reach=reach)
        return (flank, strict != (0.0, 0.0), reach) if flank.bearing_source == FLANK_SOURCE else None

    def end_peak(self, m: Measured, bearing: float, reach: tuple[float, float]) -> float | None:
        """Where the region's flank puts its peak were it an end at ``bearing``: a point at its range in the fan,
        its flank fitted in that point's own angles off the axis (:func:`~.flank_bearing.point_angles`); None:
        no flank there."""
        if self.beam is None or self.amplitude is None:
            return None
        g = self.gamma[m.region.steps]
        radial = float(np.median(np.hypot(m.positions[:, 1], m.positions[:, 2])))
        rho = in_fan_range(m)[0]
        if not rho > radial:
            return None
        fit = bearing_from_flank(
            point_angles(g, bearing, rho, radial), m.step_amplitude, self.beam, before=reach[0], after=reach[1]
        )
        return None if fit is None else fit[0]


def _end_by_flank(
    m: Measured,
    placements: list[tuple[list[int], float]],
    pool: list[int],
    measured: list[Measured],
    flanks: _Flanks,
) -> tuple[tuple[list[int], float], float, str] | Measured:
    """Which placement on a trace a region whose depth alone places it is (its plane's end), a floor of its
    bearing σ and why its kind is not settled ("": it is), or the region as a wall of its own, placed by its
    flank.

    Either echo follows the beam pattern across γ about its source (a mirror's foot, a corner's retro-reflecting
    line, an end's edge, each at one range), so the flank the region shows places its peak, with its σ from the
    fit, the piston's ``ka`` and the capsules' spread (:func:`~.flank_bearing.flank_measured`).  A placement
    within :data:`DISPUTE_SIGMAS` σ of their difference agrees with it: the first placement if it does, else the
    nearest that does; where the flank agrees as well with a wall of its own whose foot lies past a cut end
    (:func:`end_undecided`), the evidence does not settle which.  None agreeing, where the flank's peak may lie
    only past an end no other echo answers at inside the amplitude window (the sweep's own, or a cut by a much
    nearer echo: nothing bends the flank there) and the echo is no diffraction's (weak against the plane's
    mirror), it is no end there: a wall.
    Otherwise the first placement stands, its σ at least its distance from the flank's peak (the evidence does
    not settle where the end lies).
    """
    first = placements[0]
    got = flanks.of(m)
    if got is None:
        return first, 0.0, ""
    flank, decisive, reach = got

    def apart(p: tuple[list[int], float]) -> float:
        # As an end there, its flank is a point's, not a mirror's: fitted in the point's own angles off the axis.
        se = end_stderr(m, measured[pool[p[0][0]]], p[1])
        peak = flanks.end_peak(m, p[1], reach)
        return abs(wrap((flank.bearing if peak is None else peak) - p[1])) / math.hypot(flank.bearing_stderr, se)

    gaps = [apart(p) for p in placements]
    best = 0 if gaps[0] <= DISPUTE_SIGMAS else int(np.argmin(gaps))
    if gaps[best] <= DISPUTE_SIGMAS:
        undecided = end_undecided(m, flank, reach, placements[best][1]) if decisive else ""
        return placements[best], 0.0, undecided
    plane = measured[pool[first[0][0]]]
    end_se = end_stderr(m, plane, first[1])
    placed = replace(m, bearing=first[1], bearing_stderr=end_se)
    # Were it the end, its echo a corner's or an edge's, its flank would still be the beam's about the end's
    # bearing: the array turns about its own axis, so the view of the end (its retro-reflecting aperture, its
    # diffraction) changes across the sweep only by the capsules' parallax, the radial offset over the range.
    gap = abs(wrap(flank.bearing - first[1]))
    sigmas = gaps[0]
    if not decisive or flanks.scale.end_strength(placed, plane)[0] == "weak":
        return first, gap, ""
    why = (
        f"on the trace of the plane at {plane.depth:.2f} m as its end at γ {math.degrees(first[1]):.1f}°, but its "
        f"beam flank peaks at {math.degrees(flank.bearing):.1f}° ± {math.degrees(flank.bearing_stderr):.1f}°, "
        f"{sigmas:.1f} σ away (and from every other placement on a trace): a wall of its own"
    )
    return replace(flank, findings=(*flank.findings, (DEGRADED, why)))


def end_undecided(m: Measured, flank: Measured, reach: tuple[float, float], bearing: float) -> str:
    """Why a flank that agrees with an end at ``bearing`` cannot tell it from a wall of its own ("": it can).

    The other hypothesis is a mirror whose foot lies past a cut end, within ``reach`` of it; its flank peaks at
    that foot.  A flank whose σ exceeds the region's whole span is flat across it: it places its peak nowhere
    in the region, so it agrees with an end inside it only as it would with anything near.  With its peak (a
    mirror's, :func:`~.flank_bearing.flank_measured`) also within :data:`DISPUTE_SIGMAS` σ of the stretch
    past a cut end, it agrees with that wall as well as with the end, and says nothing of which the region is.
    """
    g0, g1 = m.span
    if not flank.bearing_stderr > g1 - g0:
        return ""
    room = []
    if reach[0] > 0:
        room.append(max(0.0, flank.bearing - g0) if flank.bearing >= g0 - reach[0] else g0 - reach[0] - flank.bearing)
    if reach[1] > 0:
        room.append(max(0.0, g1 - flank.bearing) if flank.bearing <= g1 + reach[1] else flank.bearing - g1 - reach[1])
    sigma = flank.bearing_stderr
    if not room or not (math.isfinite(sigma) and sigma > 0) or min(room) > DISPUTE_SIGMAS * sigma:
        return ""
    return (
        f"{UNSETTLED}; its beam flank (peak {math.degrees(flank.bearing):.1f}° ± {math.degrees(sigma):.1f}°) agrees "
        f"with its plane's end at γ {math.degrees(bearing):.1f}° and as well with a wall of its own whose foot lies "
        f"past its cut end, {math.degrees(min(room)):.1f}° away: the evidence does not decide which"
    )


def _in_fan(measured: list[Measured], partial: set[int]) -> list[Measured]:
    """The regions every capsule hears: a target part of the stack hears lies off the fan, so it says
    nothing of how far a plane runs along its trace in the fan."""
    return [x for k, x in enumerate(measured) if k not in partial]


def _on_traces(i: int, pool: list[int], measured: list[Measured], partial: set[int], opts: SurfaceOptions) -> list[int]:
    """The regions of ``pool`` on whose plane's trace region ``i`` lies, off that plane's own foot, within its reach."""
    p = feature_point(measured[i])
    out = []
    for j in pool:
        if j == i:
            continue
        mj = measured[j]
        if abs(wrap(measured[i].bearing - mj.bearing)) < opts.foot_separation:
            continue
        nj = unit_normal(mj.bearing, mj.tilt)
        # n_j · p moves with either bearing by ρ·sin(β_i − β_j) per rad: 3 σ of both.
        mi = measured[i]
        sb = math.hypot(mj.bearing_stderr, mi.bearing_stderr)
        tol = opts.on_trace + 3 * mi.depth * abs(math.sin(mi.bearing - mj.bearing)) * sb
        if abs(float(nj @ p) - mj.depth) <= tol and not beyond_reach(
            mi, mi.bearing, mj, _in_fan(measured, partial), opts
        ):
            out.append(j)
    return out


def _others(i: int, pool: list[int]) -> list[int]:
    return [j for j in pool if j != i]


def _planes(
    measured: list[Measured], partial: set[int], across: list[bool], scale: EchoScale, opts: SurfaceOptions
) -> list[int]:
    """The regions that hold a plane's traces: a determined bearing, no diffraction's echo, and no end or corner
    of the others."""
    candidates = [i for i, m in enumerate(measured) if not across[i]]
    # Only planes whose bearing is determined, and whose echo is not a diffraction's, hold traces.
    # (A target only part of the stack hears is no mirror: every capsule hears a mirror's foot alike.)
    determined = [
        i
        for i in candidates
        if measured[i].bearing_source != "undetermined" and not scale.weak(measured[i]) and i not in partial
    ]
    # A region on another's trace, at two planes' double bounce, or at one plane's double bounce with a surface
    # across the stack is an end or a corner; once those are set aside, the ties are counted again against the
    # planes alone (a corner's own trace is no wall).
    ends = {
        i
        for i in determined
        if _on_traces(i, determined, measured, partial, opts)
        or pair_corner(measured[i], [measured[j] for j in _others(i, determined)], opts) is not None
        or stack_dihedral(measured[i], [measured[j] for j in _others(i, determined)], opts) is not None
    }
    return [i for i in determined if i not in ends]


def classify_regions(
    measured: list[Measured],
    partial: set[int],
    scale: EchoScale,
    gamma: np.ndarray,
    opts: SurfaceOptions,
    amplitude: np.ndarray | None = None,
    distance: np.ndarray | None = None,
) -> tuple[dict[int, Kind], set[int]]:
    """The kind of every region that is no plane, and which of them are lines across the fan.

    Each region's entry of ``measured`` takes the bearing, depth and tilt its classification places it at.
    With ``amplitude`` (the sweep's, ``(n_steps, n_capsules)``), a region whose depth alone places it on a trace
    is weighed by its beam flank (:func:`_end_by_flank`); with ``distance`` (the sweep's ranges), a flank past a
    cut by a much nearer echo weighs as one past the sweep's end.
    """
    across = [across_stack(m, opts) for m in measured]
    planes = _planes(measured, partial, across, scale, opts)
    walls_of_corners = walls_of_unseen_corners(measured, planes, across, partial, gamma, opts)
    flanks = _Flanks([measured[j] for j in planes], gamma, amplitude, scale, opts, distance)
    for i, text in walls_of_corners.items():
        m = measured[i]
        if m.bearing_source == "amplitude peak":
            # Its corner's echo answers beside it inside the amplitude window and sums into its flank: the peak
            # may sit anywhere the region allows its foot.
            m = replace(m, bearing_stderr=reach_stderr(m, opts))
        elif m.bearing_source == "undetermined":
            # A wall's mirror, its foot past a cut end: placed by its flank where nothing else answers inside
            # its amplitude window past that end (as a wall the end-or-wall test finds is).
            got = flanks.of(m)
            if got is not None and got[1]:
                m = got[0]
        measured[i] = replace(m, findings=(*m.findings, (DEGRADED, text)))
    kinds: dict[int, Kind] = {}
    across_lines: set[int] = set()
    for i in range(len(measured)):
        m, kind, across_line = _region_kind(
            i, measured, planes, across[i], partial, i in walls_of_corners, scale, gamma, opts, flanks
        )
        measured[i] = m
        if kind is not None:
            kinds[i] = kind
        if across_line:
            across_lines.add(i)
    return kinds, across_lines


def _region_kind(
    i: int,
    measured: list[Measured],
    planes: list[int],
    across: bool,
    partial: set[int],
    wall_of_corner: bool,
    scale: EchoScale,
    gamma: np.ndarray,
    opts: SurfaceOptions,
    flanks: _Flanks,
) -> tuple[Measured, Kind | None, bool]:
    """Region ``i`` placed as its kind says, its kind (None: a plane) and whether it is a line across the fan."""
    m = measured[i]
    pool = _others(i, planes)
    # The double bounce with a floor or a ceiling ties the region to its wall: tried before the curvature
    # alone, which says only that the line runs across the stack.
    near = [measured[j] for j in pool]
    low = stack_dihedral(m, near, opts)
    pair = pair_corner(m, near, opts)
    unsettled = ""
    if low is not None and pair is not None:
        # A plane's yaw slopes its corner with a plane in the fan as a line across the fan would.
        chosen, unsettled = stack_or_pair(m, near, low, pair)
        if chosen == "pair":
            low = None
    if low is not None:
        j, z, text = low
        pj = measured[pool[j]]
        # The line's point: the plane's foot, off the fan by z; its depth, the distance to it.
        foot = pj.depth * unit_normal(pj.bearing) + np.array([z, 0.0, 0.0])
        tilt = math.atan2(z, pj.depth)
        m = replace(
            m, bearing=pj.bearing, bearing_stderr=pj.bearing_stderr, depth=float(np.linalg.norm(foot)), tilt=tilt
        )
        # On the wall's trace across the fan: a concave corner with the floor or ceiling, or, if its echo
        # diffracts, the wall's free top or bottom edge.
        verdict, why = scale.end_strength(m, pj, confirmed=True)
        if verdict == "weak":
            return m, ("edge", [text.replace("double bounce", "line"), why], [pool[j]]), True
        return m, ("corner", [text, why] if verdict == "strong" else [text, UNSETTLED], [pool[j]]), True
    if across:
        m = across_stack_measured(m)
        text = (
            f"ranges curve along the capsule stack (c = {m.curvature:.2f}/m ≈ 1/(2ρ) = "
            f"{1 / (2 * m.depth):.2f}/m): a line across the stack, not a plane"
        )
        return m, ("edge" if scale.weak(m) else "corner", [text], []), True
    m, ties, undecided = _ties(i, m, pool, pair, measured, planes, partial, wall_of_corner, gamma, opts, flanks)
    m, kind = _kind_from_ties(m, ties, unsettled or undecided, measured, scale)
    return m, kind, False


def _ties(
    i: int,
    m: Measured,
    pool: list[int],
    pair: tuple[list[int], float] | None,
    measured: list[Measured],
    planes: list[int],
    partial: set[int],
    wall_of_corner: bool,
    gamma: np.ndarray,
    opts: SurfaceOptions,
    flanks: _Flanks,
) -> tuple[Measured, list[int], str]:
    """The planes region ``i`` ties to (two: their double bounce; one: its end), the region placed there and why
    its kind is not settled ("": it is)."""
    undecided = ""
    if pair is not None:
        which, bearing = pair
        ties = [pool[j] for j in which]
        # The two planes' line leans off the fan with their tilts: its echo comes from its point nearest the
        # array, off the fan by that lean, at the region's range.
        line = plane_line(measured[ties[0]], measured[ties[1]])
        lean = 0.0 if line is None else math.asin(max(-1.0, min(1.0, float(line[0][0] / np.linalg.norm(line[0])))))
        m = replace(m, bearing=bearing, bearing_stderr=pair_stderr(m, which, pool, measured), tilt=lean)
    elif m.bearing_source == "undetermined":
        placements = (
            []
            if wall_of_corner
            else list(plane_ends(m, [measured[j] for j in pool], opts, _in_fan(measured, partial), gamma))
        )
        placed = _end_by_flank(m, placements, pool, measured, flanks) if placements else None
        if placed is None or isinstance(placed, Measured):
            ties = []
            m = m if placed is None else placed
        else:
            (which, bearing), floor, undecided = placed
            ties = [pool[j] for j in which]
            m = replace(m, bearing=bearing, bearing_stderr=max(end_stderr(m, measured[ties[0]], bearing), floor))
    else:
        ties = [] if wall_of_corner else _on_traces(i, planes, measured, partial, opts)
    return m, ties, undecided


def _kind_from_ties(
    m: Measured, ties: list[int], unsettled: str, measured: list[Measured], scale: EchoScale
) -> tuple[Measured, Kind | None]:
    """A region's kind from the planes it ties to and its echo's strength (None: a plane)."""
    if len(ties) >= 2:
        return m, (
            "corner",
            ["at the double-bounce range of the two planes it joins (their intersection)"]
            + ([unsettled] if unsettled else []),
            ties[:2],
        )
    if len(ties) == 1:
        verdict, why = scale.end_strength(m, measured[ties[0]])
        if verdict == "weak":
            # A diffraction's weak echo is no wall's mirror: nothing else explains it.
            return m, ("edge", [f"on a plane's trace off its foot, {why}"], ties)
        if verdict == "strong":
            return m, ("corner", [f"on a plane's trace off its foot, {why}"] + ([unsettled] if unsettled else []), ties)
        return m, ("edge", [f"on a plane's trace off its foot (its end); {UNSETTLED}"], ties)
    if scale.weak(m):
        if m.bearing_source == "undetermined":
            m = replace(m, bearing_stderr=reach_stderr(m, scale.opts))
        return m, (
            "edge",
            [
                f"echo at most {100 * scale.upper_strength(m) / scale.mirror:.0f} % of the sweep's strongest at its "
                "range: diffraction"
            ],
            [],
        )
    return m, None
