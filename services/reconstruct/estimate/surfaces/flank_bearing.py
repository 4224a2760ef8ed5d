"""A wall's bearing where its region of constant depth holds only one flank of its echo: its foot lies past a cut end.

A region cut by the sweep's end, with no amplitude peak inside it, has neither a centre nor a peak to give its
bearing (one cut by a nearer echo keeps it undetermined: that echo answers beside it in the amplitude window
and bends its flank where they meet).  Two measurements remain, each with its own σ:

* **the beam pattern's flank**: every echo of a rotating transceiver follows ``D(γ − β)²`` across γ, so the
  shape of the flank it shows (not only its level) places the peak it does not show.  The piston's ``ka`` comes
  from the same sweep's uncut regions (:func:`sweep_beam`), fitted with the piston over their whole profiles:
  a parabola fitted over a top alone overstates ``ka`` by a few %, which on a far flank is degrees;
* **the ranges across the sweep**: a mirror's range from a capsule at ``p`` is ``h − n(β, t)·p``; as the
  capsule turns about the axis at its radial offset ``r`` the range changes by ``r (1 − cos(γ − β))``, which
  places the foot of the perpendicular (:func:`range_bearing`).  With ``r`` a few cm against mm of range noise
  this is a weak measurement (the capsules move across the beam only by ``r``), never a bearing on its own
  when the flank gives one; weighed with it by their variances (Birge-scaled where they disagree).

A region whose amplitude hands over from one target to another at one range (a box's face and its own edge)
holds one flank of each: :func:`split_jump` cuts it there.

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import special
from scipy.optimize import least_squares

from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.quality import DEGRADED, UNRELIABLE
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import PLATEAU, amplitude_jump
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, measure_region, step_table, unit_normal
from lelsonar.reconstruct.estimate.surfaces.regions import subregion
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions
from lelsonar.signal.directivity import PISTON_FIRST_NULL, piston_directivity

__all__ = [
    "FLANK_SOURCE",
    "SweepBeam",
    "bearing_from_flank",
    "flank_measured",
    "piston_fit",
    "range_bearing",
    "split_jump",
    "sweep_beam",
]

#: The bearing source of a region placed by its flank (and its ranges).
FLANK_SOURCE = "beam flank"
#: Fewest steps with an amplitude a piston fit of a whole profile needs (three parameters, and their residuals).
MIN_PROFILE_STEPS = 8
#: Fewest steps with an amplitude a flank needs (two parameters, and their residuals).
MIN_FLANK_STEPS = 4
#: Fewest second differences a robust noise estimate takes.
MIN_NOISE_DIFFERENCES = 5
#: How far under its peak a profile is fitted, in log amplitude: 20 dB, clear of the first null and sidelobe.
MAIN_LOBE_TOP = math.log(10.0)
#: A profile's residual σ over its amplitude noise beyond which the piston does not describe the beam.
MODEL_MISFIT = 3.0


@dataclass(frozen=True)
class SweepBeam:
    """The sweep's beam as a piston: ``ka`` and its σ, from its uncut regions' amplitude profiles."""

    ka: float
    ka_stderr: float
    n_regions: int


def _log_profile(gamma: np.ndarray, amplitude: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The steps with an unclipped echo, in γ order: γ and ``log A`` (a plateau of three or more steps at the
    region's largest value is the receiver clipping: those steps are lower bounds and are left out)."""
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if ok.any():
        top = a >= (1.0 - PLATEAU) * float(np.max(a[ok]))
        if np.count_nonzero(top & ok) >= 3:
            ok &= ~top
    g, la = g[ok], np.log(a[ok])
    order = np.argsort(g)
    return g[order], la[order]


def _log_piston(u: np.ndarray, ka: float) -> np.ndarray:
    """``log D(u)²`` of a piston, ``-inf`` at its nulls."""
    with np.errstate(divide="ignore"):
        return 2.0 * np.log(np.abs(piston_directivity(u, ka)))


def _log_piston_slopes(u: np.ndarray, ka: float) -> tuple[np.ndarray, np.ndarray]:
    """``∂ log D(u)² / ∂u`` and ``/ ∂ka``: with ``x = ka·sin u``, ``d log(2J1(x)/x)/dx = J0(x)/J1(x) − 2/x``
    (``−x/4`` as ``x → 0``)."""
    x = ka * np.sin(u)
    small = np.abs(x) < 1e-6
    safe = np.where(small, 1.0, x)
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = np.where(small, -x / 4.0, special.j0(safe) / special.j1(safe) - 2.0 / safe)
    return 2.0 * dx * ka * np.cos(u), 2.0 * dx * np.sin(u)


