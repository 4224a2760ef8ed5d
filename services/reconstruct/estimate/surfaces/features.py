"""Corners and edges as features: each where its planes or its own echo put it, along its line.

A concave corner of two fitted planes lies on their line, with their covariance (:mod:`.placement`), where its
own echoes admit that line (:func:`pair_denied`): else where its own echo comes from.  Any other corner or edge
lies where its own echo comes from, off the fan by its stack slope's tilt.  An end set on one plane's trace at its
range because its own bearing is undetermined has no bearing of its own: the trace picks one of the bearings its
region's reach allows, and its σ spans that reach (:func:`~.evidence.reach_stderr`); one with a bearing of its own
weighs it with the trace's, its σ grown where the two disagree.  Its direction: along the
two planes' line, along its one plane across the ray to it (that plane's end), across the fan for a line across
the stack, else along the stack.  Where its own echoes deny what placed it (:mod:`.feature_kinds`), it lies where
its own echo comes from, and its kind, which rested on that placement, is not settled.  Its σ holds what its
evidence leaves open: a pair corner's grows where its own range and its line's disagree past both σ; a line
across the fan at its plane's foot takes the turn in the plane its tilt allows; a bearing of its own echo spans
its region's reach where that echo goes on past an end or sums another's (:mod:`.own_bearing`); a concave corner
tied to one plane spans, along that plane's trace, how far past its range an opening off a right angle may put
its line (:func:`~.placement.opening_spread`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import replace

import numpy as np

from lelsonar.reconstruct.estimate.normals import cross3
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import bearing_from_amplitude, vertex_at_curvature
from lelsonar.reconstruct.estimate.surfaces.evidence import end_stderr, in_fan_range, reach_stderr, wrap
from lelsonar.reconstruct.estimate.surfaces.feature_kinds import (
    ALIKE,
    DOUBLE_BOUNCE_HEADROOM,
    NOT_ITS_END,
    NOT_THEIR_LINE,
    falls_toward,
    like_its_mirror,
    pair_denied,
)
from lelsonar.reconstruct.estimate.surfaces.joint import JointWall
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, unit_normal
from lelsonar.reconstruct.estimate.surfaces.own_bearing import continued_ends, peak_past_fade
from lelsonar.reconstruct.estimate.surfaces.placement import (
    RANGE_FLOOR,
    echo_point,
    line_direction,
    line_yaw_stderr,
    opening_spread,
    pair_line_point,
    with_range,
)
from lelsonar.reconstruct.estimate.surfaces.results import UNSETTLED, Feature, Surface, SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.stack import stack_tilt
from lelsonar.reconstruct.estimate.surfaces.strength import EchoScale

__all__ = [
    "Kind",
    "cut_peak",
    "place_features",
    "pair_denied",
    "DOUBLE_BOUNCE_HEADROOM",
    "TRACE_ONLY",
    "NOT_THEIR_LINE",
    "MIXED",
    "STACK_MIXED",
    "PLACEMENT_CAVEATS",
    "placement_caveats",
    "kind_unsettled",
    "NOT_ITS_END",
    "ALIKE",
    "like_its_mirror",
    "falls_toward",
    "centre_off_peak",
    "OPENING_OPEN",
]

#: A classified region: its kind ("corner" or "edge"), why, and the regions (indices) it ties to.
Kind = tuple[str, list[str], list[int]]

#: In the reasons of an end set on a plane's trace because its own bearing is undetermined.
TRACE_ONLY = (
    "bearing not its own: set where its plane's trace reaches its range, one of the bearings its region's reach "
    "allows; its σ spans that reach"
)

#: In the reasons of a line across the fan whose readings scatter past a region's steadiness.
MIXED = (
    "not placed on that line: its ranges scatter {sigma:.0f} mm about a free slope along the stack, more than "
    "the {tol:.0f} mm one target's region holds to, so it holds more than one target; where its own echo puts "
    "it, its bearing anywhere its region's reach allows"
)

#: In the reasons of a line across the fan placed at its plane's foot whose turn in the plane its tilt leaves open.
YAW_OPEN = (
    "at its plane's foot, its line's turn in the plane known only through its cosine (its range and tilt): "
    "within their σ the line's point may lie {turn:.1f}° off the foot, in its bearing's σ"
)

#: In the reasons of a feature placed by its own echo whose ranges along the stack no one target explains.
STACK_MIXED = (
    "its ranges along the capsule stack scatter {sigma:.1f} mm about any one target's, more than one reading's "
    "noise, with or without any one capsule: off the fan anywhere within the beam's half-width"
)

#: In the reasons of a concave corner tied to one plane: the opening its other wall makes with it unknown.
OPENING_OPEN = "one wall tied, the other not: the opening is unknown"

#: What the reasons of a feature placed without evidence of its own bearing, or off the line its class names, start
#: with: a reader shows them beside its σ.
PLACEMENT_CAVEATS = (NOT_THEIR_LINE, TRACE_ONLY, MIXED.split(":")[0], NOT_ITS_END, ALIKE, YAW_OPEN.split(",")[0])


def kind_unsettled(reasons: Iterable[str]) -> bool:
    """Whether the reasons (a :class:`Feature`'s, or its wire message's) say its kind is not settled."""
    return any(UNSETTLED in r for r in reasons)


def placement_caveats(reasons: Iterable[str]) -> list[str]:
    """The reasons (a :class:`Feature`'s, or its wire message's) that say it is not placed on its own line."""
    return [r for r in reasons if r.startswith(PLACEMENT_CAVEATS)]


def _feature(
    kind: str,
    label: str,
    m: Measured,
    direction: np.ndarray,
    surfaces: tuple[str, ...],
    reasons: list[str],
    opts: SurfaceOptions,
    placed: tuple[np.ndarray, np.ndarray] | None = None,
    spread: np.ndarray | None = None,
) -> Feature:
    """``placed``: the point and its covariance where the planes it joins put it; else its own echo's point,
    off the fan by its stack slope's tilt (with one capsule, anywhere within the beam's half-width; a slope no
    target within the beam gives, past ``beyond_cut`` off the fan, says nothing of where it lies: in the fan,
    anywhere within that half-width).  ``spread``: a second moment about that point to add to its covariance
    (where the line may lie past it, :func:`~.placement.opening_spread`)."""
    if placed is None:
        tilt, tilt_se = m.tilt, m.tilt_stderr
        if not abs(tilt) <= opts.beyond_cut:
            tilt, tilt_se = 0.0, float("nan")
        if not math.isfinite(tilt_se):
            tilt_se = opts.beyond_cut / math.sqrt(3.0)
        placed = echo_point(m.depth, m.depth_stderr, m.bearing, m.surface_bearing_stderr, tilt, tilt_se)
    if spread is not None:
        placed = placed[0], placed[1] + spread
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


def _own_tilt(m: Measured) -> tuple[Measured, str]:
    """A target placed by its own echo, off the fan and at the range its squared ranges along the stack put it
    (:func:`~.stack.stack_tilt`: any one target's, with the capsules that hear it); the reason to add ("": none).

    Each kept reading's squared range less ``b x + κ x²`` is the squared range ``d₀²`` from its capsule's point
    moved to the stack's centre, ``q``; the target ``X = ρ u`` is at ``|X − q| = d₀`` from there, so
    ``ρ = q·u + √(d₀² − |q|² + (q·u)²)``, exact for a point, a line or a plane (where the mirror condition's
    first order leaves ``x²/(2ρ)``).  Its offset along the stack ``−b/2`` gives ``sin t = −b/(2ρ)``.
    """
    r = m.region
    if r.capsules.size == 0:
        return m, ""
    x = np.zeros(int(r.capsules.max()) + 1)
    x[r.capsules] = m.positions[:, 0]
    fit = stack_tilt(x, r.rows, r.capsules, m.ranges, m.depth, RANGE_FLOOR)
    if fit is None:
        return m, ""
    b, kappa, b_se, kept, sigma, one = fit
    if not one:
        return replace(m, tilt_stderr=float("nan")), STACK_MIXED.format(sigma=1000 * sigma)
    sel = np.isin(r.capsules, kept)
    xs, d = m.positions[sel, 0], m.ranges[sel]
    q = m.positions[sel].copy()
    q[:, 0] = 0.0
    rho = m.depth
    for _ in range(2):
        sin_t = -b / (2.0 * rho)
        if not abs(sin_t) < 1.0:
            return m, ""
        u = unit_normal(m.bearing, math.asin(sin_t))
        qu = q @ u
        with np.errstate(invalid="ignore"):
            each = qu + np.sqrt(d * d - b * xs - kappa * xs * xs - np.einsum("ij,ij->i", q, q) + qu * qu)
        if not np.all(np.isfinite(each)):
            return m, ""
        rho = float(np.median(each))
    sin_t = -b / (2.0 * rho)
    if not (abs(sin_t) < 1.0 and math.isfinite(b_se)):
        return m, ""
    tilt = math.asin(sin_t)
    n_steps = np.unique(r.rows[sel]).size
    # The median's standard error (1.25 σ/√N), one capsule's readings per step counted once per step.
    depth_se = 1.2533 * float(np.std(each)) / math.sqrt(max(n_steps, 1)) if each.size > 1 else m.depth_stderr
    tilt_se = b_se / (2.0 * rho) / max(math.cos(tilt), 1e-3)
    return replace(m, depth=rho, depth_stderr=depth_se, tilt=tilt, tilt_stderr=tilt_se), ""


def _across_line(m: Measured, own: Measured, pj: Measured, fitted: Surface | None) -> tuple[Measured, str]:
    """A plane's line with a surface across the fan, placed at the plane's foot off the fan (its
    classification's), unless its own ranges along the stack deny that the line is square to the stack.

    Square to the stack (a floor below a horizontal fan), the line's point nearest the array is the plane's foot
    moved along the stack, and the region's own squared ranges along the stack (:func:`_own_tilt`, any one
    target's) say the same tilt.  A surface across the fan at another angle (a wall beside a
    vertical fan) turns the line in the plane: its nearest point is off the foot, at the same range but nearer
    the fan.  Apart by more than 3 σ of both, the point is where the region's own range and tilt meet the
    plane's trace, on the side of the foot its echo is heard (the plane's mirror echo, nearer, hides the line's
    around the foot: the line's emerges past the plane's region on its nearest point's side), with
    :func:`~.evidence.end_stderr`'s σ.  Its bearing σ is at least the fitted plane's; at the foot, it holds the
    turn the tilt's σ leaves open (:func:`~.placement.line_yaw_stderr`).

    Returns
    -------
    The region so placed, and the reason to add ("": at the foot, square to the stack).
    """
    if fitted is not None:
        fitted_se = math.sqrt(max(float(fitted.covariance[0, 0]), 0.0))
        if fitted_se > m.bearing_stderr:
            m = replace(m, bearing_stderr=fitted_se)
    own, mixed = _own_tilt(own)
    if mixed or not (math.isfinite(own.tilt) and math.isfinite(own.tilt_stderr) and math.isfinite(m.tilt)):
        return m, ""
    se = math.hypot(own.tilt_stderr, m.tilt_stderr if math.isfinite(m.tilt_stderr) else 0.0)
    if not abs(own.tilt - m.tilt) > 3.0 * se:
        turn = line_yaw_stderr(own.depth, own.depth_stderr, own.tilt, own.tilt_stderr, pj.depth, pj.depth_stderr)
        if not turn > 0:
            return m, ""
        m = replace(m, bearing_stderr=math.hypot(m.bearing_stderr, turn))
        return m, YAW_OPEN.format(turn=math.degrees(turn))
    x0 = own.depth * math.sin(own.tilt)
    h = (pj.depth - x0 * math.sin(pj.tilt)) / math.cos(pj.tilt)
    rho = in_fan_range(own)[0]
    half = math.acos(min(1.0, h / rho)) if rho > 0 else 0.0
    trace = wrap(pj.bearing + math.copysign(half, wrap(own.bearing - pj.bearing)))
    placed = replace(own, bearing=trace, bearing_stderr=m.bearing_stderr, summed_spread=0.0)
    placed = replace(placed, bearing_stderr=max(end_stderr(placed, pj, trace), m.bearing_stderr))
    return placed, (
        f"its ranges slope along the capsule stack as a target {math.degrees(own.tilt):+.1f}° off the fan, not the "
        f"{math.degrees(m.tilt):+.1f}° of a line square to the stack (3 σ: {math.degrees(3 * se):.1f}°): placed on "
        f"its plane's trace at its own range and tilt, {math.degrees(trace):.1f}°"
    )


def cut_peak(m: Measured, gamma: np.ndarray, beam_k: float) -> tuple[Measured, str]:
    """A bearing from the amplitude peak of a region cut where its echo is still at its top: the top may go on
    past the cut, so the peak lies anywhere from the fitted vertex to past the cut end (uniform, beside its σ).

    The cut end is at the top where its step's amplitude is within 3 σ of the region's largest (σ: successive
    differences' median absolute value over 0.6745·√2).  How far past it, the echo's fall across the region says:
    with the sweep's beam curvature ``k``, ``log A + k u² = P − k v² + 2 k v u`` is a line in ``u`` whose slope
    puts the vertex ``v`` (:func:`~.beam_pattern.vertex_at_curvature`); the piston falls faster than its parabola
    off the top, so its fall is the parabola's from a vertex nearer the region: ``v`` 3 σ out (its residuals' σ
    through the slope) is as far as the peak lies.

    Returns
    -------
    The region with that σ, and the reason to add ("": its peak stands).
    """
    r, a = m.region, m.step_amplitude
    if m.bearing_source != "amplitude peak" or not (r.cut_before or r.cut_after) or a.size < 3:
        return m, ""
    ok = a[np.isfinite(a)]
    if ok.size < 3:
        return m, ""
    top = float(ok.max())
    noise = float(np.median(np.abs(np.diff(ok)))) / (0.6745 * math.sqrt(2.0))
    far = vertex_at_curvature(gamma[r.steps], a, beam_k)
    widest = 0.0
    for cut, end, amp in ((r.cut_before, m.span[0], a[0]), (r.cut_after, m.span[1], a[-1])):
        if cut and math.isfinite(float(amp)) and float(amp) >= top - 3.0 * noise:
            widest = max(widest, abs(wrap(end - m.bearing)))
            if far is not None:
                bound = far[0] - far[1] if end == m.span[0] else far[0] + far[1]
                if (bound < end) if end == m.span[0] else (bound > end):
                    widest = max(widest, abs(wrap(bound - m.bearing)))
    if not widest > 0:
        return m, ""
    se = math.hypot(m.bearing_stderr, widest / math.sqrt(3.0))
    why = (
        f"its amplitude peak is at a cut end's top: the peak may lie up to {math.degrees(widest):.1f}° from the "
        "fitted vertex, toward the cut and past it as far as the beam's fall across the region allows"
    )
    return replace(m, bearing_stderr=se), why


def centre_off_peak(m: Measured, gamma: np.ndarray) -> tuple[Measured, str]:
    """A bearing from the region's centre that its own amplitude peak disputes: two measurements of one bearing
    (the ends' threshold crossings, symmetric about the target; the beam pattern's vertex) apart by more than 3 σ
    of their difference say one model does not hold (an end left while still strong, another echo at a like
    range summing in), and nothing says which: the σ covers their difference.

    Returns
    -------
    The region with that σ, and the reason to add ("": the centre stands).
    """
    if m.bearing_source != "region centre" or m.clipped:
        return m, ""
    peak = bearing_from_amplitude(gamma[m.region.steps], m.step_amplitude)
    if peak is None:
        return m, ""
    gap = abs(wrap(peak[0] - m.bearing))
    if not gap > 3.0 * math.hypot(peak[1], m.bearing_stderr):
        return m, ""
    why = (
        f"its amplitude peak ({math.degrees(peak[0]):.1f}°) lies {math.degrees(gap):.1f}° from its region's centre, "
        "beyond 3 σ of both: its bearing's σ covers their difference"
    )
    return replace(m, bearing_stderr=math.hypot(m.bearing_stderr, gap)), why


def _pair_placement(
    ia: int, ib: int, own: Measured, surface_of: dict[int, Surface], joint: dict[int, JointWall]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, str, tuple[np.ndarray, np.ndarray]] | None:
    """A pair corner's line from its two fitted planes: its nearest point, that point's covariance (the
    planes' full covariance through the intersection), its direction, the reason to add ("": none) and the
    point with the covariance it is placed with.

    The corner's own double-bounce range and the line's are two measurements of ``|X|``: apart by more than
    their σ (χ² over 1), the planes' line misses the echo's source by what neither σ says (a plane's bearing
    off by less than its verdict notices), and the point's covariance grows by χ², as a fit's whose rows
    scatter past their σ; the tests of what its own echoes admit (:func:`pair_denied`) read the line's own.
    """
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
    why = ""
    grown = cov
    rho = float(np.linalg.norm(point))
    sd = max(RANGE_FLOOR, own.depth_stderr) if math.isfinite(own.depth_stderr) else RANGE_FLOOR
    if rho > 0 and math.isfinite(own.depth):
        u = point / rho
        chi2 = (own.depth - rho) ** 2 / (max(float(u @ cov @ u), 0.0) + sd * sd)
        if chi2 > 1.0:
            grown = cov * chi2
            why = (
                f"its own range ({own.depth:.3f} m) and their line's ({rho:.3f} m) differ by "
                f"{1000 * abs(own.depth - rho):.1f} mm, {math.sqrt(chi2):.1f}× their σ: the line's σ grown by it"
            )
    placed = point, grown
    if not tied:
        # The walls fitted apart: the corner's own double-bounce range is a measurement they did not use.
        point, cov = with_range(point, cov, own.depth, own.depth_stderr)
        placed = with_range(placed[0], placed[1], own.depth, own.depth_stderr)
    return point, cov, line_direction(params), why, placed


def _with_trace(m: Measured, pj: Measured) -> tuple[Measured, str]:
    """An end with a bearing of its own, on plane ``pj``'s trace: its bearing and the trace's where it crosses the
    region's range, at the target's own offset along the stack (:func:`~.evidence.end_stderr`), two measurements
    of one bearing, weighed by their
    σ; where they disagree past those σ (χ² over 1), the σ grows as √χ², as a fit's whose rows scatter more than
    their σ: one of them is off by what neither says.

    Returns
    -------
    The region at that bearing and its σ, and the reason to add ("" where the trace does not reach its range).
    """
    # The plane where it crosses the target's own offset along the stack, x₀ = ρ sin t: n·X = h there puts its
    # trace (h − x₀ sin t_j) / cos t_j from the stack's axis.
    x0 = m.depth * math.sin(m.tilt) if math.isfinite(m.tilt) else 0.0
    h = (pj.depth - x0 * math.sin(pj.tilt)) / math.cos(pj.tilt)
    rho = in_fan_range(m)[0]
    if not rho > h:
        return m, ""
    half = math.acos(h / rho)
    # The side of the foot the region's own bearing is on.
    trace = wrap(pj.bearing + math.copysign(half, wrap(m.bearing - pj.bearing)))
    st = end_stderr(m, pj, trace)
    so = m.surface_bearing_stderr
    if not (so > 0 and st > 0 and math.isfinite(so) and math.isfinite(st)):
        return m, ""
    gap = wrap(trace - m.bearing)
    w_o, w_t = 1.0 / (so * so), 1.0 / (st * st)
    bearing = wrap(m.bearing + w_t * gap / (w_o + w_t))
    chi2 = gap * gap / (so * so + st * st)
    se = math.sqrt(max(1.0, chi2) / (w_o + w_t))
    why = (
        f"its bearing weighs its own ({math.degrees(m.bearing):.1f}° ± {math.degrees(so):.1f}°) with its plane's "
        f"trace's at its range ({math.degrees(trace):.1f}° ± {math.degrees(st):.1f}°)"
        + (f", its σ grown ×{math.sqrt(chi2):.1f} by their disagreement" if chi2 > 1 else "")
    )
    return replace(m, bearing=bearing, bearing_stderr=se, summed_spread=0.0), why


def _unseen_opening(m: Measured, own: Measured, pj: Measured, scale: EchoScale) -> tuple[np.ndarray | None, str]:
    """A concave corner tied to plane ``pj`` alone: the other wall's opening with it is unknown, so its double
    bounce's range puts its line only at or before where it lies along ``pj``'s trace
    (:func:`~.placement.opening_spread`), as far as its own bearing (``own``'s, where determined, within 3 σ of
    its and the plane's) allows.

    Returns
    -------
    The second moment to add to its covariance (None: none) and the reason to add ("": none).
    """
    rho = in_fan_range(m)[0]
    h = pj.depth / math.cos(pj.tilt)
    off_foot = math.inf
    se = math.hypot(own.surface_bearing_stderr, pj.bearing_stderr)
    if own.bearing_source != "undetermined" and math.isfinite(se):
        # 3 σ of both bearings: the foot's own moves where the trace lies.
        off_foot = abs(wrap(own.bearing - pj.bearing)) + 3.0 * se
    spread = opening_spread(rho, m.bearing, pj.bearing, h, scale.beam_k, scale.opts.weak_echo, off_foot)
    reach = math.sqrt(3.0 * max(float(np.trace(spread)), 0.0))
    if not reach > 0:
        return None, ""
    why = (
        f"{OPENING_OPEN}: its double bounce's range puts its line no nearer, and up to {100 * reach:.1f} cm "
        "farther along its plane's trace (off a right angle by as much as a corner's echo may be, within 3 σ of "
        "its own bearing); its σ spans that"
    )
    return spread, why


def _not_its_end(
    own: Measured, bearing: float, fall: float, kind: str, reasons: list[str], scale: EchoScale
) -> tuple[Measured, list[str], tuple[str, ...]]:
    """An end set on a plane's trace whose echo fades toward that placement (:func:`falls_toward`): its echo
    comes from elsewhere, so it ties no plane and lies where its own echo comes from, its bearing anywhere its
    region's reach allows.  Its kind rested on its strength taken back to that placement or on being that
    plane's end: it stands only for an echo weak wherever its peak lies (a diffraction's), else it is not
    settled.

    Returns
    -------
    The region so placed, its reasons and the planes it ties (none).
    """
    why = (
        f"{NOT_ITS_END}: its echo fades by {fall:.2f} (log amplitude, past 3 σ of its noise) toward where that "
        f"plane's trace reaches its range, {math.degrees(bearing):.1f}°, while one target's echo rises toward it"
    )
    out = [*reasons, why]
    if not (kind == "edge" and scale.weak(own)):
        out.append(f"{UNSETTLED}; its echo's source is not at its plane's end")
    return replace(own, bearing_stderr=reach_stderr(own, scale.opts)), out, ()


def place_features(
    measured: list[Measured],
    own: list[Measured],
    kinds: dict[int, Kind],
    across_lines: set[int],
    surface_of: dict[int, Surface],
    joint: dict[int, JointWall],
    scale: EchoScale,
    distance: np.ndarray | None = None,
) -> tuple[list[Feature], list[Feature]]:
    """The corners and the edges, each where its planes or its own echo put it, along its line.

    Parameters
    ----------
    measured : list of Measured
        Every region of the sweep, placed as its kind says.
    own : list of Measured
        The same regions as their own echoes measured them, before their kinds placed them.
    kinds : dict
        The kind of each region that is no plane, by index into ``measured``.
    across_lines : set of int
        The regions that are lines across the fan.
    surface_of : dict
        The fitted plane of each region that is one.
    joint : dict
        Each wall fitted with its concave corners (:func:`~.fitting.joint_fit`).
    scale : EchoScale
        The sweep's echo references (and the extractor's options).
    distance : (n_steps, n_capsules) array, optional
        The sweep's ranges: where a region's capsules go on hearing its range past an end
        (:func:`~.own_bearing.continued_ends`; without them, the other regions say).

    Returns
    -------
    corners, edges : list of Feature
        Labelled ``c1, c2, …`` and ``e1, e2, …`` in region order.
    """
    opts = scale.opts
    corners: list[Feature] = []
    edges: list[Feature] = []

    def reach(k: Measured, reasons: list[str]) -> tuple[Measured, list[str]]:
        """``k`` with the bearing σ of its region's reach, an end its echo goes on past counted as cut."""
        cont, why = continued_ends(k, own, opts.range_tolerance, distance)
        return replace(k, bearing_stderr=reach_stderr(cont, opts)), [*reasons, why] if why else reasons

    stack_axis = np.array([1.0, 0.0, 0.0])
    for i, (kind, reasons, ties) in sorted(kinds.items()):
        m = measured[i]
        tied = tuple(surface_of[j].label for j in ties if j in surface_of)
        located: tuple[np.ndarray, np.ndarray] | None = None
        spread: np.ndarray | None = None
        if i in across_lines and ties and own[i].stack_sigma > opts.range_tolerance:
            # The double bounce with a surface across the fan explains the ranges no better than a free slope
            # whose residuals scatter past a region's own steadiness: its readings hold more than one target.
            m, reasons = reach(own[i], reasons)
            m = replace(m, tilt_stderr=float("nan"))
            reasons = [*reasons, MIXED.format(sigma=1000 * own[i].stack_sigma, tol=1000 * opts.range_tolerance)]
            tied, direction = (), stack_axis
        elif i in across_lines:
            alike = like_its_mirror(m, own[i], measured[ties[0]]) if ties else ""
            if alike:
                m, reasons = reach(own[i], [*reasons, alike])
                tied = ()
            elif ties:
                m, why = _across_line(m, own[i], measured[ties[0]], surface_of.get(ties[0]))
                reasons = [*reasons, why] if why else reasons
            direction = cross3(stack_axis, unit_normal(m.bearing))
            if not ties and m.bearing_source == "undetermined":
                m, reasons = reach(m, reasons)
        elif len(ties) >= 2:
            pair_line = _pair_placement(ties[0], ties[1], own[i], surface_of, joint)
            denied = "" if pair_line is None else pair_denied(own[i], pair_line[0], pair_line[1], scale)
            if denied:
                # Where its own echo comes from: its bearing anywhere its region's reach allows.  Its kind rested
                # on being their double bounce: a strong echo elsewhere is a mirror's or another corner's.
                m, mixed = _own_tilt(own[i])
                m, reasons = reach(m, [*reasons, denied, f"{UNSETTLED}; not their double bounce"])
                reasons = [*reasons, mixed] if mixed else reasons
                tied, direction = (), stack_axis
            elif pair_line is not None:
                located, direction = pair_line[4], pair_line[2]
                reasons = [*reasons, pair_line[3]] if pair_line[3] else reasons
            else:
                a, b = measured[ties[0]], measured[ties[1]]
                direction = cross3(unit_normal(a.bearing, a.tilt), unit_normal(b.bearing, b.tilt))
        elif len(ties) == 1:
            # A plane's end: a line in that plane, square to the ray to its nearest point (where it answers).
            pj = measured[ties[0]]
            fall = 0.0
            if m.bearing_source == "undetermined":
                fall = falls_toward(scale.gamma[own[i].region.steps], own[i].step_amplitude, m.bearing)
            if fall > 0:
                m, reasons, tied = _not_its_end(own[i], m.bearing, fall, kind, reasons, scale)
            elif m.bearing_source == "undetermined":
                m, reasons = reach(m, [*reasons, TRACE_ONLY])
            else:
                m, why = _with_trace(m, pj)
                reasons = [*reasons, why] if why else reasons
            direction = cross3(unit_normal(pj.bearing, pj.tilt), unit_normal(m.bearing, m.tilt))
            if fall > 0 or float(np.linalg.norm(direction)) < math.sin(opts.foot_separation):
                direction = stack_axis
            if kind == "corner" and tied:
                spread, why = _unseen_opening(m, own[i], pj, scale)
                reasons = [*reasons, why] if why else reasons
        else:
            direction = stack_axis  # along the stack: a line the fan crosses
            m, why = _own_tilt(m)
            m, goes_on = continued_ends(m, own, opts.range_tolerance, distance)
            m, cut = cut_peak(m, scale.gamma, scale.beam_k)
            m, off = centre_off_peak(m, scale.gamma)
            m, past = peak_past_fade(m, scale.gamma, scale.beam_k)
            reasons = [*reasons, *(w for w in (why, goes_on, cut, off, past) if w)]
            if m.bearing_source == "undetermined" or goes_on or past:
                # A region split off the rest of its echo, or whose amplitudes sum another echo's, says only that
                # its target lies within its reach.
                m = replace(m, bearing_stderr=reach_stderr(m, opts))
        direction = direction / max(float(np.linalg.norm(direction)), 1e-12)
        if direction[int(np.argmax(np.abs(direction)))] < 0:
            direction = -direction
        out = corners if kind == "corner" else edges
        out.append(_feature(kind, f"{kind[0]}{len(out) + 1}", m, direction, tied, reasons, opts, located, spread))
    return corners, edges
