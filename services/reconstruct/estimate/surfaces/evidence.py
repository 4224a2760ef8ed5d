"""What one region of constant depth says, and the physical tests that tell a plane, a corner and an edge apart.

* :func:`measure_region`: bearing (beam pattern), depth, tilt and curvature along the capsule stack,
  echo strength over a mirror's;
* :func:`pair_corner`: the double bounce of two planes (range ``|X|`` of their intersection);
* :func:`stack_dihedral`: the double bounce of a plane with a surface across the fan (a floor or a
  ceiling), where the range and the stack slope must agree;
* :func:`plane_end`: a region on one plane's trace, off its foot: that plane's end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.corner.wall import ECHO_WINDOW_RANGE
from lelsonar.reconstruct.estimate.quality import DEGRADED, UNRELIABLE
from lelsonar.reconstruct.estimate.surfaces.regions import (
    PLATEAU,
    Region,
    amplitude_jump,
    bearing_from_amplitude,
    capsule_x,
    end_crossing_stderr,
    stack_fits,
    unfaded_ends,
    weaker_at,
)
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions

__all__ = [
    "Measured",
    "across_stack",
    "beyond_reach",
    "unit_normal",
    "feature_point",
    "in_span",
    "masked_ends",
    "measure_region",
    "step_medians",
    "sweep_step",
    "mirror_normalised",
    "pair_corner",
    "pair_stderr",
    "end_stderr",
    "handed_over",
    "reach_stderr",
    "plane_end",
    "plane_line",
    "stack_dihedral",
    "stack_or_pair",
    "unseen_corner",
    "wrap",
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


def unit_normal(bearing: float, tilt: float = 0.0) -> np.ndarray:
    c = math.cos(tilt)
    return np.array([math.sin(tilt), c * math.cos(bearing), c * math.sin(bearing)])


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
    table = np.full((region.steps.size, values.shape[1]), np.nan)
    v = values[region.rows, region.capsules]
    table[np.searchsorted(region.steps, region.rows), region.capsules] = np.where(np.isfinite(v), v, np.nan)
    table.sort(axis=1)  # NaN last: each row's first `count` values are its finite ones, in order
    count = np.count_nonzero(np.isfinite(table), axis=1)
    row = np.arange(table.shape[0])
    upper = table[row, count // 2]
    lower = table[row, np.maximum(count - 1, 0) // 2]
    # The middle value of an odd count, the mean of the middle two of an even one (NaN for none).
    return np.where(count % 2 == 1, upper, (lower + upper) / 2)


def sweep_step(gamma: np.ndarray) -> float:
    """The sweep's step, rad: the median ``|Δγ|`` (1° for a single step)."""
    return float(np.median(np.abs(np.diff(gamma)))) if gamma.size > 1 else math.radians(1.0)


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
    ref[~have] = float(np.median(ref[have]))
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
    peak = float("nan")
    clipped: bool | None = None
    per_step = np.full(region.steps.size, np.nan)
    if amplitude is not None:
        per_step = step_medians(region, amplitude)
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
        # fall (its σ, as an amplitude peak's alone, holds the steps' quantisation): where the two agree within
        # 3 σ of their difference, each weighs by its inverse variance.
        peak_sb = math.hypot(peak_fit[1], quant) if peak_fit is not None else math.inf
        if clipped is False and peak_fit is not None and abs(peak_fit[0] - mid) <= 3.0 * math.hypot(peak_sb, sb):
            wc, wp = 1.0 / sb**2, 1.0 / peak_sb**2
            bearing, sb = (wc * mid + wp * peak_fit[0]) / (wc + wp), 1.0 / math.sqrt(wc + wp)
    elif peak_fit is not None:
        bearing, sb, source = peak_fit[0], math.hypot(peak_fit[1], quant), "amplitude peak"
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
    caps = geometry.capsule_positions(gamma[region.rows])[np.arange(region.rows.size), region.capsules]
    d = distance[region.rows, region.capsules]
    x = capsule_x(geometry)[region.capsules]
    (lin, lin_cov, lin_sigma), (quad, quad_cov, _) = stack_fits(x, region.rows, d)
    slope = float(lin[0])
    tilt = math.asin(max(-1.0, min(1.0, -slope))) if math.isfinite(slope) else 0.0
    tilt_se = math.sqrt(float(lin_cov[0, 0])) if math.isfinite(slope) else float("nan")
    n = unit_normal(bearing, tilt)
    h_i = d + caps @ n
    depth = float(np.median(h_i))
    # The median's standard error (1.25 σ/√N), with one capsule per step counted once per step.
    depth_se = 1.2533 * float(np.std(h_i)) / math.sqrt(max(region.steps.size, 1)) if h_i.size > 1 else float("nan")
    strength = mirror_normalised(peak, depth, opts)
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
    )


