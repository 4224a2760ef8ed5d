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
* **class** by physics (the tests are in :mod:`.evidence`):

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
    (:data:`~.results.UNSETTLED`, ``Feature.settled``);
  - an echo much weaker than the sweep's strongest at its range (diffraction):
    an **edge**; a region cut before its peak is weak only if the upper
    estimate of its peak (its flank, extrapolated with the sweep's own beam
    curvature) is;
  - anything else: a **plane**.

A target only part of the capsule stack hears, nearer than what the rest hear at its steps (an edge off the
fan), is found among the readings no region holds; it is a corner or an edge, never a plane.  A weak region
whose amplitude steps as no one beam pattern does holds two diffracting targets at one range: two edges.

Each plane is fitted on its own echoes, walls joined at concave corners with them (:mod:`.fitting`, :mod:`.joint`).
A corner or an edge lies where its echo comes from, off the fan by its stack slope's tilt; a concave corner
of two fitted planes on their line, with their covariance (:mod:`.placement`).

The planes' verdicts go through :func:`~lelsonar.reconstruct.estimate.quality.assess_plane`
with the extractor's own findings (bearing undetermined or disputed, region cut).
Their covariance is over (bearing, tilt, offset): a wall well placed in range can
be poorly placed in bearing.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.quality import DEGRADED, GOOD
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import (
    PLATEAU,
    amplitude_jump,
    extrapolated_peak,
    log_amplitude_curvature,
    peak_at_bearing,
)
from lelsonar.reconstruct.estimate.surfaces.evidence import (
    across_stack,
    beyond_reach,
    end_stderr,
    feature_point,
    off_fan_tilt,
    off_fan_weak,
    pair_corner,
    pair_stderr,
    plane_end,
    plane_line,
    reach_stderr,
    stack_dihedral,
    stack_or_pair,
    taken_back,
    walls_of_unseen_corners,
    wrap,
)
from lelsonar.reconstruct.estimate.surfaces.fitting import METHOD, fit_surface, joint_fit
from lelsonar.reconstruct.estimate.surfaces.flanks import partial_regions, split_dihedral, split_ends
from lelsonar.reconstruct.estimate.surfaces.measurement import (
    Measured,
    measure_region,
    mirror_normalised,
    summed_width_stderr,
    sweep_step,
    unit_normal,
)
from lelsonar.reconstruct.estimate.surfaces.placement import echo_point, line_direction, pair_line_point, with_range
from lelsonar.reconstruct.estimate.surfaces.regions import capsule_x, find_regions, subregion
from lelsonar.reconstruct.estimate.surfaces.results import (
    OFF_FAN,
    UNSETTLED,
    Feature,
    Surface,
    SurfaceOptions,
    SurfaceSet,
)

__all__ = ["SurfaceOptions", "Surface", "Feature", "SurfaceSet", "extract_surfaces", "METHOD", "UNSETTLED"]