def _noise(la: np.ndarray) -> float:
    """The log amplitudes' noise σ, robust, from second differences (variance 6 σ² for white noise); NaN from
    fewer than :data:`MIN_NOISE_DIFFERENCES` of them (the median absolute deviation of a few is near 0 by
    chance)."""
    second = np.diff(la, 2)
    if second.size < MIN_NOISE_DIFFERENCES:
        return float("nan")
    return 1.4826 * float(np.median(np.abs(second - np.median(second)))) / math.sqrt(6.0)


def piston_fit(gamma: np.ndarray, amplitude: np.ndarray, bearing: float, ka0: float) -> tuple[float, float] | None:
    """``ka`` of the piston whose two-way pattern ``A = P·D(γ − β)²`` fits one whole echo profile, and its σ.

    Least squares in ``log A`` over ``(log P, β, ka)``, from the region's bearing and a first ``ka``, over the
    steps within 20 dB of the region's peak (:data:`MAIN_LOBE_TOP`).

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        An uncut region's steps' γ (rad) and echo amplitudes (NaN: none).
    bearing : float
        The region's bearing, rad (its centre or its peak).
    ka0 : float
        A first guess of ``ka``.

    Returns
    -------
    (ka, σ), or None when too few steps have an amplitude, the fit leaves the main lobe, or its residuals
    exceed the amplitudes' own noise by more than :data:`MODEL_MISFIT` (no piston).
    """
    g, la = _log_profile(gamma, amplitude)
    # The main lobe's top, within 20 dB of the peak: a strong near echo stays over the receiver's threshold
    # into the nulls and the first sidelobe (35 dB down, two-way), where no smooth lobe describes it.
    top = la >= float(la.max()) - MAIN_LOBE_TOP if g.size else np.zeros(0, dtype=bool)
    g, la = g[top], la[top]
    if g.size < MIN_PROFILE_STEPS or not ka0 > 0:
        return None

    def res(p: np.ndarray) -> np.ndarray:
        return p[0] + _log_piston(g - p[1], p[2]) - la

    def jacobian(p: np.ndarray) -> np.ndarray:
        du, dka = _log_piston_slopes(g - p[1], p[2])
        return np.stack([np.ones_like(g), -du, dka], axis=1)

    start = np.array([float(la.max()), bearing, ka0])
    if not np.all(np.isfinite(res(start))):
        return None
    fit = least_squares(res, start, jac=jacobian, method="lm")
    if not fit.success or not np.all(np.isfinite(fit.fun)):
        return None
    c, b, ka = (float(v) for v in fit.x)
    if not ka > 0 or np.any(ka * np.abs(np.sin(g - b)) >= PISTON_FIRST_NULL):
        return None
    dof = g.size - 3
    s2 = float(fit.fun @ fit.fun) / dof
    noise = _noise(la)
    if math.isfinite(noise) and noise > 0 and math.sqrt(s2) > MODEL_MISFIT * noise:
        return None
    cov = s2 * np.linalg.pinv(fit.jac.T @ fit.jac)
    return ka, math.sqrt(max(float(cov[2, 2]), 0.0))