def mirror_normalised(amplitude: float, depth: float, opts: SurfaceOptions) -> float:
    """An echo amplitude over a mirror's spreading and absorption at ``depth``: ``A · 2ρ · 10^(α·2ρ/20)``."""
    return amplitude * 2 * depth * 10 ** (opts.absorption_db_per_m * 2 * depth / 20)


def across_stack(m: Measured, opts: SurfaceOptions) -> bool:
    """Ranges curved along the stack as a line or point across it (``c ≈ 1/(2ρ)``), not as a plane (``c = 0``)."""
    c, sc = m.curvature, m.curvature_stderr
    if not (math.isfinite(c) and math.isfinite(sc) and sc > 0):
        return False
    expected = 1.0 / (2.0 * m.depth)
    return c > opts.curvature_sigmas * sc and abs(c - expected) < max(0.5 * expected, 3 * sc)


def feature_point(m: Measured) -> np.ndarray:
    return m.depth * unit_normal(m.bearing)


def in_span(bearing: float, m: Measured, margin: float, beyond_cut: float) -> bool:
    """``bearing`` within the region's span of γ; on a cut side the target may lie up to ``beyond_cut`` past it."""
    g0, g1 = m.span
    lo = g0 - margin - (beyond_cut if m.region.cut_before else 0.0)
    hi = g1 + margin + (beyond_cut if m.region.cut_after else 0.0)
    return lo <= bearing <= hi


def plane_line(a: Measured, b: Measured) -> tuple[np.ndarray, np.ndarray] | None:
    """The line where two planes meet, with their tilts: its point nearest the array and its direction.

    Returns None for planes nearly parallel (no corner): ``|n_a × n_b| < 0.2``.
    """
    na, nb = unit_normal(a.bearing, a.tilt), unit_normal(b.bearing, b.tilt)
    direction = np.cross(na, nb)
    size = float(np.linalg.norm(direction))
    if size < 0.2:
        return None
    # The least-norm solution of n_a·X = h_a, n_b·X = h_b is the line's point nearest the origin.
    mat = np.stack([na, nb])
    x = mat.T @ np.linalg.solve(mat @ mat.T, np.array([a.depth, b.depth]))
    return x, direction / size


def pair_corner(m: Measured, planes: list[Measured], opts: SurfaceOptions) -> tuple[list[int], float] | None:
    """Two planes whose double bounce this region is: a concave corner.

    A corner's echo comes from the line ``X`` where its two walls meet, at the double-bounce range
    ``|X|`` (the retro-reflection in the plane normal to the edge; ``X`` its point nearest the array)
    and the bearing of ``X`` in the fan, which must fall within the region's span of γ (past a cut
    end, within ``beyond_cut``).  The planes' tilts place the line: a wall the fan meets off square
    leans it out of the fan.

    Returns
    -------
    (indices into ``planes``, bearing of ``X``), the closest in range, or None.
    """
    best: tuple[float, list[int], float] | None = None
    for a in range(len(planes)):
        for b in range(a + 1, len(planes)):
            line = plane_line(planes[a], planes[b])
            if line is None:
                continue
            x = line[0]
            rho = float(np.linalg.norm(x))
            bearing = math.atan2(float(x[2]), float(x[1]))
            miss = abs(rho - m.depth)
            if (
                miss <= opts.on_trace
                and in_span(bearing, m, m.step, opts.beyond_cut)
                and (best is None or miss < best[0])
            ):
                best = (miss, [a, b], bearing)
    return None if best is None else (best[1], best[2])


