"""What one region of constant depth says, before its class is decided.

:func:`measure_region`: bearing (beam pattern), depth, tilt and curvature along the capsule stack, echo
strength over a mirror's (:func:`mirror_normalised`), and whether a nearer echo masks its ends; the
:class:`Measured` region that :mod:`~lelsonar.reconstruct.estimate.surfaces.evidence` tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.corner.wall import ECHO_WINDOW_RANGE
from lelsonar.reconstruct.estimate.quality import DEGRADED, UNRELIABLE
from lelsonar.reconstruct.estimate.robust import median
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import (
    PLATEAU,
    amplitude_jump,
    bearing_from_amplitude,
    capsule_peak_spread,
    end_crossing_stderr,
    unfaded_ends,
)
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.stack import capsule_x, stack_fits
from lelsonar.reconstruct.estimate.surfaces.symmetry import flank_asymmetry

__all__ = [
    "Measured",
    "across_stack_measured",
    "centre_with_peak",
    "clean_cuts",
    "handed_over",
    "masked_ends",
    "measure_region",
    "mirror_normalised",
    "reading_positions",
    "step_medians",
    "step_table",
    "summed_width_stderr",
    "sweep_step",
    "unit_normal",
]


@dataclass(frozen=True, eq=False)
class Measured:
    """A region with what its echoes say, before its class is decided."""

    region: Region
    bearing: float
    bearing_stderr: float
    bearing_source: str
    findings: tuple[tuple[str, str], ...]
    depth: float
    depth_stderr: float
    tilt: float
    tilt_stderr: float
    curvature: float
    curvature_stderr: float
    stack_slope: float
    strength: float  # peak amplitude over a mirror's at this depth (NaN: unknown)
    peak: float
    peak_inside: bool  # the region holds its amplitude peak
    exact: bool  # its peak is inside and not clipped (else its strength is only a lower bound)
    clipped: bool  # the receiver clipped its peak (its strength is only a lower bound)
    span: tuple[float, float]  # γ of the region's first and last steps, rad
    step: float  # the sweep's step, rad
    step_amplitude: np.ndarray  # each step's median echo amplitude, V (NaN: none or no amplitudes)
    positions: np.ndarray  # (N, 3) each reading's capsule position, m
    ranges: np.ndarray  # (N,) each reading's range, m
    stack_sigma: float  # residual σ of the ranges along the stack about a free slope per region, m
    # rad: how far an echo summed into the amplitude window may have moved the bearing, the capsules' own peaks'
    # spread times the peak's share of the bearing, and for a centred region how far its flanks are from mirror
    # images about its bearing (:func:`~.symmetry.flank_asymmetry`); part of the surface's σ, not of the tests
    # that classify it
    summed_spread: float = 0.0
    # rad: the capsules' own amplitude peaks' spread (:func:`~.beam_pattern.capsule_peak_spread`) whatever the
    # peak's share of the bearing (0: no peak or no amplitudes), for a bearing weighed with the peak anew
    peak_spread: float = 0.0
    # (before, after): an end where another target's echo at a like range takes over (an amplitude jump split the
    # region there); that echo sums into the region's amplitude window there and bends its profile
    handed_over: tuple[bool, bool] = (False, False)

    @property
    def surface_bearing_stderr(self) -> float:
        """The bearing's σ a surface of this region reports: ``bearing_stderr`` and ``summed_spread``, rad."""
        return math.hypot(self.bearing_stderr, self.summed_spread)


def unit_normal(bearing: float, tilt: float = 0.0) -> np.ndarray:
    c = math.cos(tilt)
    return np.array([math.sin(tilt), c * math.cos(bearing), c * math.sin(bearing)])


def step_table(region: Region, values: np.ndarray) -> np.ndarray:
    """The region's readings' values by step and capsule: ``(len(region.steps), n_capsules)``, NaN where the
    capsule has no reading of the region at that step (or its value is not finite)."""
    table = np.full((region.steps.size, values.shape[1]), np.nan)
    v = values[region.rows, region.capsules]
    table[np.searchsorted(region.steps, region.rows), region.capsules] = np.where(np.isfinite(v), v, np.nan)
    return table