def sweep_beam(measured: list[Measured], gamma: np.ndarray, amplitude: np.ndarray, ka0: float) -> SweepBeam | None:
    """The sweep's piston ``ka``, from its planes' regions that hold their echo's peak and the profile about it:
    their bearing their centre or their peak (a clipped top left out), one beam pattern (no amplitude jump).
    A mirror's echo follows the beam alone; a corner's or an edge's adds its own change with the angle, so only
    planes are passed.

    Each region's steps' median profile gives its ``ka``; each capsule's own profile gives one too.  Another echo
    summed into the amplitude window (a wall's double bounce with the floor, a few mm deeper) bends a profile
    smoothly, which its residuals do not show, and it adds with a phase that differs from capsule to capsule
    (their paths differ by wavelengths): the capsules' ``ka`` spread by as much as the summing bends them.

    Parameters
    ----------
    measured : list of Measured
        The sweep's planes.
    gamma : (n_steps,) array
        The sweep's γ, rad.
    amplitude : (n_steps, n_capsules) array
        The sweep's echo amplitudes, V (NaN: none).
    ka0 : float
        A first guess (``2√k`` of the sweep's beam curvature ``k``).

    Returns
    -------
    The median of the regions' ``ka``; its σ the largest of the capsules' spread (standard deviation over every
    region's capsules, not shrunk by their count: a bent profile is biased, not noisy), the regions' spread and
    the median of their own fits' σ.  None when no region gives one.
    """
    kas, ses, capsules = [], [], []
    for m in measured:
        if m.bearing_source not in ("region centre", "amplitude peak"):
            continue
        g = gamma[m.region.steps]
        if amplitude_jump(g, m.step_amplitude) is not None:
            continue
        fit = piston_fit(g, m.step_amplitude, m.bearing, ka0)
        if fit is None:
            continue
        kas.append(fit[0])
        ses.append(fit[1])
        table = step_table(m.region, amplitude)
        for c in range(table.shape[1]):
            own = piston_fit(g, table[:, c], m.bearing, fit[0])
            if own is not None:
                capsules.append(own[0])
    if not kas:
        return None
    spread = max(
        float(np.std(kas, ddof=1)) if len(kas) >= 2 else 0.0,
        float(np.std(capsules, ddof=1)) if len(capsules) >= 2 else 0.0,
    )
    return SweepBeam(ka=float(np.median(kas)), ka_stderr=max(spread, float(np.median(ses))), n_regions=len(kas))


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
    with the sweep's ``ka``, fitted over ``(log P, β)`` in ``log A``.

    The flank's slope and its bend together place the peak: on a piston, the log amplitude falls faster the
    farther off the axis, so one flank's shape says how far off it lies.  The σ is the fit's (its residuals'
    scale) and the change of β with ``ka`` over ``ka``'s own σ, added in quadrature.

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
    g, la = _log_profile(gamma, amplitude)
    if g.size < MIN_FLANK_STEPS or not (before > 0 or after > 0):
        return None
    step = float(np.median(np.diff(g))) if g.size > 1 else 0.0

    def fit(ka: float, b0: float) -> tuple[float, float, np.ndarray, np.ndarray] | None:
        def res(p: np.ndarray) -> np.ndarray:
            return p[0] + _log_piston(g - p[1], ka) - la

        def jacobian(p: np.ndarray) -> np.ndarray:
            return np.stack([np.ones_like(g), -_log_piston_slopes(g - p[1], ka)[0]], axis=1)

        start = np.array([float(la.max()), b0])
        if not np.all(np.isfinite(res(start))):
            return None
        out = least_squares(res, start, jac=jacobian, method="lm")
        if not out.success or not np.all(np.isfinite(out.fun)):
            return None
        return float(out.x[0]), float(out.x[1]), out.fun, out.jac

    # Start on the side the amplitudes rise toward, just past that end.
    rising_first = la[0] > la[-1]
    if rising_first and before > 0:
        b0 = float(g[0]) - min(before, 5 * step)
    elif not rising_first and after > 0:
        b0 = float(g[-1]) + min(after, 5 * step)
    else:
        return None
    best = fit(beam.ka, b0)
    if best is None:
        return None
    _, b, resid, jac = best
    if np.any(beam.ka * np.abs(np.sin(g - b)) >= PISTON_FIRST_NULL):
        return None
    # On the half of the span by an end it may lie past, or past that end within the reach: the far half's end
    # faded, so the peak is not there (a peak too near a cut end for the peak fit's samples on both sides
    # still shapes the flank).
    mid = 0.5 * float(g[0] + g[-1])
    if not ((before > 0 and g[0] - before <= b <= mid) or (after > 0 and mid <= b <= g[-1] + after)):
        return None
    s2 = float(resid @ resid) / max(g.size - 2, 1)
    # Residuals beyond the amplitudes' own noise: no one piston's flank (another echo bends it), no bearing.
    noise = _noise(la)
    if model_check and math.isfinite(noise) and noise > 0 and math.sqrt(s2) > MODEL_MISFIT * noise:
        return None
    if bearing_only:
        return b, float("nan")
    cov = s2 * np.linalg.pinv(jac.T @ jac)
    se = math.sqrt(max(float(cov[1, 1]), 0.0))
    # A step that is another target's (at the region's end, where two echoes at one range hand over) or that
    # another echo bent pulls the flank as its residual alone does not show: the jackknife over the steps
    # (each left out in turn) measures how far any one of them moves β.
    # (Each left out to first order: the fit's change is (JᵀJ)⁻¹ J_k r_k / (1 − h_kk), h the hat matrix's.)
    if g.size > MIN_FLANK_STEPS:
        inv = np.linalg.pinv(jac.T @ jac)
        lever = np.einsum("ij,jk,ik->i", jac, inv, jac)
        if np.all(lever < 1.0 - 1e-9):
            moved_b = (jac @ inv)[:, 1] * resid / (1.0 - lever)
            se = max(se, math.sqrt((g.size - 1) / g.size * float(np.sum((moved_b - moved_b.mean()) ** 2))))
    # β's change with ka, over ka's σ (a secant over ±σ, the larger side).
    moved = 0.0
    for sign in (-1.0, 1.0):
        other = fit(beam.ka + sign * beam.ka_stderr, b)
        if other is None:
            return None
        moved = max(moved, abs(other[1] - b))
    return b, math.hypot(se, moved)


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