def beyond_reach(
    m: Measured, bearing: float, pj: Measured, seen: list[Measured], opts: SurfaceOptions, *, placed: bool = False
) -> str:
    """Why plane ``pj`` cannot reach ``bearing`` along its trace, where region ``m`` would be its end ("": nothing
    the sweep saw says so).

    A mirror answers only at its foot; how far it runs along its trace shows only in what lies between its
    region and ``m`` (every other region whose span lies between theirs in the sweep):

    * one whose bearing is determined, deeper than the trace's range there (``h / cos(β_k − β_j)``) by
      more than ``on_trace``, would be hidden behind the plane had it run on: the plane ends before it;
    * where ``placed`` (``m``'s bearing is the trace's alone, its own undetermined), one on the trace
      nearer the foot (at its determined bearing, or, undetermined, at the bearing its depth puts it on
      the trace, within its span) is the plane's own end: the plane ends there.  A region whose own
      bearing puts it on the trace is evidence of its own and is not set aside for it.

    A line across the stack at the plane's foot (its corner with a surface across the fan) is no end along
    the fan and is passed over.
    """
    delta = wrap(bearing - pj.bearing)
    h = pj.depth / math.cos(pj.tilt)
    # Between, in the sweep: past the plane's region on m's side, and before m's.
    if delta > 0:
        lo, hi = pj.span[1], m.span[0] if m.span[0] > pj.span[1] else math.inf
    else:
        lo, hi = m.span[1] if m.span[1] < pj.span[0] else -math.inf, pj.span[0]
    for k in seen:
        if k is m or k is pj or not (lo < k.span[0] and k.span[1] < hi):
            continue
        if k.bearing_source != "undetermined":
            dk = wrap(k.bearing - pj.bearing)
            if dk * delta <= 0 or abs(dk) >= abs(delta) or abs(dk) >= 0.5 * math.pi:
                continue
            trace = h / math.cos(dk)
            if k.depth > trace + opts.on_trace:
                return (
                    f"a target {k.depth:.2f} m away at γ {math.degrees(k.bearing):.1f}° lies behind its trace "
                    f"({trace:.2f} m): the plane ends before it"
                )
            on = placed and abs(k.depth - trace) <= opts.on_trace
        else:
            if not placed or k.depth <= h:
                continue
            dk = math.copysign(math.acos(h / k.depth), delta)
            on = abs(dk) < abs(delta) - m.step and in_span(wrap(pj.bearing + dk), k, k.step, opts.beyond_cut)
        if on and not across_stack(k, opts) and stack_dihedral(k, [pj], opts) is None:
            at = math.degrees(wrap(pj.bearing + dk))
            return f"another target on its trace at γ {at:.1f}°, nearer its foot, is its end"
    return ""