def step_medians(region: Region, values: np.ndarray) -> np.ndarray:
    """Each of the region's steps' median over its readings' finite values (NaN: none), as ``np.median``.

    Parameters
    ----------
    region : Region
    values : (n_steps, n_capsules) array
        A value per reading of the sweep (NaN or infinite: none).

    Returns
    -------
    (k,) array over ``region.steps``.
    """
    return _row_medians(step_table(region, values))


def _row_medians(table: np.ndarray) -> np.ndarray:
    """Each row's median over its finite values (NaN: none), as ``np.median``; sorts ``table`` in place."""
    table.sort(axis=1)  # NaN last: each row's first `count` values are its finite ones, in order
    count = np.count_nonzero(np.isfinite(table), axis=1)
    row = np.arange(table.shape[0])
    upper = table[row, count // 2]
    lower = table[row, np.maximum(count - 1, 0) // 2]
    # The middle value of an odd count, the mean of the middle two of an even one (NaN for none).
    return np.where(count % 2 == 1, upper, (lower + upper) / 2)


def reading_positions(geometry: ArrayGeometry, gamma: np.ndarray, rows: np.ndarray, capsules: np.ndarray) -> np.ndarray:
    """Each reading's capsule position (eq. 9), m: row ``capsules[i]`` of ``geometry.capsule_positions`` at
    ``gamma[rows[i]]``, the same numbers without the other capsules' rows."""
    g = np.asarray(gamma[rows], dtype=float)
    out = np.empty((g.size, 3))
    out[:, 0] = np.asarray(geometry.capsule_x, dtype=float)[capsules]
    out[:, 1] = geometry.radial_offset * np.cos(g)
    out[:, 2] = geometry.radial_offset * np.sin(g)
    return out


def sweep_step(gamma: np.ndarray) -> float:
    """The sweep's step, rad: the median ``|Δγ|`` (1° for a single step)."""
    return median(np.abs(np.diff(gamma))) if gamma.size > 1 else math.radians(1.0)


def masked_ends(region: Region, distance: np.ndarray, tolerance: float, max_gap: int) -> tuple[bool, bool]:
    """Whether a nearer echo in any one capsule's beam, just before and just after the region, masks it there.

    The receiver keeps each capsule's first echo: a nearer target seen by only some capsules (an edge beside
    the stack) ends the region in those capsules first, and the steps' median range may not show it.  Each
    capsule is compared with its own median over the region (a tilt spreads the capsules' ranges steadily).
    """
    block = distance[region.steps]
    # Each capsule's median (NaNs sort last); a capsule without an echo in the region takes the others'.
    count = np.count_nonzero(np.isfinite(block), axis=0)
    srt = np.sort(block, axis=0)
    cols = np.arange(block.shape[1])
    have = count > 0
    ref = 0.5 * (srt[np.maximum(count - 1, 0) // 2, cols] + srt[count // 2 - (count == 0), cols])
    ref[~have] = median(ref[have])
    reach = max_gap + 2
    first, last = int(region.steps[0]), int(region.steps[-1])
    before = distance[max(first - reach, 0) : first]
    after = distance[last + 1 : last + 1 + reach]
    with np.errstate(invalid="ignore"):
        return bool(np.any(before < ref - tolerance)), bool(np.any(after < ref - tolerance))


def handed_over(region: Region, distance: np.ndarray, ends: tuple[bool, bool], opts: SurfaceOptions) -> bool:
    """Whether another echo at a like range answers just past a flagged end: the echoes sum there, so the end's
    amplitude says nothing of where the region's own echo fades.  Like: nearer by no more than twice the range
    tolerance (the band a reading of the region's own target stays in), or farther by no more than that plus
    the amplitude window's reach in range (:data:`~lelsonar.reconstruct.estimate.corner.wall.ECHO_WINDOW_RANGE`):
    a later echo that rises inside the window the amplitude is read in adds to the region's own there, though
    the first echo alone sets the range."""
    spread = 2 * opts.range_tolerance
    with np.errstate(all="ignore"):
        ref = float(np.nanmedian(distance[region.rows, region.capsules]))
    reach = opts.max_gap + 2
    first, last = int(region.steps[0]), int(region.steps[-1])
    past = []
    if ends[0]:
        past.append(distance[max(first - reach, 0) : first])
    if ends[1]:
        past.append(distance[last + 1 : last + 1 + reach])
    with np.errstate(invalid="ignore"):
        return any(
            bool(np.any((block - ref >= -spread) & (block - ref <= spread + ECHO_WINDOW_RANGE))) for block in past
        )


def clean_cuts(region: Region, distance: np.ndarray, opts: SurfaceOptions) -> tuple[bool, bool]:
    """Which of the region's cut ends another echo cuts without reaching into its amplitude window there.

    The region's amplitude is read in a window just past its own time of flight
    (:data:`~lelsonar.reconstruct.estimate.corner.wall.ECHO_WINDOW_RANGE` of range): an echo that answers just
    past a cut end within that reach of the region's range, nearer (its ring-out, about as long as the window
    made to hold an echo's rise, still fills it) or farther (it rises inside it), sums into the region's last
    steps there and bends its flank; one nearer by more answers wholly before the window, so the flank there is
    the region's own echo alone, as past the sweep's end.  Like :func:`handed_over`, with the window's reach
    on the nearer side too.

    Returns
    -------
    (before, after): cut on that side, and no reading within the window's reach of the region's median range
    among the steps a run may bridge past that end.
    """
    spread = 2 * opts.range_tolerance + ECHO_WINDOW_RANGE
    with np.errstate(all="ignore"):
        ref = float(np.nanmedian(distance[region.rows, region.capsules]))
    reach = opts.max_gap + 2
    first, last = int(region.steps[0]), int(region.steps[-1])
    past = (distance[max(first - reach, 0) : first], distance[last + 1 : last + 1 + reach])
    with np.errstate(invalid="ignore"):
        like = [bool(np.any(np.abs(block - ref) <= spread)) for block in past]
    return region.cut_before and not like[0], region.cut_after and not like[1]


def measure_region(
    region: Region,
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
    *,
    step: float | None = None,
) -> Measured:
    """What a region's echoes say; ``step`` is :func:`sweep_step` of ``gamma`` (computed when not given)."""
    masked = masked_ends(region, distance, opts.range_tolerance, opts.max_gap)
    if (masked[0] and not region.cut_before) or (masked[1] and not region.cut_after):
        region = replace(region, cut_before=region.cut_before or masked[0], cut_after=region.cut_after or masked[1])
    g = gamma[region.steps]
    step = sweep_step(gamma) if step is None else step
    quant = step / math.sqrt(24.0)  # each end of the region uniform within a step
    findings: list[tuple[str, str]] = []
    cut = region.cut_before or region.cut_after
    mid = 0.5 * (float(g[0]) + float(g[-1]))
    peak_fit = None
    peak_weight = 0.0  # the amplitude peak's share of the bearing
    asymmetry = 0.0  # rad: how far the flanks' own midpoints put a centred region's bearing off
    peak = float("nan")
    clipped: bool | None = None
    per_step = np.full(region.steps.size, np.nan)
    if amplitude is not None:
        table = step_table(region, amplitude)
        per_step = _row_medians(table.copy())
        peak = float(np.nanmax(per_step)) if np.isfinite(per_step).any() else float("nan")
        clipped = bool(np.count_nonzero(per_step >= (1.0 - PLATEAU) * peak) >= 3) if math.isfinite(peak) else None
        peak_fit = bearing_from_amplitude(g, per_step)
    # Two echoes at one range, one taking over from the other inside the region: its ends are not both one
    # beam pattern's.  The shorter side may be the other echo's, so the centre may be off by half its extent:
    # a σ that says so while it stays within the verdict's bound, no centre bearing beyond it.
    jump = amplitude_jump(g, per_step) if amplitude is not None and not cut else None
    shift = 0.0 if jump is None else 0.5 * jump[1] * step
    mixed = ""
    if jump is not None:
        mixed = (
            f"the echo amplitude steps at γ {math.degrees(jump[0]):.1f}° as no one beam pattern does: two echoes "
            f"at one range, {jump[1]} steps of the region may be the other's, so its centre is not the wall's"
        )
    # An end the echo stops at while still strong is where its mirror ends, not where the beam fades it.
    unfaded = unfaded_ends(g, per_step) if amplitude is not None and not cut and jump is None else None
    unfaded = unfaded or (False, False)
    # Its consequence, a centre off the beam pattern's peak, must show beyond both σ before the centre is doubted
    # (without a peak in the region nothing vouches for the centre).
    stops = any(unfaded) and not handed_over(region, distance, unfaded, opts)
    if stops and peak_fit is not None:
        ends_se = math.hypot(step, step) / math.sqrt(48.0)
        stops = abs(peak_fit[0] - mid) > 3.0 * math.hypot(peak_fit[1], quant, ends_se)
    if stops:
        at = float(g[0]) if unfaded[0] else float(g[-1])
        mixed = (
            f"the echo stops at γ {math.degrees(at):.1f}° stronger than at its other end, as no beam pattern "
            "fades it: its mirror ends there, so the region's centre is not the wall's"
        )
    centred = not cut and not stops and shift <= opts.limits.max_normal_stderr
    if centred:
        # The region's ends are where the beam pattern falls under the threshold on either side: symmetric
        # about the target, so the centre is its bearing (the amplitudes can be bent by a later echo ringing
        # into the same window).  Each end's crossing is uniform over the gap to the next step out, which a
        # servo's quantised positions make uneven: the centre's variance is (gap_before² + gap_after²)/48.
        first, last = int(region.steps[0]), int(region.steps[-1])
        before = abs(float(gamma[first] - gamma[first - 1])) if first > 0 else step
        after = abs(float(gamma[last + 1] - gamma[last])) if last + 1 < gamma.size else step
        ends = math.sqrt((before * before + after * after) / 48.0)
        # The amplitude noise moves each end's threshold crossing too (the beam's log slope there over it).
        if amplitude is not None:
            jitter = end_crossing_stderr(g, per_step)
            ends = math.sqrt(ends * ends + (jitter[0] ** 2 + jitter[1] ** 2) / 4.0)
        bearing, sb, source = mid, math.hypot(ends, shift), "region centre"
        # The beam pattern's peak is a second measurement of the same bearing, independent of where the ends
        # fall: where the two agree within 3 σ of their difference, each weighs by its inverse variance.  The
        # peak is a parabola's vertex through every step's amplitude at its measured γ, so the step size enters
        # its σ only through the fit's residuals; the ends' quantisation is the centre's alone.
        # Two measurements that differ by more than their σ say (another echo summed into the amplitudes bends
        # the peak smoothly, which the parabola's residuals do not show) scale the weighted σ by their
        # difference in σ of it (the Birge ratio, at least 1).
        bearing, sb, peak_weight = centre_with_peak(mid, sb, peak_fit, clipped is False)
        # Its two flanks must be one beam pattern's, mirror images about that bearing: where they are not (an end
        # another target's echo at a like range sets), it is off by as much as their own axis and wander say.
        # Only where both ends fade alike are they one level's crossings (an echo that stops strong, at its main
        # lobe's null or its mirror's end, crosses no level there).
        if amplitude is not None and not any(unfaded):
            asymmetry = flank_asymmetry(g, per_step, bearing, sb)
    elif peak_fit is not None:
        bearing, sb, source = peak_fit[0], math.hypot(peak_fit[1], quant), "amplitude peak"
        peak_weight = 1.0
        # The peak of a cut region rests on the amplitudes alone, which other echoes ringing into the same
        # window bend (and a receiver's clipping flattens): usable, not good.
        findings.append(
            (
                DEGRADED,
                "bearing from the amplitude peak alone: "
                + (
                    mixed
                    if mixed
                    else "the region of constant depth is cut (a nearer echo or the sweep's end), so its centre "
                    "is not the wall's"
                ),
            )
        )
    else:
        bearing, source = mid, "undetermined"
        sb = 0.5 * (float(g[-1]) - float(g[0])) + step
        side = "both sides" if region.cut_before and region.cut_after else "one side"
        why = mixed if mixed else f"the region of constant depth is cut on {side} (a nearer echo or the sweep's end)"
        findings.append((UNRELIABLE, f"bearing not determined: {why}, and no amplitude peak is in it"))
    caps = reading_positions(geometry, gamma, region.rows, region.capsules)
    d = distance[region.rows, region.capsules]
    x = capsule_x(geometry)[region.capsules]
    (lin, lin_cov, lin_sigma), (quad, quad_cov, _) = stack_fits(x, region.rows, d)
    slope = float(lin[0])
    tilt = math.asin(max(-1.0, min(1.0, -slope))) if math.isfinite(slope) else 0.0
    tilt_se = math.sqrt(float(lin_cov[0, 0])) if math.isfinite(slope) else float("nan")
    n = unit_normal(bearing, tilt)
    h_i = d + caps @ n
    depth = median(h_i)
    # The median's standard error (1.25 σ/√N), with one capsule per step counted once per step.
    depth_se = 1.2533 * float(np.std(h_i)) / math.sqrt(max(region.steps.size, 1)) if h_i.size > 1 else float("nan")
    strength = mirror_normalised(peak, depth, opts)
    # rad: how far the capsules' own peaks disagree (another echo summing into the window moves each capsule's
    # peak its own way), through the peak's share of the bearing.
    spread = capsule_peak_spread(g, table) if peak_fit is not None and amplitude is not None else 0.0
    return Measured(
        region=region,
        bearing=bearing,
        bearing_stderr=sb,
        bearing_source=source,
        findings=tuple(findings),
        depth=depth,
        depth_stderr=depth_se,
        tilt=tilt,
        tilt_stderr=tilt_se,
        curvature=float(quad[1]),
        curvature_stderr=math.sqrt(float(quad_cov[1, 1])) if math.isfinite(quad[1]) else float("nan"),
        stack_slope=slope,
        strength=strength,
        peak=peak,
        peak_inside=centred or peak_fit is not None,
        exact=(centred or peak_fit is not None) and clipped is False,
        clipped=clipped is True,
        span=(float(g[0]), float(g[-1])),
        step=step,
        step_amplitude=per_step,
        positions=caps,
        ranges=d,
        stack_sigma=lin_sigma,
        summed_spread=math.hypot(peak_weight * spread, asymmetry),
        peak_spread=spread,
    )


def centre_with_peak(
    centre: float, centre_stderr: float, peak: tuple[float, float] | None, unclipped: bool
) -> tuple[float, float, float]:
    """A region's centre bearing weighed with its amplitude peak where the two agree within 3 σ of their difference.

    Two measurements of one bearing (the ends' threshold crossings; the beam pattern's vertex), each weighed by
    its inverse variance; a difference larger than their σ say scales the weighted σ by it (the Birge ratio, at
    least 1).  A clipped top's plateau, or a peak beyond 3 σ, leaves the centre alone.

    Parameters
    ----------
    centre, centre_stderr : float
        rad.
    peak : (bearing, σ) or None
        rad: :func:`~.beam_pattern.bearing_from_amplitude`.
    unclipped : bool
        The receiver did not clip the region's peak.

    Returns
    -------
    (bearing, σ, the peak's share of the bearing), rad, rad, in [0, 1].
    """
    if not unclipped or peak is None:
        return centre, centre_stderr, 0.0
    apart = abs(peak[0] - centre) / math.hypot(peak[1], centre_stderr)
    if not apart <= 3.0:
        return centre, centre_stderr, 0.0
    wc, wp = 1.0 / centre_stderr**2, 1.0 / peak[1] ** 2
    return (wc * centre + wp * peak[0]) / (wc + wp), max(1.0, apart) / math.sqrt(wc + wp), wp / (wc + wp)


def mirror_normalised(amplitude: float, depth: float, opts: SurfaceOptions) -> float:
    """An echo amplitude over a mirror's spreading and absorption at ``depth``: ``A · 2ρ · 10^(α·2ρ/20)``."""
    return amplitude * 2 * depth * 10 ** (opts.absorption_db_per_m * 2 * depth / 20)


def summed_width_stderr(curvature: float | None, beam: float, flattest: float) -> float:
    """How far another echo summing into a region's flank may have moved its amplitude peak, rad.

    One target's echo follows the beam, in ``log`` a parabola of curvature ``k``: a spread ``s² = 1/(2k)``
    across γ.  A second echo of weight ``w`` (the weaker, ``w ≤ ½``) ``δ`` away widens the sum to about
    ``s² + w(1 − w)δ²`` and moves its peak by about ``wδ``, whose square is at most that excess.  So
    ``√(1/(2c) − 1/(2k))``, with ``c`` the region's own curvature and ``k`` the sweep's (its regions with a
    clean peak), bounds the shift; 0 when the top is no flatter than one echo's can be (``c ≥ flattest``).

    Parameters
    ----------
    curvature : float or None
        The region's ``c`` (1/rad², :func:`~.beam_pattern.log_amplitude_curvature`); None: unknown.
    beam : float
        The sweep's ``k`` (1/rad²); NaN: unknown.
    flattest : float
        The smallest curvature one echo shows in the sweep (its regions' spread), 1/rad².

    Returns
    -------
    The bound, rad (0 when either curvature is unknown or the top is no flatter than one echo's).
    """
    if curvature is None or not (curvature > 0 and beam > 0) or curvature >= flattest:
        return 0.0
    return math.sqrt(max(0.0, 1.0 / (2.0 * curvature) - 1.0 / (2.0 * beam)))


def across_stack_measured(m: Measured) -> Measured:
    """A region whose ranges curve along the stack (a line across it, or a point), placed by its exact ranges.

    A line across the stack (its direction in the fan's plane, at ``x_0`` along the stack and ``h`` from the
    rotation axis in the fan, its normal there at the region's bearing ``β``) is at
    ``d = √((h − p·n)² + (x − x_0)²)`` from a capsule at ``p`` (``x`` along the stack, ``p·n`` its radial offset
    toward the line): a parabola in ``x`` only to second order, whose third-order term a straight or a
    quadratic fit of the ranges over unevenly heard capsules turns into a slope.  Gauss-Newton on ``(h, x_0)``
    from the straight fit's guess; their covariance from the residuals.  The point ``x_0·e_x + h·n`` gives the
    depth ``√(h² + x_0²)`` and the tilt ``atan2(x_0, h)``.

    Returns
    -------
    The region with that depth, tilt and their σ (unchanged when fewer than two capsules hear it or the fit
    does not converge).
    """
    x = m.positions[:, 0]
    if np.unique(x).size < 2 or m.ranges.size < 4:
        return m
    radial = m.positions @ unit_normal(m.bearing)
    h, x0 = m.depth * math.cos(m.tilt), m.depth * math.sin(m.tilt)
    cov = None
    for _ in range(10):
        a = h - radial
        dist = np.hypot(a, x - x0)
        if not np.all(dist > 0):
            return m
        jac = np.stack([a / dist, (x0 - x) / dist], axis=1)
        res = m.ranges - dist
        jtj = jac.T @ jac
        if np.linalg.cond(jtj) > 1e12:
            return m
        step = np.linalg.solve(jtj, jac.T @ res)
        h, x0 = h + float(step[0]), x0 + float(step[1])
        if abs(float(step[0])) + abs(float(step[1])) < 1e-9:
            break
    else:
        return m
    a = h - radial
    dist = np.hypot(a, x - x0)
    res = m.ranges - dist
    jac = np.stack([a / dist, (x0 - x) / dist], axis=1)
    s2 = float(res @ res) / max(res.size - 2, 1)
    cov = s2 * np.linalg.inv(jac.T @ jac)
    depth = math.hypot(h, x0)
    # σ along the ray and across it (the tilt): the covariance of (h, x0) rotated by the tilt.
    tilt = math.atan2(x0, h)
    along = np.array([math.cos(tilt), math.sin(tilt)])
    across = np.array([-math.sin(tilt), math.cos(tilt)])
    depth_se = math.sqrt(max(float(along @ cov @ along), 0.0))
    tilt_se = math.sqrt(max(float(across @ cov @ across), 0.0)) / depth
    return replace(m, tilt=tilt, tilt_stderr=tilt_se, depth=depth, depth_stderr=depth_se)
