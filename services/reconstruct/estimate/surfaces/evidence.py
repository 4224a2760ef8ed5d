"""The physical tests that tell a plane, a corner and an edge apart, on measured regions.

Each test reads :class:`~lelsonar.reconstruct.estimate.surfaces.measurement.Measured` regions:

* :func:`pair_corner`: the double bounce of two planes (range ``|X|`` of their intersection);
* :func:`stack_dihedral`: the double bounce of a plane with a surface across the fan (a floor or a
  ceiling), where the range and the stack slope must agree;
* :func:`plane_end`: a region on one plane's trace, off its foot: that plane's end;
* :func:`walls_of_unseen_corners`: two regions on one plane's trace explained by a wall and its corner
  with that plane, not by the plane's end.
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Iterator

import numpy as np

from lelsonar.reconstruct.estimate.normals import cross3
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import weaker_at
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, unit_normal
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions

__all__ = [
    "across_stack",
    "bend_of_one_target",
    "beyond_reach",
    "feature_point",
    "in_fan_range",
    "heard_from_every_step",
    "in_span",
    "pair_corner",
    "pair_stderr",
    "end_stderr",
    "reach_stderr",
    "plane_end",
    "plane_ends",
    "plane_line",
    "stack_dihedral",
    "stack_or_pair",
    "unseen_corner",
    "walls_of_unseen_corners",
    "wrap",
]


def across_stack(m: Measured, opts: SurfaceOptions) -> bool:
    """Ranges curved along the stack as a line or point across it (``c ≈ 1/(2ρ)``), not as a plane (``c = 0``),
    and bent as one target's (:func:`bend_of_one_target`)."""
    c, sc = m.curvature, m.curvature_stderr
    if not (math.isfinite(c) and math.isfinite(sc) and sc > 0):
        return False
    expected = 1.0 / (2.0 * m.depth)
    if not (c > opts.curvature_sigmas * sc and abs(c - expected) < max(0.5 * expected, 3 * sc)):
        return False
    return bend_of_one_target(m) <= opts.curvature_sigmas


def bend_of_one_target(m: Measured) -> float:
    """How far, in σ, a region's ranges along the capsule stack bend as no one target's do (0: as one's).

    Whatever one target is, a capsule at ``x`` along the stack hears it at ``d² = a + b x + κ x²`` (:mod:`.stack`:
    ``κ = n_x²`` for a plane, ``1 − u_x²`` for a line, 1 for a point), so its squared ranges bend alike at every
    capsule.  A face that ends between the capsules does not: those whose foot falls on it hear its mirror, a
    straight profile, and those past its end hear the end's edge, a hyperbola tangent to it, so the profile is
    straight on one side and curved by ``1/ρ`` on the other; fitted with one curvature, it curves about half as a
    line across the stack does.  The squared ranges' profile with a free offset per capsule against one
    quadratic, both with one intercept per step, differ by more than that free profile's residual noise allows
    where one target does not explain the readings: ``χ²`` over the ``n_capsules − 3`` constraints, as a normal
    deviate (exact for one constraint, Wilson–Hilferty's beyond).

    Returns
    -------
    The deviate, σ (0 where fewer than four capsules hear the region or the readings leave no freedom).
    """
    x = m.positions[:, 0]
    xs = np.unique(x)
    q = xs.size - 3
    if q < 1 or not m.depth > 0:
        return 0.0
    group = np.unique(m.region.rows, return_inverse=True)[1]
    counts = np.bincount(group)
    dof = x.size - counts.size - (xs.size - 1)
    if dof < 1:
        return 0.0

    def demeaned(v: np.ndarray) -> np.ndarray:
        return v - (np.bincount(group, weights=v) / counts)[group]

    # In metres (≈ the range itself): the constant scale leaves a quadratic in x a quadratic.
    y = demeaned(m.ranges * m.ranges / (2.0 * m.depth))
    which = np.searchsorted(xs, x)
    free = np.stack([demeaned((which == k).astype(np.float64)) for k in range(1, xs.size)], axis=1)
    one = np.stack([demeaned(x), demeaned(x * x)], axis=1)

    def rss(cols: np.ndarray) -> float:
        coef, *_ = np.linalg.lstsq(cols, y, rcond=None)
        r = y - cols @ coef
        return float(r @ r)

    rss_free = rss(free)
    if not rss_free > 0:
        return 0.0
    chi2 = max(rss(one) - rss_free, 0.0) / (rss_free / dof)
    if q == 1:
        return math.sqrt(chi2)
    k = 2.0 / (9.0 * q)
    return ((chi2 / q) ** (1.0 / 3.0) - (1.0 - k)) / math.sqrt(k)