def plane_end(
    m: Measured,
    planes: list[Measured],
    opts: SurfaceOptions,
    seen: list[Measured] | None = None,
    gamma: np.ndarray | None = None,
) -> tuple[list[int], float] | None:
    """Where a region whose own bearing is not determined sits on one plane's trace: that plane's end.

    The end lies on the trace at the region's depth, at ``β_j ± acos(h_j/ρ)``, within the region's span of γ.
    Off the foot by less than ``foot_separation`` it is still no part of the plane when it is deeper than the
    plane by more than ``range_tolerance``: a mirror's echoes all lie at its one depth.  With ``seen`` (every
    region of the sweep), no bearing the plane cannot reach (:func:`beyond_reach`).  With ``gamma`` (the
    sweep's), no bearing inside the region where its own echo is weaker than elsewhere in it
    (:func:`~.regions.weaker_at`): a target there would be its region's strongest echo.

    Returns
    -------
    ([index into ``planes``], bearing) or None.
    """
    for j, pj in enumerate(planes):
        # The plane's trace in the fan: a tilted plane crosses it at h / cos(tilt).
        h = pj.depth / math.cos(pj.tilt)
        if h >= m.depth:
            continue
        half = math.acos(h / m.depth)
        if half <= opts.foot_separation and m.depth - h <= opts.range_tolerance:
            continue
        # Either side of the foot may fall within the reach past a cut end: the side nearer the region's own
        # steps first (its echo is heard there, the other side only through the beam's far flank).
        sides = sorted((wrap(pj.bearing - half), wrap(pj.bearing + half)), key=lambda b: _off_span(b, m))
        for bearing in sides:
            if (
                in_span(bearing, m, m.step, opts.beyond_cut)
                and not (seen is not None and beyond_reach(m, bearing, pj, seen, opts, placed=True))
                and not (gamma is not None and weaker_at(gamma[m.region.steps], m.step_amplitude, bearing))
            ):
                return [j], bearing
    return None


def _off_span(bearing: float, m: Measured) -> float:
    """How far ``bearing`` lies outside the region's span of γ (0 inside), rad."""
    return max(0.0, m.span[0] - bearing, bearing - m.span[1])


def unseen_corner(mi: Measured, mk: Measured, pj: Measured, opts: SurfaceOptions) -> float | None:
    """A bearing for the plane of region ``mi`` (its own left open) whose concave corner with plane ``pj`` is
    region ``mk``: the two regions' echoes explained together, ``mi`` a wall's mirror and ``mk`` its corner.

    A mirror answers at its foot, at its depth ``h_i``; two walls meet on the line where ``n_i·X = h_i`` and
    ``n_j·X = h_j`` (its range ``|X|``, the double bounce of :func:`pair_corner`).  For a concave corner seen
    from inside, ``X`` lies between the two feet in the fan.  Where some bearing ``β_i`` within ``mi``'s reach
    (its span, past a cut end by up to ``beyond_cut``) puts that line at ``mk``'s depth (within ``on_trace``) and
    at a bearing within ``mk``'s reach, both regions are explained by one wall and its corner with ``pj``.  The
    wall's foot lies past ``mi``'s cut end away from ``mk``, and ``mk`` is cut on ``mi``'s side: the wall's nearer
    mirror masks its corner where both answer.

    Returns
    -------
    That ``β_i`` (the one nearest ``mi``'s span), rad, or None.
    """
    # The wall's foot lies past mi's cut end on the side away from mk (a foot inside its region would show as
    # its amplitude peak or its centre): mk beside it, masked there by the wall's nearer mirror.
    if mk.span[0] > mi.span[1] and mi.region.cut_before and mk.region.cut_before:
        lo, hi = mi.span[0] - opts.beyond_cut, mi.span[0] - mi.step
    elif mk.span[1] < mi.span[0] and mi.region.cut_after and mk.region.cut_after:
        lo, hi = mi.span[1] + mi.step, mi.span[1] + opts.beyond_cut
    else:
        return None
    beta = np.arange(lo, hi + 0.5 * mi.step, mi.step)
    if not beta.size:
        return None
    ti = beta - pj.bearing
    sin_t = np.sin(ti)
    with np.errstate(divide="ignore", invalid="ignore"):
        # X in the fan from n_i·X = h_i, n_j·X = h_j (unit normals at β_i and β_j), in the frame of β_j.
        along_j = np.full(beta.size, pj.depth)
        across = (mi.depth - pj.depth * np.cos(ti)) / sin_t
        rho = np.hypot(along_j, across)
        bearing_x = pj.bearing + np.arctan2(across, along_j)
    # Between the feet (a concave corner seen from inside), at mk's depth and within its reach.
    t_w = np.angle(np.exp(1j * ti))
    off_x = np.angle(np.exp(1j * (bearing_x - pj.bearing)))
    between = (np.sign(off_x) == np.sign(t_w)) & (np.abs(off_x) < np.abs(t_w))
    lo_k = mk.span[0] - mk.step - (opts.beyond_cut if mk.region.cut_before else 0.0)
    hi_k = mk.span[1] + mk.step + (opts.beyond_cut if mk.region.cut_after else 0.0)
    at_x = np.angle(np.exp(1j * bearing_x))
    ok = np.isfinite(rho) & (np.abs(sin_t) > 0.2) & between & (np.abs(rho - mk.depth) <= opts.on_trace)
    ok &= (at_x >= lo_k) & (at_x <= hi_k)
    if not ok.any():
        return None
    centre = 0.5 * (mi.span[0] + mi.span[1])
    cand = beta[ok]
    return wrap(float(cand[int(np.argmin(np.abs(cand - centre)))]))


