"""A region of constant depth whose end steps hold another target at a like range, told apart.

* :func:`split_flanks`: both ends the middle's double bounce with a surface across the fan explains;
* :func:`trim_ends`: ends whose slope along the stack, or depth, is not the middle's plane's;
* :func:`split_ends`: the two for one region, in that order;
* :func:`split_dihedral`: an end block that is the double bounce of the plane with a nearer plane;
* :func:`partial_regions`: a target part of the stack hears, among the readings no region holds;
* :func:`masked_regions`: a target part of the stack hears past a nearer one the rest hear first.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.robust import median
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import bearing_from_amplitude, unfaded_ends
from lelsonar.reconstruct.estimate.surfaces.evidence import plane_line, stack_dihedral, wrap
from lelsonar.reconstruct.estimate.surfaces.jump_split import split_jump
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, centre_with_peak, measure_region, unit_normal
from lelsonar.reconstruct.estimate.surfaces.regions import Region, find_regions, subregion
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.slopes import step_slopes
from lelsonar.reconstruct.estimate.surfaces.symmetry import flank_asymmetry

__all__ = [
    "masked_regions",
    "partial_regions",
    "split_dihedral",
    "split_ends",
    "split_flanks",
    "trim_ends",
    "trimmed_centre",
]


def _flank(z: np.ndarray, min_steps: int, sigmas: float) -> int:
    """The run of steps at the start whose slopes stand off the rest together: its length, 0 for none.

    ``z``: each step's deviation from the region's slope in its own σ (NaN: none).  The run is the one of
    largest ``t = Σ z / √n`` (``n`` its steps with a slope), which must exceed ``sigmas``, with at least
    ``min_steps`` slopes in it and twice that left after it.
    """
    finite = np.isfinite(z)
    zs = np.cumsum(np.where(finite, z, 0.0))
    counts = np.cumsum(finite)
    # The runs that end at a step with a slope, at least min_steps of them, up to the first that leaves fewer
    # than twice that after it.
    ends = finite & (counts >= min_steps)
    short = np.flatnonzero(ends & (counts[-1] - counts < 2 * min_steps))
    if short.size:
        ends[short[0] :] = False
    at = np.flatnonzero(ends)
    if not at.size:
        return 0
    t = np.abs(zs[at]) / np.sqrt(counts[at].astype(np.float64))
    k = int(np.argmax(t))  # the first of the largest
    return int(at[k]) + 1 if t[k] > 0.0 and t[k] > sigmas else 0


def split_flanks(
    m: Measured,
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
) -> list[Measured] | None:
    """A plane's region whose end steps slope along the stack as its middle's do not: another target there.

    Where a wall meets the floor below a horizontal fan, the corner's double bounce lies behind the wall by
    ``z²/(2h)`` only (``z`` the array's height, ``h`` the wall's depth): within the range tolerance, and at
    the wall's own bearing.  Where the beam turns off the wall, the corner (brighter: two reflections of a
    retro-reflector against one mirror) stays over the receiver's threshold a few steps longer than the wall,
    so the region's ends are the corner's.  The capsule stack tells them apart: the wall's ranges take its one
    slope at every step, the corner's the slope of the capsules' distances to a line off the stack's middle.
    Each end's run of steps whose slopes stand off the region's median slope together by more than
    ``curvature_sigmas`` of their σ (:func:`step_slopes`, ``Σz/√n``), ``min_steps`` long, splits off, cut on
    the middle's side, where the middle's own double bounce with a surface across the fan explains its
    ranges (:func:`~.evidence.stack_dihedral`); else it stays the plane's.  With both flanks split, the
    middle keeps the whole region's bearing when that came from its centre: the flanks' target shares it (a
    line's nearest point lies at the wall's foot), so the span stays symmetric about the foot.  With one, the
    other side's flank is not in the region (its echoes made a region of their own), so the whole span is
    lopsided by the split flank's width and the middle's own centre (where the wall's nearer echo gives way
    on both sides) is the bearing.

    Returns
    -------
    The region's replacement (the flanks and the middle, in sweep order), or None.
    """
    r = m.region
    if r.steps.size < 3 * opts.min_steps:
        return None
    slopes, sigmas, _ = step_slopes(m)
    ok = np.isfinite(slopes) & np.isfinite(sigmas) & (sigmas > 0)
    if np.count_nonzero(ok) < 3 * opts.min_steps:
        return None
    ref = median(slopes[ok])
    z = np.where(ok, (slopes - ref) / np.where(ok, sigmas, 1.0), np.nan)
    head = _flank(z, opts.min_steps, opts.curvature_sigmas)
    tail = _flank(z[::-1], opts.min_steps, opts.curvature_sigmas)
    if not (head or tail) or np.count_nonzero(ok[head : r.steps.size - tail]) < opts.min_steps:
        return None

    def middle_of(head: int, tail: int) -> Measured:
        middle = subregion(r, r.steps[head : r.steps.size - tail], r.cut_before, r.cut_after)
        centre = measure_region(middle, gamma, distance, amplitude, geometry, opts, step=m.step)
        if m.bearing_source != "region centre" or not (head and tail):
            return centre
        h_i = centre.ranges + centre.positions @ unit_normal(m.bearing, centre.tilt)
        return replace(
            centre,
            bearing=m.bearing,
            bearing_stderr=m.bearing_stderr,
            summed_spread=m.summed_spread,
            bearing_source=m.bearing_source,
            findings=m.findings,
            depth=median(h_i),
        )

    centre = middle_of(head, tail)
    # A flank stays split only where the middle's own double bounce with a surface across the fan explains it.
    first = last = None
    if head:
        first = measure_region(
            subregion(r, r.steps[:head], r.cut_before, True), gamma, distance, amplitude, geometry, opts, step=m.step
        )
        if stack_dihedral(first, [centre], opts) is None:
            first, head = None, 0
    if tail:
        last = measure_region(
            subregion(r, r.steps[r.steps.size - tail :], True, r.cut_after),
            gamma,
            distance,
            amplitude,
            geometry,
            opts,
            step=m.step,
        )
        if stack_dihedral(last, [centre], opts) is None:
            last, tail = None, 0
    if first is None and last is None:
        return None
    if first is None or last is None:
        centre = middle_of(head, tail)
    return [x for x in (first, centre, last) if x is not None]


def trim_ends(
    m: Measured,
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
) -> list[Measured] | None:
    """A plane's whole region whose end steps hold another target's echo at a like range: its core and ends.

    A plane's ranges along the stack share one slope (``−n_x``) at every step.  A line across the stack
    at a like range (the plane's own corner with a floor or a ceiling off the fan, whose double bounce
    answers wider than the plane's mirror echo, just deeper) spreads the four ranges by
    ``(x − z)/ρ`` instead: at the region's ends, where the plane's echo has faded, its steps join the
    region within the range tolerance and move the region's centre off the plane's foot.  The steps at
    either end whose own slope differs from the plane's (the median over the region's middle half) by more than
    ``curvature_sigmas`` of its standard error ``σ/√Σ(x − x̄)²`` (``σ`` one range's, from the spread of
    the steps' slopes, 1.4826 MAD) are not the plane's, nor are those whose mean depth along the plane's
    normal lies deeper than the middle half's by more than that many σ of a step's mean (with
    or without readings enough for a slope).  As they lie deeper
    than the plane, its echo ended there on its
    own (the plane keeps its ends uncut); a nearer block would have masked it (a cut).

    Returns
    -------
    The plane's core and each end block of at least ``min_steps`` steps (cut on the core's side), in
    sweep order; None when no end step departs, or the core would keep fewer than half the region's steps.
    """
    r = m.region
    sigma = m.stack_sigma
    if r.cut_before or r.cut_after or not (math.isfinite(sigma) and sigma > 0):
        return None
    slopes, _, sxx = step_slopes(m, min_readings=3)
    finite = np.isfinite(slopes)
    if np.count_nonzero(finite) < 2 * opts.min_steps:
        return None
    # The plane's slope and the range σ from the steps of the region's middle half, where its own echo is
    # strongest (robust, 1.4826 MAD): another target's steps sit at the ends and must not set them.
    k = r.steps.size
    middle = np.zeros(k, dtype=bool)
    middle[k // 4 : k - k // 4] = True
    middle &= finite
    if np.count_nonzero(middle) < opts.min_steps:
        return None
    core = median(slopes[middle])
    robust = 1.4826 * median(np.abs((slopes[middle] - core) * np.sqrt(sxx[middle])))
    sigma = robust if robust > 0 else sigma
    with np.errstate(divide="ignore", invalid="ignore"):
        off = finite & (np.abs(slopes - core) > opts.curvature_sigmas * sigma / np.sqrt(sxx))
    # The line lies deeper than the plane's foot (|X| ≥ h): a step whose mean depth along the plane's normal
    # sits deeper than the middle half's by more than its own noise is not the plane's, whatever its slope.
    pos = np.searchsorted(r.steps, r.rows)
    own = m.ranges + m.positions @ unit_normal(m.bearing, m.tilt)
    count = np.bincount(pos, minlength=k)
    depth = np.bincount(pos, weights=own, minlength=k) / np.maximum(count, 1)
    level = median(depth[middle])
    spread = 1.4826 * median(np.abs(depth[middle] - level) * np.sqrt(count[middle]))
    # Depth needs no slope: an end step with too few readings for one (a corner's echo in one or two capsules
    # at the beam's edge) is judged by its depth alone.
    judged = finite.copy()
    if spread > 0:
        deep = (count > 0) & (depth - level > opts.curvature_sigmas * spread / np.sqrt(np.maximum(count, 1)))
        off |= deep
        judged |= deep

    def block(order: np.ndarray) -> int:
        """How many steps from that end up to the last departing one before the first that agrees (a step
        with too few readings to be judged goes with its neighbours)."""
        n_off = 0
        for j, s in enumerate(order):
            if judged[s] and not off[s]:
                break
            if judged[s]:
                n_off = j + 1
        return n_off

    head = block(np.arange(k))
    tail = block(np.arange(k - 1, head - 1, -1))
    if head + tail == 0 or 2 * (k - head - tail) < k or k - head - tail < opts.min_steps:
        return None
    core_sel = (pos >= head) & (pos < k - tail)
    level = median(own[core_sel])
    noise = 3 * sigma

    def nearer(sel: np.ndarray) -> bool:
        return bool(np.any(sel)) and median(own[sel]) < level - noise

    cut_before = r.cut_before or (head > 0 and nearer(pos < head))
    cut_after = r.cut_after or (tail > 0 and nearer(pos >= k - tail))
    parts = [subregion(r, r.steps[head : k - tail], cut_before, cut_after)]
    if head >= opts.min_steps:
        parts.insert(0, subregion(r, r.steps[:head], r.cut_before, True))
    if tail >= opts.min_steps:
        parts.append(subregion(r, r.steps[k - tail :], True, r.cut_after))
    out = [measure_region(p, gamma, distance, amplitude, geometry, opts) for p in parts]
    at = 1 if head >= opts.min_steps else 0
    nearest = (int(r.steps[head - 1]) if head else None, int(r.steps[k - tail]) if tail else None)
    out[at] = trimmed_centre(out[at], gamma, nearest)
    return out


def trimmed_centre(core: Measured, gamma: np.ndarray, nearest: tuple[int | None, int | None]) -> Measured:
    """The centre bearing of a plane's core whose end steps were trimmed off as another target's.

    A centred region's ends are where the beam pattern fades its echo, each within the gap to the next step
    out (variance ``gap²/12`` each, ``(gap_a² + gap_b²)/48`` for their mean).  The trimmed step next to the
    core held a like-range echo (the plane's corner with a surface across the fan, a few mm deeper) whose
    slope or depth is not the plane's: where the plane's fading echo sums into it, it moves that step's ranges
    and slope, so the plane's own echo may have faded there or one gap past it.  Farther out the other
    target's echo stands alone.  Uniform over that span (``w``, from the core's end to that step, plus the
    gap past it), the end is the middle of the core's end and that step, with variance ``(w + gap)²/12``.
    Only the bearing of a core centred on its own span changes (and its depth, along the new normal); that centre
    is weighed with the core's own amplitude peak where the two agree (:func:`~.measurement.centre_with_peak`),
    and the surface's σ holds the capsules' own peaks' spread through the peak's share and how far the core's
    flanks are from mirror images about that bearing (:func:`~.symmetry.flank_asymmetry`), as a whole region's.

    Parameters
    ----------
    core : Measured
        The trimmed region's core.
    gamma : (n_steps,) array
        The sweep's γ, rad.
    nearest : (before, after)
        The trimmed step next to the core before and after it (None: that end was not trimmed).
    """
    if core.bearing_source != "region centre" or nearest == (None, None):
        return core
    steps = core.region.steps
    n = gamma.size

    def gap(step: int, outward: int) -> float:
        nxt = step + outward
        return abs(float(gamma[nxt] - gamma[step])) if 0 <= nxt < n else core.step

    ends, base = [], 0.0
    for step, trimmed, outward in ((int(steps[0]), nearest[0], -1), (int(steps[-1]), nearest[1], 1)):
        g_out = gap(step, outward)
        base += g_out * g_out / 48.0
        if trimmed is None:
            ends.append((float(gamma[step]), g_out * g_out / 12.0))
        else:
            span = abs(float(gamma[trimmed] - gamma[step])) + gap(trimmed, outward)
            ends.append((0.5 * float(gamma[step] + gamma[trimmed]), span * span / 12.0))
    bearing = 0.5 * (ends[0][0] + ends[1][0])
    # The ends' share of the core's σ replaced; whatever else it holds (a jump's shift) kept.
    var = max(core.bearing_stderr**2 - base, 0.0) + 0.25 * (ends[0][1] + ends[1][1])
    # The trimmed ends' centre and the core's amplitude peak are two measurements of one bearing, as for any
    # region: weighed together where they agree, the peak's share of the bearing bringing the capsules' own
    # peaks' spread into the surface's σ (another echo summed into part of the stack bends the summed peak).
    peak = bearing_from_amplitude(gamma[steps], core.step_amplitude)
    bearing, sb, weight = centre_with_peak(bearing, math.sqrt(var), peak, not core.clipped)
    # The core's flanks must be mirror images about that bearing, where both ends fade alike, as a whole region's.
    fades = not any(unfaded_ends(gamma[steps], core.step_amplitude) or (False, False))
    asymmetry = flank_asymmetry(gamma[steps], core.step_amplitude, bearing, sb) if fades else 0.0
    h_i = core.ranges + core.positions @ unit_normal(bearing, core.tilt)
    spread = math.hypot(weight * core.peak_spread, asymmetry)
    return replace(core, bearing=bearing, bearing_stderr=sb, summed_spread=spread, depth=median(h_i))


def split_ends(
    m: Measured,
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
) -> list[Measured]:
    """A region's end steps that hold another target along the stack, told apart: the region's replacement.

    First its flanks the middle's double bounce with a surface across the fan explains
    (:func:`split_flanks`, both ends at once), then, on each piece, the ends that still slope off or lie
    deeper than the plane's middle (:func:`trim_ends`).

    A region neither splits where its amplitude hands over from one target to another (:func:`split_jump`).

    Returns
    -------
    The region's pieces in sweep order (``[m]`` when nothing splits off).
    """
    pieces = split_flanks(m, gamma, distance, amplitude, geometry, opts) or [m]
    out = [t for p in pieces for t in (trim_ends(p, gamma, distance, amplitude, geometry, opts) or [p])]
    if len(out) == 1:
        out = split_jump(m, gamma, distance, amplitude, geometry, opts) or out
    return out


def _deeper_block(depths: np.ndarray, opts: SurfaceOptions) -> tuple[int, float, float] | None:
    """The block of steps at the start that lies deeper than the rest, if significant: (length, depth
    difference m, its standard error m).

    The split that best separates two levels (the largest t of their difference); it must be deeper by
    more than ``curvature_sigmas`` of its standard error and by no more than twice the range tolerance
    (farther, the corner's echoes would have made their own region), each side ``min_steps`` long.
    """
    ok = np.isfinite(depths)
    k = depths.size
    if np.count_nonzero(ok) < 2 * opts.min_steps:
        return None
    best: tuple[float, int] | None = None
    for b in range(opts.min_steps, k - opts.min_steps + 1):
        head, tail = depths[:b][ok[:b]], depths[b:][ok[b:]]
        if head.size < 2 or tail.size < 2:
            continue
        diff = float(np.mean(head) - np.mean(tail))
        pooled = math.sqrt(
            (float(np.sum((head - head.mean()) ** 2)) + float(np.sum((tail - tail.mean()) ** 2)))
            / (head.size + tail.size - 2)
        )
        se = pooled * math.sqrt(1 / head.size + 1 / tail.size)
        t = diff / se if se > 0 else 0.0
        if 0 < diff <= 2 * opts.range_tolerance and (best is None or t > best[0]):
            best = (t, b)
    if best is None or best[0] < opts.curvature_sigmas:
        return None
    b = best[1]
    head, tail = depths[:b][ok[:b]], depths[b:][ok[b:]]
    return b, float(np.mean(head) - np.mean(tail)), float(np.mean(head) - np.mean(tail)) / best[0]


def split_dihedral(
    i: int,
    measured: list[Measured],
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
) -> list[Measured] | None:
    """A plane's region that runs on into the double bounce of its corner with a nearer plane.

    Where a plane meets a nearer one (a wall and the floor close below the array), the line they share
    lies barely deeper than the plane: ``|X| − h = h'²/(2h)`` for a wall ``h`` away and a floor ``h'``
    below.  Both answer within the range tolerance, so the region holds the plane's echoes and, past
    them on the line's side, the corner's: its span is no longer symmetric about the plane's foot.
    Each step's depth along the plane's normal tells the two apart (the corner's steps lie deeper, as
    one block on the line's side, by a level the steps' own scatter resolves): the region splits into
    the plane's (whole: it is nearer, nothing masks it) and the corner's (cut on the plane's side).
    The line's place is the trigger (a plane's bearing biased by the corner's steps moves it), and the
    confirmation: with the plane placed on its own steps, the block lies deeper by ``|X| − h``.

    Returns
    -------
    The region's replacement, the plane's and the corner's measured regions, or None if no nearer
    plane's corner runs into it or its steps do not resolve it.
    """
    m = measured[i]
    # Only a whole region: the corner's echoes lengthen it; a cut one has no span to be lengthened.
    if m.region.cut_before or m.region.cut_after:
        return None
    r = m.region
    n = unit_normal(m.bearing, m.tilt)
    for j, mj in enumerate(measured):
        if j == i or mj.bearing_source == "undetermined" or abs(wrap(m.bearing - mj.bearing)) < opts.foot_separation:
            continue
        line = plane_line(m, mj)
        if line is None:
            continue
        x = line[0]
        rho = float(np.linalg.norm(x))
        toward = math.atan2(float(x[2]), float(x[1]))
        half = 0.5 * (m.span[1] - m.span[0])
        if not (0.0 <= rho - m.depth <= 2 * opts.range_tolerance and abs(wrap(toward - m.bearing)) <= half):
            continue
        after = wrap(toward - m.bearing) > 0
        # Each step's depth along the plane's normal: the corner's steps lie deeper, as one block on its side.
        own = m.ranges + m.positions @ n
        pos = np.searchsorted(r.steps, r.rows)
        hs = np.array([median(own[pos == k]) if np.any(pos == k) else np.nan for k in range(r.steps.size)])
        found = _deeper_block(hs[::-1] if after else hs, opts)
        if found is None:
            return None
        block, step, step_se = found
        if after:
            plane_steps, corner_steps = r.steps[: r.steps.size - block], r.steps[r.steps.size - block :]
            plane_r = subregion(r, plane_steps, r.cut_before, False)
            corner_r = subregion(r, corner_steps, True, r.cut_after)
        else:
            corner_steps, plane_steps = r.steps[:block], r.steps[block:]
            plane_r = subregion(r, plane_steps, False, r.cut_after)
            corner_r = subregion(r, corner_steps, r.cut_before, True)
        plane_m, corner_m = (measure_region(s, gamma, distance, amplitude, geometry, opts) for s in (plane_r, corner_r))
        # The block must lie where the line of the plane so placed puts it: deeper by |X| − h.
        line = plane_line(plane_m, mj)
        if line is None:
            return None
        expected = float(np.linalg.norm(line[0])) - plane_m.depth
        if abs(step - expected) > 3 * step_se + 0.25 * expected:
            return None
        return [plane_m, corner_m]
    return None


def partial_regions(
    d: np.ndarray,
    held: list[Region],
    opts: SurfaceOptions,
    spread: float,
    *,
    gamma: np.ndarray | None = None,
    radial_offset: float = 0.0,
) -> list[Region]:
    """Regions among the readings no region holds, nearer than their steps' held readings by more than the
    range tolerance (a first-echo receiver: a capsule that hears a nearer target hears it first).

    Every capsule turns ``r`` off the axis, so a target part of the stack hears drifts along its run by
    ``r·(1 − cos Δγ)`` as one the whole stack hears: with ``gamma`` and ``radial_offset`` the runs that drift
    split are one region again (:func:`~.regions.find_regions`).

    Parameters
    ----------
    d : (n_steps, n_capsules) array
        The sweep's ranges, m.
    held : list of Region
        The regions found so far.
    opts : SurfaceOptions
    spread : float
        m: as :func:`~.regions.find_regions`' ``max_spread``.
    gamma : (n_steps,) array, optional
        Each step's rotation, rad.
    radial_offset : float
        The capsules' distance from the rotation axis, m.

    Returns
    -------
    list of Region, in sweep order.
    """
    mask, found = _unheld_regions(d, held, opts, spread, gamma=gamma, radial_offset=radial_offset)
    out = []
    for r in found:
        own = float(np.median(d[r.rows, r.capsules]))
        others = d[r.steps][mask[r.steps]]
        if (
            others.size
            and own < float(np.median(others)) - opts.range_tolerance
            and not _flank_of(r, own, held, d, opts)
        ):
            out.append(r)
    return out


def _unheld_regions(
    d: np.ndarray,
    held: list[Region],
    opts: SurfaceOptions,
    spread: float,
    *,
    gamma: np.ndarray | None = None,
    radial_offset: float = 0.0,
) -> tuple[np.ndarray, list[Region]]:
    """The readings ``held`` holds (a mask of ``d``'s shape), and the regions among the others."""
    mask = np.zeros(d.shape, dtype=bool)
    for r in held:
        mask[r.rows, r.capsules] = True
    found = find_regions(
        np.where(mask, np.nan, d),
        tolerance=opts.range_tolerance,
        max_gap=opts.max_gap,
        min_steps=opts.min_steps,
        max_spread=spread,
        gamma=gamma,
        radial_offset=radial_offset,
    )
    return mask, found


def _flank_of(r: Region, own: float, held: list[Region], d: np.ndarray, opts: SurfaceOptions) -> bool:
    """Whether a region the whole stack hears, at ``r``'s range (within twice the range tolerance) and on
    overlapping or adjacent steps (within ``max_gap``), is the same target: ``r`` is its flank, where only
    part of the stack still hears it."""
    lo, hi = int(r.steps[0]), int(r.steps[-1])
    for h in held:
        if int(h.steps[0]) > hi + opts.max_gap + 1 or int(h.steps[-1]) < lo - opts.max_gap - 1:
            continue
        if abs(float(np.median(d[h.rows, h.capsules])) - own) <= 2 * opts.range_tolerance:
            return True
    return False


def masked_regions(d: np.ndarray, held: list[Region], opts: SurfaceOptions, spread: float) -> list[Region]:
    """Regions among the readings no region holds, farther than a nearer target every other capsule hears at
    each of their steps (a wall past a box whose top only some capsules' beams clear).

    The receiver keeps each capsule's first echo: a capsule that hears a nearer target never reports a farther
    one, so a farther target's silence in those capsules says nothing of where it lies.  Where, at each of the
    region's steps, every capsule without a reading of the region holds a nearer reading of some region
    (nearer by more than the range tolerance), the target is heard as far as the first-echo receiver lets
    it be: a region of the fan like any other, classified on its own evidence (with one capsule per step its
    tilt is not determined, and its fit says so).

    Parameters
    ----------
    d : (n_steps, n_capsules) array
        The sweep's ranges, m.
    held : list of Region
        The regions found so far (those part of the stack hears included).
    opts : SurfaceOptions
    spread : float
        m: as :func:`~.regions.find_regions`' ``max_spread``.

    Returns
    -------
    list of Region, in sweep order.
    """
    mask, found = _unheld_regions(d, held, opts, spread)
    out = []
    for r in found:
        own = float(np.median(d[r.rows, r.capsules]))
        mine = np.zeros((r.steps.size, d.shape[1]), dtype=bool)
        mine[np.searchsorted(r.steps, r.rows), r.capsules] = True
        block = np.where(mask[r.steps], d[r.steps], np.nan)
        with np.errstate(invalid="ignore"):
            nearer = block < own - opts.range_tolerance
        if np.all(mine | nearer):
            out.append(r)
    return out