def feature_point(m: Measured) -> np.ndarray:
    return m.depth * unit_normal(m.bearing)


def in_span(bearing: float, m: Measured, margin: float, beyond_cut: float) -> bool:
    """``bearing`` within the region's span of γ; on a cut side the target may lie up to ``beyond_cut`` past it, and
    no farther than that from the far end (:func:`heard_from_every_step`)."""
    g0, g1 = m.span
    lo = g0 - margin - (beyond_cut if m.region.cut_before else 0.0)
    hi = g1 + margin + (beyond_cut if m.region.cut_after else 0.0)
    return lo <= bearing <= hi and heard_from_every_step(bearing, m, beyond_cut)


def heard_from_every_step(bearing: float, m: Measured, reach: float) -> bool:
    """``bearing`` within ``reach`` of both ends of the region's span of γ.

    Each reading is an echo its step's beam heard, so its target lies within the beam's half-width (``reach``) of
    that step's axis, both ends of the region included: a target past it from the far end is another target at a
    like range (the same two walls' mirror image across the array, in a corridor's middle).
    """
    return all(abs(wrap(bearing - end)) <= reach for end in m.span)


def plane_line(a: Measured, b: Measured) -> tuple[np.ndarray, np.ndarray] | None:
    """The line where two planes meet, with their tilts: its point nearest the array and its direction
    (read-only arrays).

    Returns None for planes nearly parallel (no corner): ``|n_a × n_b| < 0.2``.
    """
    # The classification asks for the same pairs of planes over and over: the line is a function of the six
    # numbers alone, remembered by their bits (so -0.0 and 0.0 stay apart).
    return _plane_line(_LINE_KEY.pack(a.bearing, a.tilt, a.depth, b.bearing, b.tilt, b.depth))


_LINE_KEY = struct.Struct("<6d")


@functools.lru_cache(maxsize=4096)
def _plane_line(key: bytes) -> tuple[np.ndarray, np.ndarray] | None:
    bearing_a, tilt_a, depth_a, bearing_b, tilt_b, depth_b = _LINE_KEY.unpack(key)
    na, nb = unit_normal(bearing_a, tilt_a), unit_normal(bearing_b, tilt_b)
    direction = cross3(na, nb)
    size = float(np.linalg.norm(direction))
    if size < 0.2:
        return None
    # The least-norm solution of n_a·X = h_a, n_b·X = h_b is the line's point nearest the origin.
    mat = np.stack([na, nb])
    x = mat.T @ np.linalg.solve(mat @ mat.T, np.array([depth_a, depth_b]))
    unit = direction / size
    x.flags.writeable = False
    unit.flags.writeable = False
    return x, unit