def stack_dihedral(m: Measured, planes: list[Measured], opts: SurfaceOptions) -> tuple[int, float, str] | None:
    """A plane whose concave corner with a surface across the stack (a floor, a ceiling) this region is.

    That corner is a line in the plane, across the stack at ``x = z``: its echo retro-reflects in the plane
    normal to the line, so each reading's range is the capsule's distance to it,
    ``√((h − n·p)² + (x_p − z)²)``, with the plane's own ``n`` and ``h``.  One unknown, ``z``, must then
    explain every reading of the region as well as a free slope per region does (within twice its
    residual σ), with ``z`` off the fan by more than 3 σ (else it is the plane's own echo).  The plane's
    bearing must lie within a beam's half-width (``beyond_cut``) of the region.

    Returns
    -------
    (index into ``planes``, ``z`` in m, the evidence) or None.
    """
    s, se, sigma = m.stack_slope, m.tilt_stderr, m.stack_sigma
    if not (math.isfinite(s) and math.isfinite(se) and se > 0 and abs(s) > opts.curvature_sigmas * se):
        return None
    if not (math.isfinite(sigma) and sigma > 0 and abs(s) < 1):
        return None
    x, d = m.positions[:, 0], m.ranges
    for j, pj in enumerate(planes):
        # The wall's own nearer echo masks the line's wherever both answer, whether or not the ranges differ
        # enough to mark the region cut: the foot may lie a beam's half-width past either end.
        if not (m.span[0] - opts.beyond_cut <= pj.bearing <= m.span[1] + opts.beyond_cut and m.depth > pj.depth):
            continue
        a = pj.depth - m.positions @ unit_normal(pj.bearing)
        z = -s * m.depth  # the slope's own guess, then Gauss-Newton on the one unknown
        for _ in range(8):
            r = np.sqrt(a * a + (x - z) ** 2)
            jac = (z - x) / r
            den = float(jac @ jac)
            if not den > 0:
                break
            z -= float(jac @ (r - d)) / den
        r = np.sqrt(a * a + (x - z) ** 2)
        rms = math.sqrt(float(np.mean((d - r) ** 2)))
        den = float(((z - x) / r) @ ((z - x) / r))
        z_se = sigma / math.sqrt(den) if den > 0 else float("inf")
        if rms <= 2 * sigma and abs(z) > 3 * z_se:
            return (
                j,
                z,
                (
                    f"the double bounce of the plane at {pj.depth:.2f} m with a surface across the fan {z:+.2f} m "
                    f"along the stack: one line explains the ranges to {1000 * rms:.1f} mm rms "
                    f"(a free slope: {1000 * sigma:.1f} mm)"
                ),
            )
    return None