def _feature(
    kind: str,
    label: str,
    m: Measured,
    direction: np.ndarray,
    surfaces: tuple[str, ...],
    reasons: list[str],
    opts: SurfaceOptions,
    placed: tuple[np.ndarray, np.ndarray] | None = None,
) -> Feature:
    """``placed``: the point and its covariance where the planes it joins put it; else its own echo's point,
    off the fan by its stack slope's tilt (with one capsule, anywhere within the beam's half-width)."""
    if placed is None:
        tilt_se = m.tilt_stderr if math.isfinite(m.tilt_stderr) else opts.beyond_cut / math.sqrt(3.0)
        placed = echo_point(m.depth, m.depth_stderr, m.bearing, m.bearing_stderr, m.tilt, tilt_se)
    return Feature(
        kind=kind,
        label=label,
        point=placed[0],
        direction=direction,
        covariance=placed[1],
        bearing=m.bearing,
        depth=m.depth,
        surfaces=surfaces,
        reasons=tuple(reasons),
        steps=m.region.steps.copy(),
        n_echoes=m.region.n_echoes,
        rows=m.region.rows.copy(),
        capsules=m.region.capsules.copy(),
    )


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
    regions = find_regions(
        d,
        tolerance=opts.range_tolerance,
        max_gap=opts.max_gap,
        min_steps=opts.min_steps,
        max_spread=spread,
        gamma=g,
        radial_offset=geometry.radial_offset,
    )
    step = sweep_step(g)
    measured = [measure_region(r, g, d, amp, geometry, opts, step=step) for r in regions]
    # A region whose ends hold another target along the stack (its plane's double bounce with a surface across
    # the fan, a line across the stack at a like range): its plane's middle and those ends.
    measured = [piece for m in measured for piece in split_ends(m, g, d, amp, geometry, opts)]
    # A plane's region that runs on into its corner with a nearer plane: split where the steps tell them apart.
    split: list[Measured] = []
    for i in range(len(measured)):
        split.extend(split_dihedral(i, measured, g, d, amp, geometry, opts) or [measured[i]])
    measured = split
    # A target heard by part of the stack only, nearer than what its steps' other capsules hear (an edge off
    # the fan beside the stack: its weak echo crosses the receiver's threshold in the capsules nearest it):
    # its readings are off their step's range, so a second pass over the readings no region holds finds it.
    partial: dict[int, float] = {}  # index -> its stack slope's own σ
    for r in partial_regions(d, [m.region for m in measured], opts, spread):
        partial[len(measured)] = (pm := measure_region(r, g, d, amp, geometry, opts, step=step)).tilt_stderr
        # Heard on the beam's flank: its slope is that at the middle of the capsules heard, not the stack's.
        tilt, tilt_se = off_fan_tilt(pm, pm.tilt_stderr, opts)
        measured.append(replace(pm, tilt=tilt, tilt_stderr=tilt_se))
    regions = [m.region for m in measured]

    # The strongest echo of the sweep, range-corrected, is a mirror's or a corner's (a clipped or cut one's is
    # a lower bound of its own, so the largest is still no edge's unless the sweep saw only edges); an echo
    # far below it diffracts.  A median would not do: in a cluttered sweep most regions may be edges.
    strengths = [m.strength for m in measured if math.isfinite(m.strength)]
    mirror = max(strengths) if len(strengths) >= 2 else float("nan")
    # The beam's curvature in log amplitude, from this sweep's own regions with an unclipped peak: what puts the peak
    # of a region cut before its peak (an upper estimate of its strength, see extrapolated_peak).
    ks = [
        k
        for m in measured
        if m.exact
        for k in [log_amplitude_curvature(g[m.region.steps], m.step_amplitude)]
        if k is not None
    ]
    beam_k = float(np.median(ks)) if ks else float("nan")
    # The flattest top one echo shows in this sweep (3 σ of its regions' spread under their median, robust):
    # flatter, a second echo widens it.
    beam_low = beam_k - 3 * 1.4826 * float(np.median(np.abs(np.asarray(ks) - beam_k))) if len(ks) >= 3 else beam_k

    # The receiver clips at one level, its full scale: the sweep's largest peak.  A plateau well under it is the
    # amplitude's quantisation on a weak echo, whose peak stands.
    full_scale = max((m.peak for m in measured if math.isfinite(m.peak)), default=float("nan"))

    def upper_strength(m: Measured) -> float:
        """The region's strength if its peak is inside it, else an upper estimate of it (NaN: none)."""
        if m.peak_inside and m.clipped and m.peak >= (1.0 - PLATEAU) * full_scale:
            return float("nan")  # a clipped peak is only a lower bound of its echo: no upper estimate
        if m.peak_inside:
            return m.strength
        if not math.isfinite(beam_k):
            return float("nan")
        peak = extrapolated_peak(
            g[m.region.steps],
            m.step_amplitude,
            beam_k,
            before=opts.beyond_cut if m.region.cut_before else 0.0,
            after=opts.beyond_cut if m.region.cut_after else 0.0,
        )
        return float("nan") if peak is None else mirror_normalised(peak, m.depth, opts)

    def weak(m: Measured, ref: float = mirror) -> bool:
        top = upper_strength(m)
        return math.isfinite(ref) and math.isfinite(top) and top < opts.weak_echo * ref

    def strong(m: Measured, ref: float = mirror) -> bool:
        # The observed peak is a lower bound of the region's.
        return math.isfinite(ref) and math.isfinite(m.strength) and m.strength >= opts.weak_echo * ref

    def end_strength(m: Measured, mj: Measured, *, confirmed: bool = False) -> tuple[str, str]:
        """Whether a plane's end (or its line across the fan) echoes weakly, strongly or unknown, and why.

        Against the plane's own mirror echo (same material, a like range) where its peak is clean, else the
        sweep's strongest.  In order: the region's own peak is a lower bound (strong); where a step lies on
        the beam's top, the beam pattern taken back from its steps to the bearing the geometry puts it at (see
        peak_at_bearing) is close to the peak (strong or weak); the upper estimate from its flank's own slope
        (weak); that beam pattern taken back from farther out, a lower bound (strong).  ``confirmed``: the
        readings themselves confirm the bearing (one line explains every range), so that lower bound comes
        before the flank's slope, whose few steps' noise can put its vertex anywhere.
        """
        ref = mj.strength if mj.exact and math.isfinite(mj.strength) else mirror
        of = "its plane's mirror echo" if ref is not mirror else "the sweep's strongest"
        if not math.isfinite(ref):
            return "unknown", ""
        if strong(m, ref):
            return "strong", f"with an echo as strong as {of}"
        at = peak_at_bearing(g[m.region.steps], m.step_amplitude, m.bearing, beam_k)
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
        if weak(m, ref):
            return "weak", f"with a weak (diffracted) echo: under {of} × {opts.weak_echo:.2f}"
        if traced >= opts.weak_echo * ref:
            return "strong", strong_there
        return "unknown", ""

    # Two diffracting targets at one range side by side (a thin wall's two ends, a box's two edges) make one
    # region whose amplitude steps where one beam pattern hands over to the other: two edges, not one.
    for i in range(len(measured)):
        m = measured[i]
        # (Part of the stack hears a target off the fan on fewer steps in its farther capsules: its steps'
        # medians step where those capsules join, which is no second target.)
        if i in partial or not weak(m) or m.region.cut_before or m.region.cut_after:
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
        first, second = (measure_region(r, g, d, amp, geometry, opts, step=step) for r in pieces)
        measured[i] = first
        measured.append(second)

    across = [across_stack(m, opts) for m in measured]
    candidates = [i for i, m in enumerate(measured) if not across[i]]
    # Only planes whose bearing is determined, and whose echo is not a diffraction's, hold traces.
    # (A target only part of the stack hears is no mirror: every capsule hears a mirror's foot alike.)
    determined = [
        i
        for i in candidates
        if measured[i].bearing_source != "undetermined" and not weak(measured[i]) and i not in partial
    ]

    def in_fan() -> list[Measured]:
        """The regions every capsule hears: a target part of the stack hears lies off the fan, so it says
        nothing of how far a plane runs along its trace in the fan."""
        return [x for k, x in enumerate(measured) if k not in partial]

    def on_traces(i: int, pool: list[int]) -> list[int]:
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
            if abs(float(nj @ p) - mj.depth) <= tol and not beyond_reach(mi, mi.bearing, mj, in_fan(), opts):
                out.append(j)
        return out

    def others(i: int, pool: list[int]) -> list[int]:
        return [j for j in pool if j != i]

    # A region on another's trace, at two planes' double bounce, or at one plane's double bounce with a surface
    # across the stack is an end or a corner; once those are set aside, the ties are counted again against the
    # planes alone (a corner's own trace is no wall).
    ends = {
        i
        for i in determined
        if on_traces(i, determined)
        or pair_corner(measured[i], [measured[j] for j in others(i, determined)], opts) is not None
        or stack_dihedral(measured[i], [measured[j] for j in others(i, determined)], opts) is not None
    }
    planes = [i for i in determined if i not in ends]
    walls_of_corners = walls_of_unseen_corners(measured, planes, across, partial, g, opts)
    for i, text in walls_of_corners.items():
        measured[i] = replace(measured[i], findings=(*measured[i].findings, (DEGRADED, text)))
    kinds: dict[int, tuple[str, list[str], list[int]]] = {}
    across_lines: set[int] = set()
    for i, m in enumerate(measured):
        pool = others(i, planes)
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
            measured[i] = m = replace(
                m, bearing=pj.bearing, bearing_stderr=pj.bearing_stderr, depth=float(np.linalg.norm(foot)), tilt=tilt
            )
            # On the wall's trace across the fan: a concave corner with the floor or ceiling, or, if its echo
            # diffracts, the wall's free top or bottom edge.
            verdict, why = end_strength(m, pj, confirmed=True)
            if verdict == "weak":
                kinds[i] = ("edge", [text.replace("double bounce", "line"), why], [pool[j]])
            else:
                kinds[i] = ("corner", [text, why] if verdict == "strong" else [text, UNSETTLED], [pool[j]])
            across_lines.add(i)
            continue
        if across[i]:
            text = (
                f"ranges curve along the capsule stack (c = {m.curvature:.2f}/m ≈ 1/(2ρ) = "
                f"{1 / (2 * m.depth):.2f}/m): a line across the stack, not a plane"
            )
            kinds[i] = ("edge" if weak(m) else "corner", [text], [])
            across_lines.add(i)
            continue
        if pair is not None:
            which, bearing = pair
            ties = [pool[j] for j in which]
            # The two planes' line leans off the fan with their tilts: its echo comes from its point nearest the
            # array, off the fan by that lean, at the region's range.
            line = plane_line(measured[ties[0]], measured[ties[1]])
            lean = 0.0 if line is None else math.asin(max(-1.0, min(1.0, float(line[0][0] / np.linalg.norm(line[0])))))
            measured[i] = m = replace(
                m, bearing=bearing, bearing_stderr=pair_stderr(m, which, pool, measured), tilt=lean
            )
        elif m.bearing_source == "undetermined":
            placed = None if i in walls_of_corners else plane_end(m, [measured[j] for j in pool], opts, in_fan(), g)
            if placed is None:
                ties = []
            else:
                which, bearing = placed
                ties = [pool[j] for j in which]
                measured[i] = m = replace(m, bearing=bearing, bearing_stderr=end_stderr(m, measured[ties[0]], bearing))
        else:
            ties = on_traces(i, planes)
        if len(ties) >= 2:
            kinds[i] = (
                "corner",
                ["at the double-bounce range of the two planes it joins (their intersection)"]
                + ([unsettled] if unsettled else []),
                ties[:2],
            )
        elif len(ties) == 1:
            verdict, why = end_strength(m, measured[ties[0]])
            if verdict == "weak":
                kinds[i] = ("edge", [f"on a plane's trace off its foot, {why}"], ties)
            elif verdict == "strong":
                kinds[i] = ("corner", [f"on a plane's trace off its foot, {why}"], ties)
            else:
                kinds[i] = ("edge", [f"on a plane's trace off its foot (its end); {UNSETTLED}"], ties)
        elif weak(m):
            if m.bearing_source == "undetermined":
                measured[i] = m = replace(m, bearing_stderr=reach_stderr(m, opts))
            kinds[i] = (
                "edge",
                [
                    f"echo at most {100 * upper_strength(m) / mirror:.0f} % of the sweep's strongest at its range: "
                    "diffraction"
                ],
                [],
            )

    # A plane's bearing from its amplitude peak alone: another echo summing into its flank moves the peak as
    # much as it widens the top (:func:`summed_width_stderr`), which the parabola's residuals do not show.
    for i, m in enumerate(measured):
        if i in kinds or m.bearing_source != "amplitude peak" or m.peak >= (1.0 - PLATEAU) * full_scale:
            continue  # (a clipped top: its plateau's centre, whose width is no beam's)
        c = log_amplitude_curvature(g[m.region.steps], m.step_amplitude, plateau=True)
        extra = summed_width_stderr(c, beam_k, beam_low)
        if extra > 0:
            measured[i] = replace(m, bearing_stderr=math.hypot(m.bearing_stderr, extra))

    # A target part of the stack hears lies off the fan on the beam's flank: its echo's strength is only a lower
    # bound of its peak, so where strength set its kind (not two planes' intersection), its kind is not settled.
    for i in partial:
        if i in kinds and len(kinds[i][2]) < 2 and i not in across_lines:
            kind, reasons, ties = kinds[i]
            # Its slope along the stack says how far off the fan it lies: taken back there, still weak.
            back = None if amp is None else taken_back(measured[i], amp, partial[i], beam_k, opts)
            weak_there = "" if back is None else off_fan_weak(upper_strength(back[0]), mirror, back[1], opts)
            kinds[i] = (
                ("edge", [*reasons, weak_there], ties)
                if weak_there
                else (kind, [*reasons, f"{UNSETTLED}; {OFF_FAN}"], ties)
            )

    # The joint corner model: walls that meet at a concave corner (two ties, in the fan) fitted with it.
    pairs = [(i, ties) for i, (kind, _r, ties) in kinds.items() if kind == "corner" and len(ties) >= 2]
    pairs = [(i, ties) for i, ties in pairs if i not in across_lines]
    joint, disputed = joint_fit(pairs, measured, opts) if opts.joint_corners else ({}, {})
    for j, text in disputed.items():
        measured[j] = replace(measured[j], findings=(*measured[j].findings, (DEGRADED, text)))

    surfaces: list[Surface] = []
    label_of: dict[int, str] = {}
    surface_of: dict[int, Surface] = {}
    failed = 0
    unsorted = 0
    for i, m in enumerate(measured):
        if i in kinds:
            continue
        if i in partial:
            unsorted += m.region.n_echoes
            continue
        s = fit_surface(f"s{len(surfaces) + 1}", m, g, d, geometry, opts, joint.get(i))
        if s is None:
            failed += m.region.n_echoes
            continue
        label_of[i] = s.label
        surface_of[i] = s
        surfaces.append(s)

    def pair_placement(ia: int, ib: int, m: Measured) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """A pair corner's line from its two fitted planes: its nearest point, that point's covariance (the
        planes' full covariance through the intersection) and its direction."""
        sa, sb = surface_of.get(ia), surface_of.get(ib)
        if sa is None or sb is None:
            return None
        params = np.array([sa.bearing, sa.tilt, sa.offset, sb.bearing, sb.tilt, sb.offset])
        ja, jb = joint.get(ia), joint.get(ib)
        tied = ja is not None and jb is not None and ja.full is not None
        if ja is not None and jb is not None and ja.full is not None:
            idx = [3 * ja.index + k for k in range(3)] + [3 * jb.index + k for k in range(3)]
            cov6 = ja.full[np.ix_(idx, idx)]
        else:
            cov6 = np.zeros((6, 6))
            cov6[:3, :3], cov6[3:, 3:] = sa.covariance, sb.covariance
        line = pair_line_point(params, cov6)
        if line is None:
            return None
        point, cov = line
        if not tied:
            # The walls fitted apart: the corner's own double-bounce range is a measurement they did not use.
            point, cov = with_range(point, cov, m.depth, m.depth_stderr)
        return point, cov, line_direction(params)

    corners: list[Feature] = []
    edges: list[Feature] = []
    stack_axis = np.array([1.0, 0.0, 0.0])
    for i, (kind, reasons, ties) in sorted(kinds.items()):
        m = measured[i]
        tied = tuple(label_of[j] for j in ties if j in label_of)
        located: tuple[np.ndarray, np.ndarray] | None = None
        if i in across_lines:
            direction = np.cross(stack_axis, unit_normal(m.bearing))
        elif len(ties) >= 2:
            pair_line = pair_placement(ties[0], ties[1], m)
            if pair_line is not None:
                located, direction = (pair_line[0], pair_line[1]), pair_line[2]
            else:
                a, b = measured[ties[0]], measured[ties[1]]
                direction = np.cross(unit_normal(a.bearing, a.tilt), unit_normal(b.bearing, b.tilt))
        elif len(ties) == 1:
            # A plane's end: a line in that plane, square to the ray to its nearest point (where it answers).
            pj = measured[ties[0]]
            direction = np.cross(unit_normal(pj.bearing, pj.tilt), unit_normal(m.bearing, m.tilt))
            if float(np.linalg.norm(direction)) < math.sin(opts.foot_separation):
                direction = stack_axis
        else:
            direction = stack_axis  # along the stack: a line the fan crosses
        direction = direction / max(float(np.linalg.norm(direction)), 1e-12)
        if direction[int(np.argmax(np.abs(direction)))] < 0:
            direction = -direction
        out = corners if kind == "corner" else edges
        out.append(_feature(kind, f"{kind[0]}{len(out) + 1}", m, direction, tied, reasons, opts, located))

    valid = np.isfinite(d)
    in_region = np.zeros_like(valid)
    in_run = np.zeros(g.size, dtype=bool)
    for r in regions:
        in_region[r.rows, r.capsules] = True
        in_run[r.steps] = True
    n_valid = int(np.count_nonzero(valid))
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
    return SurfaceSet(
        surfaces=tuple(surfaces),
        corners=tuple(corners),
        edges=tuple(edges),
        n_echoes=n_valid,
        unexplained=unexplained,
    )


def good_surfaces(result: SurfaceSet) -> tuple[Surface, ...]:
    """The surfaces whose verdict is good."""
    return tuple(s for s in result.surfaces if s.quality == GOOD)
