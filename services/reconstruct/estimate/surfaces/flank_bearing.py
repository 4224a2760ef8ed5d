"""A wall's bearing where its region of constant depth holds only one flank of its echo: its foot lies past a cut end.

A region cut by the sweep's end, with no amplitude peak inside it, has neither a centre nor a peak to give its
bearing (one cut by a nearer echo keeps it undetermined: that echo answers beside it in the amplitude window
and bends its flank where they meet).  Two measurements remain, each with its own σ:

* **the beam pattern's flank**: every echo of a rotating transceiver follows ``D(γ − β)²`` across γ, so the
  shape of the flank it shows (not only its level) places the peak it does not show.  The piston's ``ka`` comes
  from the same sweep's uncut regions (:func:`~.piston_beam.sweep_beam`);
* **the ranges across the sweep**: a mirror's range from a capsule at ``p`` is ``h − n(β, t)·p``; as the
  capsule turns about the axis at its radial offset ``r`` the range changes by ``r (1 − cos(γ − β))``, which
  places the foot of the perpendicular (:func:`range_bearing`).  With ``r`` a few cm against mm of range noise
  this is a weak measurement (the capsules move across the beam only by ``r``), never a bearing on its own
  when the flank gives one; weighed with it by their variances (Birge-scaled where they disagree).

The piston fits themselves are :func:`~.piston.piston_lm`'s: every profile of one region and its capsules in
one compiled Levenberg–Marquardt call.

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.reconstruct.estimate.quality import DEGRADED, UNRELIABLE
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import log_amplitude_noise
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, step_table, unit_normal
from lelsonar.reconstruct.estimate.surfaces.piston import Profiles, piston_lm
from lelsonar.reconstruct.estimate.surfaces.piston_beam import MODEL_MISFIT, SweepBeam, log_profile
from lelsonar.signal.directivity import PISTON_FIRST_NULL, piston_directivity

__all__ = [
    "FLANK_SOURCE",
    "across_jump_bearing",
    "end_refuted",
    "bearing_from_flank",
    "flank_bearings",
    "flank_measured",
    "flank_reach",
    "point_angles",
    "range_bearing",
]

#: The bearing source of a region placed by its flank (and its ranges).
FLANK_SOURCE = "beam flank"
#: Fewest steps with an amplitude a flank needs (two parameters, and their residuals).
MIN_FLANK_STEPS = 4


def flank_bearings(
    profiles: list[tuple[np.ndarray, np.ndarray]],
    beam: SweepBeam,
    *,
    before: float,
    after: float,
    model_check: list[bool],
    bearing_only: list[bool],
) -> list[tuple[float, float] | None]:
    """:func:`bearing_from_flank` of several profiles of one region, fitted together (:func:`~.piston.piston_lm`):
    each profile's flank, then the ``ka ± σ`` refits of those that want a σ, started at their β.

    Parameters
    ----------
    profiles : list of (γ, log A)
        Each profile's unclipped steps in γ order (``log_profile``).
    beam : SweepBeam
    before, after : float
        As :func:`bearing_from_flank`'s.
    model_check, bearing_only : list of bool
        Per profile, as :func:`bearing_from_flank`'s.

    Returns
    -------
    Per profile, ``(β, σ)`` or None, as :func:`bearing_from_flank` gives them.
    """
    out: list[tuple[float, float] | None] = [None] * len(profiles)
    if not (before > 0 or after > 0):
        return out
    rows, starts = [], []
    for i, (g, la) in enumerate(profiles):
        if g.size < MIN_FLANK_STEPS:
            continue
        step = float(np.median(np.diff(g))) if g.size > 1 else 0.0
        # Start on the side the amplitudes rise toward, just past that end.
        rising_first = la[0] > la[-1]
        if rising_first and before > 0:
            starts.append(float(g[0]) - min(before, 5 * step))
        elif not rising_first and after > 0:
            starts.append(float(g[-1]) + min(after, 5 * step))
        else:
            continue
        rows.append(i)
    if not rows:
        return out
    p = Profiles.pack([profiles[i] for i in rows])
    fit = piston_lm(p, np.array(starts), np.full(len(rows), beam.ka), free_ka=False)
    b = fit.bearing
    inside = ~np.any(p.w & (beam.ka * np.abs(np.sin(p.g - b[:, None])) >= PISTON_FIRST_NULL), axis=1)
    s2 = fit.cost / np.maximum(p.n - 2, 1)
    noise = p.noise()
    wanted = []
    for j, i in enumerate(rows):
        g = profiles[i][0]
        # On the half of the span by an end it may lie past, or past that end within the reach: the far half's
        # end faded, so the peak is not there (a peak too near a cut end for the peak fit's samples on both
        # sides still shapes the flank).
        mid = 0.5 * float(g[0] + g[-1])
        bj = float(b[j])
        if not (fit.ok[j] and inside[j]):
            continue
        if not ((before > 0 and g[0] - before <= bj <= mid) or (after > 0 and mid <= bj <= g[-1] + after)):
            continue
        # Residuals beyond the amplitudes' own noise: no one piston's flank (another echo bends it), no bearing.
        if model_check[i] and math.isfinite(noise[j]) and noise[j] > 0 and math.sqrt(s2[j]) > MODEL_MISFIT * noise[j]:
            continue
        if bearing_only[i]:
            out[i] = bj, float("nan")
            continue
        n = int(p.n[j])
        jac = fit.jacobian[j, :n]
        resid = fit.residual[j, :n]
        inv = np.linalg.pinv(jac.T @ jac)
        se = math.sqrt(max(float(s2[j] * inv[1, 1]), 0.0))
        # A step that is another target's (at the region's end, where two echoes at one range hand over) or that
        # another echo bent pulls the flank as its residual alone does not show: the jackknife over the steps
        # (each left out in turn) measures how far any one of them moves β.
        # (Each left out to first order: the fit's change is (JᵀJ)⁻¹ J_k r_k / (1 − h_kk), h the hat matrix's.)
        if n > MIN_FLANK_STEPS:
            lever = np.einsum("ij,jk,ik->i", jac, inv, jac)
            if np.all(lever < 1.0 - 1e-9):
                moved_b = (jac @ inv)[:, 1] * resid / (1.0 - lever)
                se = max(se, math.sqrt((n - 1) / n * float(np.sum((moved_b - moved_b.mean()) ** 2))))
        wanted.append((i, j, bj, se))
    if not wanted:
        return out
    # β's change with ka, over ka's σ (a secant over ±σ, the larger side): each wanted row refitted twice.
    pick = [j for _i, j, _b, _se in wanted for _ in (0, 1)]
    sub = p.rows(pick)
    kas = np.tile([beam.ka - beam.ka_stderr, beam.ka + beam.ka_stderr], len(wanted))
    other = piston_lm(sub, b[pick], kas, free_ka=False)
    for w, (i, _j, bj, se) in enumerate(wanted):
        pair = slice(2 * w, 2 * w + 2)
        if not np.all(other.ok[pair]):
            continue
        moved = float(np.max(np.abs(other.bearing[pair] - bj)))
        out[i] = bj, math.hypot(se, moved)
    return out


def bearing_from_flank(
    gamma: np.ndarray,
    amplitude: np.ndarray,
    beam: SweepBeam,
    *,
    before: float,
    after: float,
    model_check: bool = True,
    bearing_only: bool = False,
) -> tuple[float, float] | None:
    """The bearing of an echo whose region shows one flank of its beam pattern: the piston ``A = P·D(γ − β)²``
    with the sweep's ``ka``, fitted over ``(log P, β)`` in ``log A`` (:func:`piston_lm`).

    The flank's slope and its bend together place the peak: on a piston, the log amplitude falls faster the
    farther off the axis, so one flank's shape says how far off it lies.  The σ is the fit's (its residuals'
    scale, or a first-order jackknife over the steps where one step moves β more) and the change of β with
    ``ka`` over ``ka``'s own σ, added in quadrature.

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        The region's steps' γ (rad) and echo amplitudes (NaN: none).
    beam : SweepBeam
    before, after : float
        rad: how far before the first and after the last step the peak may lie (0 on a side the region's echo
        faded on, where its peak is not).
    model_check : bool
        Refuse a flank whose residuals exceed its noise (off for one capsule's flank, whose bend is what the
        capsules' spread measures).
    bearing_only : bool
        Return the bearing with a NaN σ (one capsule's flank, of which only the spread is wanted).

    Returns
    -------
    (β, σ) in rad, or None when too few steps have an amplitude, the fitted peak lies neither past an end it
    may lie past (within that reach) nor in the half of the span by that end, a step falls outside the main
    lobe, or the residuals exceed the amplitudes' own noise by more than :data:`MODEL_MISFIT` (another echo
    bends the flank).
    """
    return flank_bearings(
        [log_profile(gamma, amplitude)],
        beam,
        before=before,
        after=after,
        model_check=[model_check],
        bearing_only=[bearing_only],
    )[0]


def range_bearing(
    positions: np.ndarray, ranges: np.ndarray, bearing: float, tilt: float, depth: float, *, max_iter: int = 30
) -> tuple[float, float] | None:
    """A mirror's bearing from its ranges alone: least squares over ``(β, t, h)`` of ``d = h − n(β, t)·p``.

    As the capsule turns at its radial offset, its range to a mirror grows by ``r (1 − cos(γ − β))`` off the
    foot: a weak hold on β (mm of range change over the beam), honest only through its σ.  A reading more than
    3.5 σ (robust) off the fit is an outlier (a carrier cycle slipped) and is left out, once.

    Parameters
    ----------
    positions : (N, 3) array
        Each reading's capsule position, m.
    ranges : (N,) array
        Ranges, m.
    bearing, tilt, depth : float
        The start, rad, rad, m.

    Returns
    -------
    (β, σ) rad, σ from the covariance at the residuals' scale; None with fewer than five readings or no
    convergence.
    """
    p = np.asarray(positions, dtype=np.float64)
    d = np.asarray(ranges, dtype=np.float64)
    keep = np.isfinite(d)
    out = None
    for _round in range(2):
        pk, dk = p[keep], d[keep]
        if dk.size < 5:
            return None
        b, t, h = bearing, tilt, depth
        jac = np.empty((dk.size, 3))
        for _ in range(max_iter):
            n = unit_normal(b, t)
            dn_b = np.array([0.0, -math.cos(t) * math.sin(b), math.cos(t) * math.cos(b)])
            dn_t = np.array([math.cos(t), -math.sin(t) * math.cos(b), -math.sin(t) * math.sin(b)])
            res = pk @ n + dk - h
            jac[:, 0], jac[:, 1], jac[:, 2] = pk @ dn_b, pk @ dn_t, -1.0
            z, *_ = np.linalg.lstsq(jac, -res, rcond=None)
            b, t, h = b + float(z[0]), t + float(z[1]), h + float(z[2])
            if float(np.abs(z).max()) < 1e-12:
                break
        else:
            return None
        res = pk @ unit_normal(b, t) + dk - h
        dof = max(dk.size - 3, 1)
        s2 = float(res @ res) / dof
        out = (b, s2, np.linalg.pinv(jac.T @ jac))
        scale = 1.4826 * float(np.median(np.abs(res - np.median(res))))
        if not scale > 0:
            break
        full = p @ unit_normal(b, t) + d - h
        inlier = np.isfinite(d) & (np.abs(full - float(np.median(res))) <= 3.5 * scale)
        if np.array_equal(inlier, keep):
            break
        keep = inlier
    if out is None:
        return None
    b, s2, inv = out
    return (b + math.pi) % (2 * math.pi) - math.pi, math.sqrt(max(s2 * float(inv[0, 0]), 0.0))


def point_angles(gamma: np.ndarray, bearing: float, rho: float, radial_offset: float) -> np.ndarray:
    """Each step's angle off the beam's axis of a point target (a line across the fan seen in it: a corner, an
    edge), as ``γ' − β``: the γ at which a mirror's echo would be that far off the axis.

    A mirror's echo leaves along its normal whatever the capsule's place, so it is ``ψ = γ − β`` off the axis.
    A point's leaves toward the point from the capsule, which sits ``r`` out along its own axis:
    ``tan ψ = ρ sin(γ − β) / (ρ cos(γ − β) − r)``, steeper than a mirror's by about ``ρ / (ρ − r)``.  Fitted as
    a mirror's, a point's flank a distance ``u`` off its peak puts the peak about ``2 (r/ρ) u`` too far out.

    Parameters
    ----------
    gamma : (k,) array
        Steps' γ, rad.
    bearing, rho : float
        The point's bearing (rad) and range in the fan (m).
    radial_offset : float
        The capsules' distance from the rotation axis, m.

    Returns
    -------
    (k,) array, rad.
    """
    d = np.asarray(gamma, dtype=np.float64) - bearing
    return bearing + np.arctan2(rho * np.sin(d), rho * np.cos(d) - radial_offset)


def flank_reach(
    m: Measured, n_steps: int, n_capsules: int, beyond_cut: float, clean: tuple[bool, bool] = (False, False)
) -> tuple[float, float]:
    """How far past its first and last step (rad) the peak of an undetermined plane's region may lie, its flank
    its own echo's alone: ``beyond_cut`` on a side the sweep's own end cuts, or another echo cuts without
    reaching into the region's amplitude window (``clean``, :func:`~.measurement.clean_cuts`), else 0; (0, 0)
    when its flank cannot place it.

    An echo at a like range that cuts a region answers beside it in the same amplitude window where they meet and
    bends the flank there; past the sweep's end nothing else answers, and one much nearer answers wholly before
    the window.  A face part of the stack hears ends within the stack's height: its edge, at a like range,
    answers in the same amplitude window on every step and bends the whole flank alike in the capsules that hear
    the face.
    """
    if m.bearing_source != "undetermined":
        return 0.0, 0.0
    if np.median(np.bincount(np.searchsorted(m.region.steps, m.region.rows))) < n_capsules:
        return 0.0, 0.0
    first, last = int(m.region.steps[0]), int(m.region.steps[-1])
    return (
        beyond_cut if m.region.cut_before and (first == 0 or clean[0]) else 0.0,
        beyond_cut if m.region.cut_after and (last == n_steps - 1 or clean[1]) else 0.0,
    )


def flank_measured(
    m: Measured,
    gamma: np.ndarray,
    amplitude: np.ndarray,
    beam: SweepBeam | None,
    beyond_cut: float,
    reach: tuple[float, float] | None = None,
) -> Measured:
    """A plane's region whose bearing its centre and peak leave undetermined, placed by its flank and ranges.

    The flank's bearing (:func:`bearing_from_flank`, its peak past the sweep's own end by up to ``beyond_cut``) and the
    ranges' (:func:`range_bearing`, started there) weigh by their inverse variances, the σ scaled by their
    difference in σ of it where that exceeds 1 (the Birge ratio).  Another echo summed into the amplitude window
    bends the flank smoothly, which the fit's residuals do not show, and bends each capsule's flank its own way
    (their paths differ by wavelengths): the capsules' own flank bearings' spread (standard deviation) is part
    of the flank's σ.  Without a flank bearing the region stays as it
    is: the ranges alone do not hold a wall's bearing.  The depth follows the new normal.  The verdict: usable,
    not good (the beam's shape carries the bearing, and another echo summed into the flank bends it unseen).

    Returns
    -------
    The region with that bearing, its σ, source :data:`FLANK_SOURCE` and its findings (unchanged when the flank
    gives none, or when part of the capsule stack hears the region on most of its steps).
    """
    if reach is None:
        reach = flank_reach(m, gamma.size, amplitude.shape[1], beyond_cut)
    if beam is None or reach == (0.0, 0.0):
        return m
    g = gamma[m.region.steps]
    table = step_table(m.region, amplitude)
    profiles = [log_profile(g, m.step_amplitude)] + [log_profile(g, table[:, c]) for c in range(table.shape[1])]
    # The region's median profile, then each capsule's (their bearings only, for their spread).
    n = table.shape[1]
    out = flank_bearings(
        profiles,
        beam,
        before=reach[0],
        after=reach[1],
        model_check=[True] + [False] * n,
        bearing_only=[False] + [True] * n,
    )
    flank = out[0]
    if flank is None:
        return m
    own = [f[0] for f in out[1:] if f is not None]
    spread = float(np.std(own, ddof=1)) if len(own) >= 2 else 0.0
    flank = (flank[0], math.hypot(flank[1], spread))
    bearing, sb = flank
    ranged = range_bearing(m.positions, m.ranges, bearing, m.tilt, m.depth)
    note = ""
    if ranged is not None and ranged[1] > 0 and sb > 0:
        wf, wr = 1.0 / sb**2, 1.0 / ranged[1] ** 2
        gap = (ranged[0] - bearing + math.pi) % (2 * math.pi) - math.pi
        apart = abs(gap) / math.hypot(sb, ranged[1])
        bearing, sb = bearing + wr * gap / (wf + wr), max(1.0, apart) / math.sqrt(wf + wr)
        note = f", weighed with its ranges' ({math.degrees(ranged[1]):.1f}°)"
    h_i = m.ranges + m.positions @ unit_normal(bearing, m.tilt)
    depth = float(np.median(h_i))
    depth_se = 1.2533 * float(np.std(h_i)) / math.sqrt(max(m.region.steps.size, 1)) if h_i.size > 1 else m.depth_stderr
    side = "both" if m.region.cut_before and m.region.cut_after else "one"
    findings = tuple(f for f in m.findings if not (f[0] == UNRELIABLE and f[1].startswith("bearing not determined")))
    findings += (
        (
            DEGRADED,
            f"bearing from the beam pattern's flank alone (±{math.degrees(flank[1]):.1f}°{note}): the region of "
            f"constant depth is cut on {side} side{'s' if side == 'both' else ''} and its peak lies past the cut, "
            "so the beam's shape places the wall",
        ),
    )
    return replace(
        m,
        bearing=(bearing + math.pi) % (2 * math.pi) - math.pi,
        bearing_stderr=sb,
        bearing_source=FLANK_SOURCE,
        findings=findings,
        depth=depth,
        depth_stderr=depth_se,
    )


def end_refuted(
    m: Measured,
    gamma: np.ndarray,
    beam: SweepBeam,
    end_bearing: float,
    end_se: float,
    rho: float,
    reach: tuple[float, float],
) -> tuple[float, float, float] | None:
    """Whether a region's own beam flank refutes an end placed at ``end_bearing``: how many σ of their difference
    its flank's peak lies from where it peaks were it that end.

    An end's echo (a concave corner's retro-reflection, an edge's diffraction) follows the beam pattern about the
    end's bearing across the sweep: the array turns about its own axis, so the view of the end changes only by the
    capsules' parallax (:func:`point_angles`).  Fitted in the point's own angles off the axis, its flank peaks at
    the end's bearing; a mirror's flank, fitted in ``γ − β``, peaks at its foot.  Both fits are
    :func:`bearing_from_flank`'s, with their residuals held to the amplitudes' noise: a flank another echo bends
    past its noise refutes nothing.

    Parameters
    ----------
    m : Measured
        The region as its own echoes measured it (its steps' amplitudes, positions, range).
    gamma : (n_steps,) array
        The sweep's γ, rad.
    beam : SweepBeam
        The sweep's piston.
    end_bearing, end_se : float
        rad: where the end lies on its plane's trace and that placement's σ.
    rho : float
        m: the end's range in the fan.
    reach : (float, float)
        rad: how far past its first and last step the region's peak may lie.

    Returns
    -------
    (σ apart, the flank's bearing as a mirror's, its σ), or None when either flank fit gives nothing.
    """
    g = gamma[m.region.steps]
    mirror = bearing_from_flank(g, m.step_amplitude, beam, before=reach[0], after=reach[1])
    if mirror is None or not (math.isfinite(mirror[1]) and mirror[1] > 0):
        return None
    radial = float(np.median(np.hypot(m.positions[:, 1], m.positions[:, 2])))
    if not rho > radial:
        return None
    point = bearing_from_flank(
        point_angles(g, end_bearing, rho, radial), m.step_amplitude, beam, before=reach[0], after=reach[1]
    )
    if point is None or not math.isfinite(point[1]):
        return None
    gap = abs((point[0] - end_bearing + math.pi) % (2 * math.pi) - math.pi)
    return gap / math.hypot(point[1], end_se), mirror[0], mirror[1]


#: rad: the grid :func:`across_jump_bearing` first scans its bearings on.
JUMP_GRID = math.radians(0.25)


def across_jump_bearing(
    profiles: list[tuple[np.ndarray, np.ndarray]], beam: SweepBeam, lo: float, hi: float
) -> tuple[float, float] | None:
    """One bearing for the profiles of two echoes at one range whose amplitude hands over from one to the other:
    the piston ``log A = log P_i + log D(γ − β)²`` with the sweep's ``ka``, one level per profile and one β.

    A mirror whose foot lies where its face ends hands over there to the diffraction of that end, at one range:
    an end on the plane at the plane's own depth lies at its foot (``cos δ = h/ρ``), so both echoes follow the
    beam pattern about one bearing, each at its own strength.  The mirror's side alone is one flank whose peak
    lies past its cut; the end's side alone is a weak echo; together their shapes place the one bearing.  The
    fit is least squares over the bearings in ``[lo, hi]`` (a scan on :data:`JUMP_GRID`, then a parabola through
    the best three), with the levels solved at each; its σ from the cost's curvature at the residuals' scale
    (``σ² = 2 s² / S''``) and the change of β with ``ka`` over ``ka``'s own σ, in quadrature.

    Parameters
    ----------
    profiles : list of (γ, log A)
        Each echo's unclipped steps (``log_profile``).
    beam : SweepBeam
    lo, hi : float
        rad: the bearings the fit may take (a peak its steps hold, not one past them).

    Returns
    -------
    (β, σ) rad, or None: too few steps, the best bearing on the edge of ``[lo, hi]``, a step outside the main
    lobe there, or residuals over :data:`~.piston_beam.MODEL_MISFIT` times the amplitudes' own noise (the two
    do not share one bearing).
    """
    pieces = [(np.asarray(g, dtype=np.float64), np.asarray(la, dtype=np.float64)) for g, la in profiles]
    if len(pieces) < 2 or any(g.size < MIN_FLANK_STEPS for g, _la in pieces) or not hi > lo:
        return None
    grid = np.arange(lo, hi + 0.5 * JUMP_GRID, JUMP_GRID)

    def costs(bearings: np.ndarray, ka: float) -> np.ndarray:
        total = np.zeros(bearings.size)
        for g, la in pieces:
            x = ka * np.sin(g[None, :] - bearings[:, None])
            with np.errstate(divide="ignore", invalid="ignore"):
                model = 2.0 * np.log(np.abs(piston_directivity(g[None, :] - bearings[:, None], ka)))
            r = la[None, :] - model
            r = r - r.mean(axis=1, keepdims=True)  # each echo's own level
            total += np.where(np.all(np.abs(x) < PISTON_FIRST_NULL, axis=1), np.sum(r * r, axis=1), np.inf)
        return total

    def best(ka: float) -> tuple[float, float, float] | None:
        s = costs(grid, ka)
        k = int(np.argmin(s))
        if not (0 < k < grid.size - 1 and np.all(np.isfinite(s[k - 1 : k + 2]))):
            return None
        curv = (s[k + 1] - 2.0 * s[k] + s[k - 1]) / JUMP_GRID**2
        if not curv > 0:
            return None
        b = float(grid[k]) - (s[k + 1] - s[k - 1]) / (2.0 * JUMP_GRID * curv)
        return b, float(costs(np.array([b]), ka)[0]), curv

    fit = best(beam.ka)
    if fit is None:
        return None
    b, cost, curv = fit
    n = sum(g.size for g, _la in pieces)
    s2 = cost / max(n - 1 - len(pieces), 1)
    noise = [log_amplitude_noise(la) for _g, la in pieces if la.size >= 5]
    floor = max(noise, default=0.0)
    if floor > 0 and math.sqrt(s2) > MODEL_MISFIT * floor:
        return None
    moved = 0.0
    for ka in (beam.ka - beam.ka_stderr, beam.ka + beam.ka_stderr):
        other = best(ka) if ka > 0 else None
        if other is None:
            return None
        moved = max(moved, abs(other[0] - b))
    return b, math.hypot(math.sqrt(2.0 * s2 / curv), moved)