def stack_or_pair(
    m: Measured, planes: list[Measured], low: tuple[int, float, str], pair: tuple[list[int], float]
) -> tuple[str, str]:
    """Which double bounce a region is when both :func:`stack_dihedral` and :func:`pair_corner` explain it.

    A plane turned about the fan's normal (a wall's yaw in the vertical fan) slopes its corner with a plane
    in the fan (the floor) along the stack as a line across the fan, off it by about the second plane's
    distance, does: over a short stack both give one linear slope.  The pair's line has no free parameter
    but its range, which the planes' depths shift as a whole: its ranges' shape along the stack must explain
    the readings to twice a free slope's residual σ, the bar the line across the fan passes with its one
    unknown.  The line across the fan answers at the plane's foot,
    the pair's at the bearing of their intersection: a determined bearing within 3 σ of one and not of the
    other settles it.  The pair's planes were both seen, the surface across the fan only inferred: where
    the evidence agrees with both, the pair is taken, and said to be unsettled.

    Returns
    -------
    ``"pair"`` or ``"stack"``, and a reason to add when the choice is not settled (empty when it is).
    """
    a, b = planes[pair[0][0]], planes[pair[0][1]]
    line = plane_line(a, b)
    if line is None:
        return "stack", ""
    rel = m.positions - line[0][None, :]
    predicted = np.linalg.norm(rel - (rel @ line[1])[:, None] * line[1][None, :], axis=1)
    # The planes' depths shift the line's range as a whole (pair_corner bounds that): its shape along the
    # stack must explain the ranges as well as the line across the fan must, within twice a free slope's σ.
    resid = m.ranges - predicted
    if not float(np.sqrt(np.mean((resid - resid.mean()) ** 2))) <= 2 * m.stack_sigma:
        return "stack", ""
    if m.bearing_source != "undetermined":
        reach = 3 * math.hypot(m.bearing_stderr, m.step)
        at_pair = abs(wrap(m.bearing - pair[1])) <= reach
        at_foot = abs(wrap(m.bearing - planes[low[0]].bearing)) <= reach
        if at_foot and not at_pair:
            return "stack", ""
        if at_pair and not at_foot:
            return "pair", ""
    return "pair", (
        "also explained as the plane's double bounce with an unseen surface across the fan: "
        "the ranges and the bearing do not settle which"
    )


def pair_stderr(m: Measured, which: list[int], planes: list[int], measured: list[Measured]) -> float:
    """A placed region's bearing σ: the planes' bearing σ, at least one step's quantisation."""
    return max(math.sqrt(sum(measured[planes[j]].bearing_stderr ** 2 for j in which)), m.step / math.sqrt(24.0))


def end_stderr(m: Measured, pj: Measured, bearing: float) -> float:
    """The bearing σ of a plane's end placed on its trace at ``bearing`` from the two depths (:func:`plane_end`).

    The end lies at ``β_j ± acos(h/ρ)``: besides the plane's bearing σ, the depths' own σ move it by
    ``σ_h / (ρ sin δ)`` and ``h σ_ρ / (ρ² sin δ)`` (``δ`` its angle off the foot), which grow without bound
    toward the foot, where the trace runs along the range; at least one step's quantisation.
    """
    sin_d = abs(math.sin(wrap(bearing - pj.bearing)))
    if not sin_d > 0:
        return math.pi
    sh = pj.depth_stderr if math.isfinite(pj.depth_stderr) else 0.0
    sr = m.depth_stderr if math.isfinite(m.depth_stderr) else 0.0
    rho = m.depth
    spread = math.hypot(sh / (rho * sin_d), pj.depth * sr / (rho * rho * sin_d))
    return min(math.pi, math.hypot(math.hypot(pj.bearing_stderr, spread), m.step / math.sqrt(24.0)))


def reach_stderr(m: Measured, opts: SurfaceOptions) -> float:
    """The bearing σ of a cut region placed at its span's centre with nothing else to place it.

    Its target lies within the span, or past a cut end by up to ``beyond_cut`` (a nearer echo hides its
    peak): uniform over that reach, the centre misses it by the reach's own σ (``width/√12``) and by its
    offset from the reach's middle.
    """
    lo = m.span[0] - (opts.beyond_cut if m.region.cut_before else 0.0)
    hi = m.span[1] + (opts.beyond_cut if m.region.cut_after else 0.0)
    bias = 0.5 * (lo + hi) - m.bearing
    return max(m.bearing_stderr, math.sqrt(bias * bias + (hi - lo) ** 2 / 12.0))


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi
