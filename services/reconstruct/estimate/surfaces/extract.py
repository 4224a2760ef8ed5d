"""Every surface of one sweep: planes, concave corners and convex edges, each with its evidence.

Per region of constant depth (:mod:`.regions`):

* **bearing** from the beam pattern: the region's centre when it is not cut,
  weighed with the peak of the echo amplitudes across γ
  (:func:`~.beam_pattern.bearing_from_amplitude`) where the two agree, else that
  peak alone; a cut region without an amplitude peak leaves the bearing
  undetermined, and says so.  A range-only fit of a wall seen near the foot of
  its perpendicular is ill-posed in bearing (the capsules differ across the
  beam only by the radial offset), so the bearing never comes from it.
* **depth** ``ρ`` from the ranges with the bearing fixed (the mirror condition
  ``n · p_c + d = h``), **tilt** from the differential ranges along the capsule
  stack.
* **flanks**: a region whose end steps slope along the capsule stack as its
  middle does not, where the middle plane's double bounce with a surface across
  the fan explains them (a wall's foot on the floor below a horizontal fan),
  splits into the plane and those ends (:mod:`.flanks`).
* **class** by physics (:mod:`.classify`; the tests are in :mod:`.evidence`, the echo's strength against the sweep's own
  references in :mod:`.strength`):

  - one line in a plane, across the fan, explaining every range (the double
    bounce of a wall with the floor or ceiling): a **corner** of that wall, an
    **edge** (its free top or bottom) if its echo is weak;
  - ranges curved along the stack as ``1/(2ρ)``: a line or point *across* the
    stack (the image of the array is not a straight array), so not a plane;
  - at the range and bearing of two planes' intersection (the double bounce):
    a **concave corner**;
  - on one other plane's trace (off that plane's own foot, or deeper than it):
    that plane's end, a **corner** if its echo is as strong as that plane's own
    mirror echo, an **edge** if weak; where the region holds only a flank of
    its echo, the beam pattern taken back to the bearing the geometry puts it
    at weighs it, and an end whose strength no evidence settles says so
    (:data:`~.results.UNSETTLED`, ``Feature.settled``); a strong end placed there by its depth alone is a
    wall of its own where its own echo's flank, away from a cut another echo bends, peaks elsewhere;
  - an echo much weaker than the sweep's strongest at its range (diffraction):
    an **edge**; a region cut before its peak is weak only if the upper
    estimate of its peak (its flank, extrapolated with the sweep's own beam
    curvature) is;
  - anything else: a **plane**.

A plane's region that hands over at an amplitude jump, at one range, to its face's end's weak echo is placed by
one beam pattern across the jump (the end lies at the face's foot); one another echo cuts at a like range is placed
by its flank away from that cut, where its own echo is alone.

A target only part of the capsule stack hears, nearer than what the rest hear at its steps (an edge off the
fan), is found among the readings no region holds; it is a corner or an edge, never a plane.  A weak region
whose amplitude steps as no one beam pattern does holds two diffracting targets at one range: two edges.

Each plane is fitted on its own echoes, walls joined at concave corners with them (:mod:`.fitting`, :mod:`.joint`).
A corner or an edge lies where its echo comes from, off the fan by its stack slope's tilt; a concave corner
of two fitted planes on their line, with their covariance (:mod:`.features`, :mod:`.placement`).

The planes' verdicts go through :func:`~lelsonar.reconstruct.estimate.quality.assess_plane`
with the extractor's own findings (bearing undetermined or disputed, region cut).
Their covariance is over (bearing, tilt, offset): a wall well placed in range can
be poorly placed in bearing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.quality import DEGRADED, GOOD, UNRELIABLE
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import PLATEAU, amplitude_jump, log_amplitude_curvature
from lelsonar.reconstruct.estimate.surfaces.classify import DISPUTE_SIGMAS, classify_regions
from lelsonar.reconstruct.estimate.surfaces.confirm import confirm_surfaces
from lelsonar.reconstruct.estimate.surfaces.evidence import end_stderr, in_fan_range
from lelsonar.reconstruct.estimate.surfaces.features import Kind, place_features
from lelsonar.reconstruct.estimate.surfaces.fitting import METHOD, fit_surface, joint_fit, place_own_mirrors
from lelsonar.reconstruct.estimate.surfaces.flank_bearing import (
    FLANK_SOURCE,
    across_jump_bearing,
    end_refuted,
    flank_measured,
    flank_reach,
)
from lelsonar.reconstruct.estimate.surfaces.flanks import masked_regions, partial_regions, split_dihedral, split_ends
from lelsonar.reconstruct.estimate.surfaces.joint import JointWall
from lelsonar.reconstruct.estimate.surfaces.measurement import (
    Measured,
    clean_cuts,
    measure_region,
    summed_width_stderr,
    sweep_step,
    unit_normal,
)
from lelsonar.reconstruct.estimate.surfaces.off_fan import (
    off_fan_corner,
    off_fan_tilt,
    off_fan_weak,
    separate_targets,
    split_stack,
    taken_back,
)
from lelsonar.reconstruct.estimate.surfaces.piston_beam import SweepBeam, log_profile, sweep_beam
from lelsonar.reconstruct.estimate.surfaces.regions import Region, find_regions, subregion
from lelsonar.reconstruct.estimate.surfaces.results import (
    OFF_FAN,
    UNSETTLED,
    Feature,
    Surface,
    SurfaceOptions,
    SurfaceSet,
)
from lelsonar.reconstruct.estimate.surfaces.stack import capsule_x
from lelsonar.reconstruct.estimate.surfaces.strength import EchoScale, echo_scale

__all__ = ["SurfaceOptions", "Surface", "Feature", "SurfaceSet", "extract_surfaces", "METHOD", "UNSETTLED"]


@dataclass(frozen=True, eq=False)
class _Sweep:
    """One sweep's validated readings and what every stage reads of them."""

    gamma: np.ndarray
    distance: np.ndarray
    amplitude: np.ndarray | None
    geometry: ArrayGeometry
    opts: SurfaceOptions
    #: rad: the sweep's step (:func:`~.measurement.sweep_step`).
    step: float
    #: m: how far one target's ranges differ between two capsules at most, their distance apart.
    spread: float


def extract_surfaces(
    gamma: np.ndarray,
    distance: np.ndarray,
    geometry: ArrayGeometry,
    *,
    amplitude: np.ndarray | None = None,
    options: SurfaceOptions | None = None,
) -> SurfaceSet:
    """Every plane, concave corner and convex edge of one sweep, in the array frame.

    Parameters
    ----------
    gamma : (n_steps,) array
        Measured rotation of each step, rad, in sweep order.
    distance : (n_steps, n_capsules) array
        Ranges, m (NaN: no echo).
    geometry : ArrayGeometry
    amplitude : (n_steps, n_capsules) array, optional
        Each echo's peak amplitude, V (:func:`lelsonar.signal.energy.echo_amplitude`); without it the
        bearing comes from the regions' centres and the weak-echo test is not made.
    options : SurfaceOptions, optional

    Returns
    -------
    SurfaceSet
    """
    opts = options or SurfaceOptions()
    sweep = _sweep(gamma, distance, amplitude, geometry, opts)
    measured, partial = _measured_regions(sweep)
    regions = [m.region for m in measured]  # what they hold: the rest of the readings is unexplained
    scale = echo_scale(measured, sweep.gamma, opts)
    _split_two_edges(measured, partial, scale, sweep)
    own = list(measured)  # each region as its own echoes measured it, before its kind places it
    kinds, across_lines = classify_regions(
        measured, partial, scale, sweep.gamma, sweep.opts, sweep.amplitude, sweep.distance
    )
    _widen_summed_bearings(measured, kinds, scale)
    _walls_not_ends(measured, own, kinds, across_lines, partial, scale, sweep)
    _unsettle_off_fan(kinds, partial, across_lines, measured, scale, sweep)
    joint = _joint_corners(measured, kinds, across_lines, opts)
    place_own_mirrors(measured, set(kinds) | partial, opts.beyond_cut)
    _flank_bearings(measured, kinds, partial, scale, sweep)
    surfaces, surface_of, failed, unsorted = _fit_planes(measured, kinds, partial, joint, sweep)
    corners, edges = place_features(measured, own, kinds, across_lines, surface_of, joint, scale, sweep.distance)
    return SurfaceSet(
        surfaces=tuple(confirm_surfaces(surfaces, _confirmed(measured, kinds, across_lines, surface_of))),
        corners=tuple(corners),
        edges=tuple(edges),
        n_echoes=int(np.count_nonzero(np.isfinite(sweep.distance))),
        unexplained=_unexplained(sweep, regions, failed, unsorted),
    )


def _sweep(
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
) -> _Sweep:
    """The readings as float arrays, their shapes checked against the array's capsules."""
    g = np.asarray(gamma, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    if d.shape != (g.size, geometry.n_capsules):
        raise ConfigError(f"distance must have shape ({g.size}, {geometry.n_capsules}), got {d.shape}")
    amp = None if amplitude is None else np.asarray(amplitude, dtype=np.float64)
    if amp is not None and amp.shape != d.shape:
        raise ConfigError(f"amplitude must have the shape of distance {d.shape}, got {amp.shape}")
    # One target's ranges differ between two capsules by no more than their distance apart.
    x = capsule_x(geometry)
    spread = float(x.max() - x.min()) + opts.range_tolerance
    return _Sweep(g, d, amp, geometry, opts, step=sweep_step(g), spread=spread)


def _measured_regions(sweep: _Sweep) -> tuple[list[Measured], set[int]]:
    """The sweep's regions of constant depth, measured and split where they hold more than one target, and the
    indices of those heard by part of the capsule stack only."""
    g, d, amp, geometry, opts, step = (
        sweep.gamma,
        sweep.distance,
        sweep.amplitude,
        sweep.geometry,
        sweep.opts,
        sweep.step,
    )
    regions = find_regions(
        d,
        tolerance=opts.range_tolerance,
        max_gap=opts.max_gap,
        min_steps=opts.min_steps,
        max_spread=sweep.spread,
        gamma=g,
        radial_offset=geometry.radial_offset,
    )
    measured = [measure_region(r, g, d, amp, geometry, opts, step=step) for r in regions]
    # A region whose ends hold another target along the stack (its plane's double bounce with a surface across
    # the fan, a line across the stack at a like range): its plane's middle and those ends.
    measured = [piece for m in measured for piece in split_ends(m, g, d, amp, geometry, opts)]
    # A plane's region that runs on into its corner with a nearer plane: split where the steps tell them apart.
    split: list[Measured] = []
    for i in range(len(measured)):
        split.extend(split_dihedral(i, measured, g, d, amp, geometry, opts) or [measured[i]])
    # Targets part of the stack hears inside a region: two at ranges apart (a run split by range), or two at one
    # range on either side of the stack (their profile along it bends as no one target's does).
    measured, partial = separate_targets(split, g, d, amp, geometry, opts, step)
    # A target heard by part of the stack only, nearer than what its steps' other capsules hear (an edge off
    # the fan beside the stack: its weak echo crosses the receiver's threshold in the capsules nearest it):
    # its readings are off their step's range, so a second pass over the readings no region holds finds it.
    held = [m.region for m in measured]
    for r in partial_regions(d, held, opts, sweep.spread, gamma=g, radial_offset=geometry.radial_offset):
        pm = measure_region(r, g, d, amp, geometry, opts, step=step)
        # Heard on the beam's flank: its slope is that at the middle of the capsules heard, not the stack's.
        tilt, tilt_se = off_fan_tilt(pm, opts)
        for piece in split_stack(pm, g, d, amp, geometry, opts, step) or [replace(pm, tilt=tilt, tilt_stderr=tilt_se)]:
            partial.add(len(measured))
            measured.append(piece)
    # A target part of the stack hears past a nearer one the other capsules hear first: a region of the fan.
    for r in masked_regions(d, [m.region for m in measured], opts, sweep.spread):
        measured.append(measure_region(r, g, d, amp, geometry, opts, step=step))
    return measured, partial


def _split_two_edges(measured: list[Measured], partial: set[int], scale: EchoScale, sweep: _Sweep) -> None:
    """Two diffracting targets at one range side by side (a thin wall's two ends, a box's two edges) make one
    region whose amplitude steps where one beam pattern hands over to the other: two edges, not one.  The first
    replaces the region in ``measured``, the second is appended."""
    g, opts = sweep.gamma, sweep.opts
    for i in range(len(measured)):
        m = measured[i]
        # (Part of the stack hears a target off the fan on fewer steps in its farther capsules: its steps'
        # medians step where those capsules join, which is no second target.)
        if i in partial or not scale.weak(m) or m.region.cut_before or m.region.cut_after:
            continue
        jump = amplitude_jump(g[m.region.steps], m.step_amplitude)
        if jump is None:
            continue
        k = int(np.searchsorted(g[m.region.steps], jump[0])) if g[-1] > g[0] else 0
        if not opts.min_steps <= k <= m.region.steps.size - opts.min_steps:
            continue
        pieces = [
            subregion(m.region, m.region.steps[:k], cut_before=False, cut_after=True),
            subregion(m.region, m.region.steps[k:], cut_before=True, cut_after=False),
        ]
        first, second = (
            measure_region(r, g, sweep.distance, sweep.amplitude, sweep.geometry, opts, step=sweep.step) for r in pieces
        )
        measured[i] = first
        measured.append(second)


def _widen_summed_bearings(measured: list[Measured], kinds: dict[int, Kind], scale: EchoScale) -> None:
    """A plane's bearing from its amplitude peak alone: another echo summing into its flank moves the peak as
    much as it widens the top (:func:`summed_width_stderr`), which the parabola's residuals do not show."""
    g = scale.gamma
    for i, m in enumerate(measured):
        if i in kinds or m.bearing_source != "amplitude peak" or m.peak >= (1.0 - PLATEAU) * scale.full_scale:
            continue  # (a clipped top: its plateau's centre, whose width is no beam's)
        c = log_amplitude_curvature(g[m.region.steps], m.step_amplitude, plateau=True)
        extra = summed_width_stderr(c, scale.beam_k, scale.beam_low)
        if extra > 0:
            measured[i] = replace(m, bearing_stderr=math.hypot(m.bearing_stderr, extra))


def _walls_not_ends(
    measured: list[Measured],
    own: list[Measured],
    kinds: dict[int, Kind],
    across_lines: set[int],
    partial: set[int],
    scale: EchoScale,
    sweep: _Sweep,
) -> None:
    """A region whose own bearing is undetermined and which only its depth puts on one plane's trace, as that
    plane's end with an echo as strong as a mirror's (a concave corner), is as well a wall of its own whose foot
    lies where its flank peaks: the corner takes the region only if its echo does not refute it.

    Were it the end, its flank would peak at the end's bearing (:func:`~.flank_bearing.end_refuted`).  Another
    echo at a like range past a cut end sums into the amplitude window where the two meet and bends the flank
    there, so the steps a run may bridge at such an end are left out of both fits; what remains is the region's
    own echo alone, and it must span the beam's ``1/√k`` to show the bend that places a peak.  Where it peaks
    more than :data:`~.classify.DISPUTE_SIGMAS` σ of their difference from the end (and the mirror's flank fits
    within its noise), the region is a wall of its own, placed by its flank (usable, never good: the beam's shape
    carries its bearing).
    """
    amp = sweep.amplitude
    if amp is None or not scale.beam_k > 0:
        return
    todo = [
        i
        for i, (kind, _reasons, ties) in kinds.items()
        if kind == "corner"
        and len(ties) == 1
        and i not in across_lines
        and i not in partial
        and own[i].bearing_source == "undetermined"
        and (own[i].region.cut_before or own[i].region.cut_after)
        and _in_fan(own[i])
    ]
    if not todo:
        return
    planes = [m for i, m in enumerate(measured) if i not in kinds and i not in partial]
    beam = sweep_beam(planes, sweep.gamma, amp, 2.0 * math.sqrt(scale.beam_k))
    if beam is None:
        return
    opts = sweep.opts
    for i in todo:
        ties = kinds[i][2]
        alone = _own_flank(own[i], sweep, scale)
        if alone is None:
            continue
        mine, reach = alone
        placed = measured[i]
        end_se = end_stderr(own[i], measured[ties[0]], placed.bearing)
        got = end_refuted(mine, sweep.gamma, beam, placed.bearing, end_se, in_fan_range(own[i])[0], reach)
        if got is None or got[0] <= DISPUTE_SIGMAS:
            continue
        wall = flank_measured(mine, sweep.gamma, amp, beam, opts.beyond_cut, reach=reach)
        if wall.bearing_source != FLANK_SOURCE:
            continue
        plane = measured[ties[0]]
        why = (
            f"on the trace of the plane at {plane.depth:.2f} m as its end at γ {math.degrees(placed.bearing):.1f}°, "
            f"but its own echo's beam flank peaks at {math.degrees(got[1]):.1f}° ± {math.degrees(got[2]):.1f}°, "
            f"{got[0]:.1f} σ from where that end's echo would: a wall of its own"
        )
        measured[i] = replace(wall, findings=(*wall.findings, (DEGRADED, why)))
        del kinds[i]


def _in_fan(m: Measured) -> bool:
    """Its ranges along the capsule stack place its target in the fan (no slope past 3 σ): one off the fan meets
    the beam at ``ψ² ≈ (γ − β)² + t²``, so its flank across γ is no in-fan piston's about its bearing."""
    return math.isfinite(m.tilt_stderr) and abs(m.tilt) <= 3.0 * m.tilt_stderr


def _own_flank(m: Measured, sweep: _Sweep, scale: EchoScale) -> tuple[Measured, tuple[float, float]] | None:
    """The region without the steps a run may bridge at each cut end where another echo answers at a like range
    (:func:`~.measurement.clean_cuts`): there that echo sums into its amplitude window (``m`` itself where nothing
    is left out); and how far past each cut end its peak may lie.  None when too little remains for a flank."""
    opts = sweep.opts
    r = m.region
    clean = clean_cuts(r, sweep.distance, opts)
    trim = opts.max_gap + 2
    first = trim if r.cut_before and not clean[0] else 0
    last = r.steps.size - (trim if r.cut_after and not clean[1] else 0)
    if last - first < 2 * opts.min_steps:
        return None
    piece = m
    if (first, last) != (0, r.steps.size):
        sub = subregion(r, r.steps[first:last], r.cut_before, r.cut_after)
        piece = measure_region(sub, sweep.gamma, sweep.distance, sweep.amplitude, sweep.geometry, opts, step=sweep.step)
    # A flank shorter than the beam's 1/√k is nearly straight in log A: its bend, which places its peak, is
    # less than one e-fold, within what an echo's own change with the angle (a corner's aperture) bends it.
    if piece.span[1] - piece.span[0] < 1.0 / math.sqrt(scale.beam_k):
        return None
    reach = (opts.beyond_cut if piece.region.cut_before else 0.0, opts.beyond_cut if piece.region.cut_after else 0.0)
    return piece, reach


def _unsettle_off_fan(
    kinds: dict[int, Kind],
    partial: set[int],
    across_lines: set[int],
    measured: list[Measured],
    scale: EchoScale,
    sweep: _Sweep,
) -> None:
    """A target part of the stack hears lies off the fan on the beam's flank: its echo's strength is only a lower
    bound of its peak, so where strength set its kind (not two planes' intersection), its kind is not settled,
    unless its echo, taken back from as far off the fan as its ranges' slope along the stack allows, is still a
    diffraction's (an edge).  So too a point or a line across the stack that every capsule hears and no plane ties
    (a concave corner of three planes above or below the fan is heard on the beam's flank)."""
    for i in partial:
        if i in kinds and len(kinds[i][2]) < 2 and i not in across_lines:
            kind, reasons, ties = kinds[i]
            amp, opts = sweep.amplitude, sweep.opts
            back = None if amp is None else taken_back(measured[i], amp, scale.beam_k, opts)
            weak = "" if back is None else off_fan_weak(scale.upper_strength(back[0]), scale.mirror, back[1], opts)
            kinds[i] = ("edge", [*reasons, weak], ties) if weak else (kind, [*reasons, f"{UNSETTLED}; {OFF_FAN}"], ties)
    for i in across_lines - partial:
        if i in kinds and kinds[i][0] == "edge" and not kinds[i][2]:
            m = measured[i]
            if off := off_fan_corner(m, scale.upper_strength(m), scale.mirror, scale.beam_k, sweep.opts):
                kind, reasons, ties = kinds[i]
                kinds[i] = (kind, [*reasons, f"{UNSETTLED}; {off}"], ties)


def _joint_corners(
    measured: list[Measured], kinds: dict[int, Kind], across_lines: set[int], opts: SurfaceOptions
) -> dict[int, JointWall]:
    """The joint corner model: walls that meet at a concave corner (two ties, in the fan) fitted with it.  A wall
    the corners dispute takes that finding."""
    pairs = [(i, ties) for i, (kind, _r, ties) in kinds.items() if kind == "corner" and len(ties) >= 2]
    pairs = [(i, ties) for i, ties in pairs if i not in across_lines]
    joint, disputed = joint_fit(pairs, measured, opts) if opts.joint_corners else ({}, {})
    for j, text in disputed.items():
        measured[j] = replace(measured[j], findings=(*measured[j].findings, (DEGRADED, text)))
    return joint


def _flank_bearings(
    measured: list[Measured], kinds: dict[int, Kind], partial: set[int], scale: EchoScale, sweep: _Sweep
) -> None:
    """The planes whose bearing neither centre nor peak determines, placed by their beam pattern's flank with
    the sweep's own piston (:mod:`.flank_bearing`); classification is done, so nothing ties to them anew."""
    if sweep.amplitude is None or not scale.beam_k > 0:
        return
    n_steps, n_capsules = sweep.amplitude.shape
    todo = [
        i
        for i, m in enumerate(measured)
        if i not in kinds
        and i not in partial
        and flank_reach(m, n_steps, n_capsules, sweep.opts.beyond_cut) != (0.0, 0.0)
    ]
    # A plane's region that hands over at an amplitude jump to its face's end at one range.
    ends = {
        i: j
        for i, m in enumerate(measured)
        if i not in kinds and i not in partial and i not in todo and m.bearing_source == "undetermined"
        for j in [_end_across_jump(i, measured, scale, sweep)]
        if j is not None
    }
    # A plane's region cut by another echo at a like range, whose steps away from that cut are its own echo alone.
    bent = [
        i
        for i, m in enumerate(measured)
        if i not in kinds
        and i not in partial
        and i not in todo
        and i not in ends
        and m.bearing_source == "undetermined"
        and (m.region.cut_before or m.region.cut_after)
        and _in_fan(m)
    ]
    if not todo and not ends and not bent:
        return
    # A mirror's echo follows the beam alone (its range and spreading constant across its region); a corner's double
    # bounce or an edge's diffraction adds its own change with the angle: only the planes calibrate the beam.
    planes = [m for i, m in enumerate(measured) if i not in kinds and i not in partial]
    beam = sweep_beam(planes, sweep.gamma, sweep.amplitude, 2.0 * math.sqrt(scale.beam_k))
    for i in todo:
        measured[i] = flank_measured(measured[i], sweep.gamma, sweep.amplitude, beam, sweep.opts.beyond_cut)
    if beam is not None:
        for i, j in ends.items():
            measured[i] = _across_jump(measured[i], measured[j], beam, sweep)
    for i in bent:
        alone = _own_flank(measured[i], sweep, scale)
        if alone is None or alone[0] is measured[i]:
            continue
        mine, reach = alone
        wall = flank_measured(mine, sweep.gamma, sweep.amplitude, beam, sweep.opts.beyond_cut, reach=reach)
        if wall.bearing_source == FLANK_SOURCE:
            measured[i] = wall


def _end_across_jump(i: int, measured: list[Measured], scale: EchoScale, sweep: _Sweep) -> int | None:
    """The region a plane's region hands over to at an amplitude jump (the next step on, at one range within
    twice the range tolerance) when that echo is weak: its face's end diffracting."""
    m = measured[i]
    first, last = int(m.region.steps[0]), int(m.region.steps[-1])
    for j, k in enumerate(measured):
        if j == i or abs(k.depth - m.depth) > 2.0 * sweep.opts.range_tolerance or not scale.weak(k):
            continue
        after = m.handed_over[1] and k.handed_over[0] and int(k.region.steps[0]) == last + 1
        before = m.handed_over[0] and k.handed_over[1] and int(k.region.steps[-1]) == first - 1
        if after or before:
            return j
    return None


def _across_jump(m: Measured, end: Measured, beam: SweepBeam, sweep: _Sweep) -> Measured:
    """A plane's region placed by one piston across the amplitude jump to its face's end
    (:func:`~.flank_bearing.across_jump_bearing`), or as it is when that fit gives nothing.

    An end on the plane at range ``ρ`` lies ``δ = acos(h/ρ)`` off its foot; with the two depths equal within
    their σ, ``ρ − h`` is at most their difference plus twice its σ, and the end anywhere up to that far off the
    foot on either side: uniform, its σ ``δ/√3`` is part of the bearing's."""
    g = sweep.gamma
    profiles = [log_profile(g[x.region.steps], x.step_amplitude) for x in (m, end)]
    lo = min(m.span[0], end.span[0])
    hi = max(m.span[1], end.span[1])
    fit = across_jump_bearing(profiles, beam, lo, hi)
    if fit is None:
        return m
    gap = abs(end.depth - m.depth) + 2.0 * math.hypot(m.depth_stderr, end.depth_stderr)
    off = math.acos(min(1.0, m.depth / (m.depth + gap))) if m.depth > 0 else math.pi
    bearing, sb = fit[0], math.hypot(fit[1], off / math.sqrt(3.0))
    h_i = m.ranges + m.positions @ unit_normal(bearing, m.tilt)
    findings = tuple(f for f in m.findings if not (f[0] == UNRELIABLE and f[1].startswith("bearing not determined")))
    why = (
        f"bearing from one beam pattern across the amplitude jump to its face's end at one range "
        f"({math.degrees(bearing):.1f}° ± {math.degrees(sb):.1f}°): the end's weak echo and the face's flank peak "
        "at one bearing, the end at its foot within the depths' σ"
    )
    return replace(
        m,
        bearing=bearing,
        bearing_stderr=sb,
        bearing_source=FLANK_SOURCE,
        depth=float(np.median(h_i)),
        findings=(*findings, (DEGRADED, why)),
    )


def _fit_planes(
    measured: list[Measured], kinds: dict[int, Kind], partial: set[int], joint: dict[int, JointWall], sweep: _Sweep
) -> tuple[list[Surface], dict[int, Surface], int, int]:
    """Every plane fitted on its own echoes; the fitted surface of each region; the echoes of regions no plane
    fits; the echoes of regions part of the stack hears that are neither corner nor edge."""
    surfaces: list[Surface] = []
    surface_of: dict[int, Surface] = {}
    failed = 0
    unsorted = 0
    for i, m in enumerate(measured):
        if i in kinds:
            continue
        if i in partial:
            unsorted += m.region.n_echoes
            continue
        s = fit_surface(
            f"s{len(surfaces) + 1}", m, sweep.gamma, sweep.distance, sweep.geometry, sweep.opts, joint.get(i)
        )
        if s is None:
            failed += m.region.n_echoes
            continue
        surface_of[i] = s
        surfaces.append(s)
    return surfaces, surface_of, failed, unsorted


def _confirmed(
    measured: list[Measured], kinds: dict[int, Kind], across_lines: set[int], surface_of: dict[int, Surface]
) -> set[str]:
    """Labels of the planes a feature ties by a test: all but an end placed on one plane's trace because its own
    bearing is undetermined (:func:`~.confirm.confirm_surfaces`)."""
    out: set[str] = set()
    for i, (_kind, _reasons, ties) in kinds.items():
        placed = len(ties) == 1 and i not in across_lines and measured[i].bearing_source == "undetermined"
        if not placed:
            out.update(surface_of[j].label for j in ties if j in surface_of)
    return out


def _unexplained(sweep: _Sweep, regions: list[Region], failed: int, unsorted: int) -> dict[str, int]:
    """The readings no surface explains, counted by why."""
    valid = np.isfinite(sweep.distance)
    in_region = np.zeros_like(valid)
    in_run = np.zeros(sweep.gamma.size, dtype=bool)
    for r in regions:
        in_region[r.rows, r.capsules] = True
        in_run[r.steps] = True
    off_step = int(np.count_nonzero(valid & ~in_region & in_run[:, None]))
    short = int(np.count_nonzero(valid & ~in_run[:, None]))
    unexplained = {
        "in runs shorter than a region of constant depth": short,
        "off their step's range (another target in the same beam)": off_step,
    }
    if failed:
        unexplained["in regions no plane fits"] = failed
    if unsorted:
        unexplained["heard by part of the capsule stack only, neither corner nor edge"] = unsorted
    return unexplained


def good_surfaces(result: SurfaceSet) -> tuple[Surface, ...]:
    """The surfaces whose verdict is good."""
    return tuple(s for s in result.surfaces if s.quality == GOOD)