def pair_corner(m: Measured, planes: list[Measured], opts: SurfaceOptions) -> tuple[list[int], float] | None:
    """Two planes whose double bounce this region is: a concave corner.

    A corner's echo comes from the line ``X`` where its two walls meet, at the double-bounce range
    ``|X|`` (the retro-reflection in the plane normal to the edge; ``X`` its point nearest the array)
    and the bearing of ``X`` in the fan, which must fall within the region's span of γ (past a cut
    end, within ``beyond_cut``, and no farther than that from both its ends: :func:`in_span`).  The planes'
    tilts place the line: a wall the fan meets off square leans it out of the fan.

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
    """The first of :func:`plane_ends` (the planes in order, the side nearer the region's own steps first), or
    None."""
    return next(plane_ends(m, planes, opts, seen, gamma), None)


def plane_ends(
    m: Measured,
    planes: list[Measured],
    opts: SurfaceOptions,
    seen: list[Measured] | None = None,
    gamma: np.ndarray | None = None,
) -> Iterator[tuple[list[int], float]]:
    """Where a region whose own bearing is not determined may sit on a plane's trace: that plane's end.

    The end lies on the trace at the region's depth, at ``β_j ± acos(h_j/ρ)``, within the region's span of γ;
    it is placed at the region's range in the fan (:func:`in_fan_range`) on that side.
    Off the foot by less than ``foot_separation`` it is still no part of the plane when it is deeper than the
    plane by more than ``range_tolerance``: a mirror's echoes all lie at its one depth.  With ``seen`` (every
    region of the sweep), no bearing the plane cannot reach (:func:`beyond_reach`).  With ``gamma`` (the
    sweep's), no bearing inside the region where its own echo is weaker than elsewhere in it
    (:func:`~.beam_pattern.weaker_at`): a target there would be its region's strongest echo.

    Yields
    ------
    ([index into ``planes``], bearing), every placement the region allows: the planes in order, on each the
    side nearer the region's own steps first.
    """
    for j, pj in enumerate(planes):
        # The plane's trace in the fan: a tilted plane crosses it at h / cos(tilt).
        h = pj.depth / math.cos(pj.tilt)
        if h >= m.depth:
            continue
        half = math.acos(h / m.depth)
        if half <= opts.foot_separation and m.depth - h <= opts.range_tolerance:
            continue
        # Where on the trace: at the region's range in the fan (its target off the fan by its tilt).
        rho = in_fan_range(m)[0]
        there = math.acos(h / rho) if rho > h else 0.0
        # Either side of the foot may fall within the reach past a cut end: the side nearer the region's own
        # steps first (its echo is heard there, the other side only through the beam's far flank).
        sides = sorted((wrap(pj.bearing - half), wrap(pj.bearing + half)), key=lambda b: _off_span(b, m))
        for bearing in sides:
            if (
                in_span(bearing, m, m.step, opts.beyond_cut)
                and not (seen is not None and beyond_reach(m, bearing, pj, seen, opts, placed=True))
                and not (gamma is not None and weaker_at(gamma[m.region.steps], m.step_amplitude, bearing))
            ):
                yield [j], wrap(pj.bearing + math.copysign(there, wrap(bearing - pj.bearing)))


def _off_span(bearing: float, m: Measured) -> float:
    """How far ``bearing`` lies outside the region's span of γ (0 inside), rad."""
    return max(0.0, m.span[0] - bearing, bearing - m.span[1])


def unseen_corner(mi: Measured, mk: Measured, pj: Measured, opts: SurfaceOptions) -> float | None:
    """A bearing for the plane of region ``mi`` whose concave corner with plane ``pj`` is region ``mk``: the two
    regions' echoes explained together, ``mi`` a wall's mirror and ``mk`` its corner.

    A mirror answers at its foot, at its depth ``h_i``; two walls meet on the line where ``n_i·X = h_i`` and
    ``n_j·X = h_j`` (its range ``|X|``, the double bounce of :func:`pair_corner`).  For a concave corner seen
    from inside, ``X`` lies between the two feet in the fan.  Where some bearing ``β_i`` within ``mi``'s reach
    puts that line at ``mk``'s depth (within ``on_trace``) and at a bearing within ``mk``'s reach, both regions
    are explained by one wall and its corner with ``pj``; ``mk`` is cut on ``mi``'s side: the wall's nearer
    mirror masks its corner where both answer.

    ``mi``'s reach is its span, or past a cut end by up to ``beyond_cut``, whatever bearing it has of its own:
    a bearing left open says nothing of where in its span the foot lies (a flank bent or cut short shows no
    peak even near a cut end), and an amplitude peak says nothing for certain where the corner's echo,
    answering inside the amplitude window beside the region, sums into it.  ``|X| = h_i / cos(β_X − β_i)``,
    with ``β_X`` on ``pj``'s trace at ``mk``'s depth, fixes ``β_i`` to within what ``on_trace`` allows: the
    reach tests it.

    Returns
    -------
    That ``β_i`` (the one nearest ``mi``'s span), rad, or None.
    """
    if not (mk.span[0] > mi.span[1] and mk.region.cut_before) and not (mk.span[1] < mi.span[0] and mk.region.cut_after):
        return None
    lo = mi.span[0] - (opts.beyond_cut if mi.region.cut_before else 0.0)
    hi = mi.span[1] + (opts.beyond_cut if mi.region.cut_after else 0.0)
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


def in_fan_range(m: Measured) -> tuple[float, float]:
    """A region's range in the fan, ``ρ cos t`` (its target off the fan by its tilt ``t``, the stack slope's),
    and its σ: a plane's trace lies in the fan, so an end on it is there at that range, not at ``ρ``."""
    sr = m.depth_stderr if math.isfinite(m.depth_stderr) else 0.0
    if not (math.isfinite(m.tilt) and math.isfinite(m.tilt_stderr)):
        return m.depth, sr
    c, s = math.cos(m.tilt), math.sin(m.tilt)
    return m.depth * c, math.hypot(sr * c, m.depth * s * m.tilt_stderr)


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
    rho, sr = in_fan_range(m)
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


def on_the_way(o: Measured, mi: Measured, mk: Measured, opts: SurfaceOptions) -> bool:
    """Whether region ``o``, between a wall's mirror ``mi`` and its corner ``mk`` in the sweep, may lie on that
    wall's trace between its foot and the corner: its depth within theirs (``range_tolerance`` either side).

    The wall's trace runs from its foot at ``h_i`` to the corner at ``|X|``, its range ``h_i / cos(β − β_i)``
    growing monotonically between: whatever the wall holds there (its own line with a floor or a ceiling, a
    mark on it) answers within those ranges.  A target nearer than the foot would hide the corner; one deeper
    than the corner lies behind the wall.  (A plane's own foot between them is a wall of its own: the caller
    sets those apart.)
    """
    return mi.depth - opts.range_tolerance <= o.depth <= mk.depth + opts.range_tolerance


def walls_of_unseen_corners(
    measured: list[Measured],
    planes: list[int],
    across: list[bool],
    partial: set[int],
    gamma: np.ndarray,
    opts: SurfaceOptions,
) -> dict[int, str]:
    """Regions without a bearing that are a wall's own mirror, its corner with a plane the deeper region beside it.

    Where two such regions fit one plane's trace on one side, both cannot be its end (a mirror answers at its
    foot only, so a point of the trace short of its end echoes nothing).  The nearer one is a wall's mirror
    when a bearing within its reach (its span, or past a cut end) makes that wall's corner with the plane the
    deeper one (:func:`unseen_corner`): one wall and its corner explain both.  So too a nearer region whose own
    bearing ties it to no two planes' double bounce, only to a plane's trace.  Returns those regions, each with
    the finding that says so.  A target only ``partial`` capsules hear is no mirror, and says nothing of a
    plane's trace in the fan.
    """
    open_ = [
        i for i, m in enumerate(measured) if m.bearing_source == "undetermined" and not across[i] and i not in partial
    ]
    held = [measured[j] for j in planes]
    placed = [
        i
        for i, m in enumerate(measured)
        if m.bearing_source != "undetermined"
        and i not in planes
        and not across[i]
        and i not in partial
        and pair_corner(m, held, opts) is None
        and stack_dihedral(m, held, opts) is None
    ]
    in_fan = [m for i, m in enumerate(measured) if i not in partial]
    out: dict[int, str] = {}
    for k in open_:
        mk = measured[k]
        for j in planes:
            pj = measured[j]
            if plane_end(mk, [pj], opts, in_fan, gamma) is None:
                continue
            for i in open_ + placed:
                mi = measured[i]
                if i == k or i in out or not mi.depth < mk.depth - opts.range_tolerance:
                    continue
                # Beside each other in the sweep: nothing between their spans but what may lie on the wall's trace
                # between its foot and its corner (no plane's own foot: a line of the wall across the fan).
                lo, hi = min(mi.span[1], mk.span[1]), max(mi.span[0], mk.span[0])
                if any(
                    lo < o.span[0] and o.span[1] < hi and (n in planes or not on_the_way(o, mi, mk, opts))
                    for n, o in enumerate(measured)
                ):
                    continue
                if unseen_corner(mi, mk, pj, opts) is not None:
                    out[i] = (
                        f"a wall at {mi.depth:.2f} m whose corner with the plane at {pj.depth:.2f} m is the echo "
                        f"{mk.depth:.2f} m away beside it: not that plane's end"
                    )
    return out