def flank_reach(m: Measured, n_steps: int, n_capsules: int, beyond_cut: float) -> tuple[float, float]:
    """How far past the sweep's first and last step (rad) the peak of an undetermined plane's region may lie:
    ``beyond_cut`` on a side the sweep's own end cuts, else 0; (0, 0) when its flank cannot place it.

    Only past the sweep's own ends: a nearer echo that cuts a region answers beside it in the same amplitude
    window where they meet and bends the flank there; past the sweep's end nothing else answers.  A face part of
    the stack hears ends within the stack's height: its edge, at a like range, answers in the same amplitude
    window on every step and bends the whole flank alike in the capsules that hear the face.
    """
    if m.bearing_source != "undetermined":
        return 0.0, 0.0
    if np.median(np.bincount(np.searchsorted(m.region.steps, m.region.rows))) < n_capsules:
        return 0.0, 0.0
    first, last = int(m.region.steps[0]), int(m.region.steps[-1])
    return (
        beyond_cut if m.region.cut_before and first == 0 else 0.0,
        beyond_cut if m.region.cut_after and last == n_steps - 1 else 0.0,
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
    flank = bearing_from_flank(g, m.step_amplitude, beam, before=reach[0], after=reach[1])
    if flank is None:
        return m
    table = step_table(m.region, amplitude)
    own = [
        f[0]
        for c in range(table.shape[1])
        for f in [
            bearing_from_flank(
                g, table[:, c], beam, before=reach[0], after=reach[1], model_check=False, bearing_only=True
            )
        ]
        if f is not None
    ]
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


def split_jump(
    m: Measured,
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
) -> list[Measured] | None:
    """A region whose echo amplitude steps as no one beam pattern does: two targets at one range, one taking
    over from the other (:func:`~.beam_pattern.amplitude_jump`), such as a box's face and its own convex edge
    beyond the face's end.  Split at the jump, each piece cut on the jump's side (the other target's echo ends
    it there), when each keeps ``min_steps``.

    Returns
    -------
    The two pieces in sweep order, or None (no jump, a cut region, or a piece too short).
    """
    r = m.region
    if amplitude is None or r.cut_before or r.cut_after:
        return None
    g = gamma[r.steps]
    jump = amplitude_jump(g, m.step_amplitude)
    if jump is None:
        return None
    k = int(np.searchsorted(g, jump[0])) if g[-1] > g[0] else 0
    if not opts.min_steps <= k <= r.steps.size - opts.min_steps:
        return None
    pieces = (subregion(r, r.steps[:k], False, True), subregion(r, r.steps[k:], True, False))
    why = (
        DEGRADED,
        f"two echoes at one range: the echo amplitude steps at γ {math.degrees(jump[0]):.1f}° as no one beam "
        "pattern does, so the region is split there and each part is cut where the other's echo takes over",
    )
    out = [measure_region(p, gamma, distance, amplitude, geometry, opts, step=m.step) for p in pieces]
    return [replace(x, findings=(*x.findings, why)) for x in out]
