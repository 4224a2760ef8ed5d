"""A surface's plane from its region's echoes: on its own, or tied to the concave corners it shares (:mod:`.joint`)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.fit import make_plane_fit, plane_data_of
from lelsonar.reconstruct.estimate.quality import DEGRADED, UNRELIABLE, assess_plane
from lelsonar.reconstruct.estimate.results import PlaneFit, SolverDiagnostics
from lelsonar.reconstruct.estimate.robust import median
from lelsonar.reconstruct.estimate.surfaces.evidence import (
    bend_of_one_target,
    heard_from_every_step,
    plane_line,
    wrap,
)
from lelsonar.reconstruct.estimate.surfaces.joint import CornerEvidence, JointWall, WallEvidence, joint_walls
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, reading_positions, unit_normal
from lelsonar.reconstruct.estimate.surfaces.placement import RANGE_FLOOR
from lelsonar.reconstruct.estimate.surfaces.results import Surface, SurfaceOptions

__all__ = ["METHOD", "bent_as_two_targets", "curved_as_a_line", "fit_surface", "joint_fit", "place_own_mirrors"]

#: The method name the surfaces' plane fits carry.
METHOD = "rcd"


def fit_surface(
    label: str,
    m: Measured,
    gamma: np.ndarray,
    distance: np.ndarray,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
    joint: JointWall | None = None,
) -> Surface | None:
    """A region's plane; ``joint``: its wall as the joint corner model fitted it (bearing, tilt, offset, σ)."""
    r = m.region
    caps = reading_positions(geometry, gamma, r.rows, r.capsules)
    d = distance[r.rows, r.capsules]
    beam = np.stack([np.zeros(r.rows.size), np.cos(gamma[r.rows]), np.sin(gamma[r.rows])], axis=1)
    if joint is not None:
        return _joint_surface(label, m, joint, caps, beam, d, gamma, opts)
    n = unit_normal(m.bearing, m.tilt)
    h_i = d + caps @ n
    h = median(h_i)
    resid = h_i - h
    sigma = float(np.std(resid, ddof=1)) if resid.size > 1 else float("nan")
    # How h moves with the bearing and the tilt (the capsules' own offsets along n), for the covariance.
    dn_db = np.array([0.0, -math.cos(m.tilt) * math.sin(m.bearing), math.cos(m.tilt) * math.cos(m.bearing)])
    dn_dt = np.array(
        [math.cos(m.tilt), -math.sin(m.tilt) * math.cos(m.bearing), -math.sin(m.tilt) * math.sin(m.bearing)]
    )
    jac = np.array([float(np.mean(caps @ dn_db)), float(np.mean(caps @ dn_dt))])
    tilt_var = m.tilt_stderr**2 if math.isfinite(m.tilt_stderr) else (math.pi / 2) ** 2
    ang = np.diag([m.surface_bearing_stderr**2, tilt_var])
    var_h = (sigma**2 / max(r.rows.size, 1) if math.isfinite(sigma) else 0.0) + float(jac @ ang @ jac)
    cov = np.zeros((3, 3))
    cov[:2, :2] = ang
    cov[2, :2] = cov[:2, 2] = ang @ jac
    cov[2, 2] = var_h
    findings = list(m.findings)
    if not math.isfinite(m.tilt_stderr):
        findings.append((DEGRADED, "tilt not determined: one capsule per step"))
    curved = curved_as_a_line(m) or bent_as_two_targets(m, opts.curvature_sigmas)
    if curved:
        findings.append((DEGRADED, curved))
    data = plane_data_of(caps[:, None, :], beam, d[:, None], r.rows, "a", n)
    fit = make_plane_fit(
        data,
        n / h,
        method=METHOD,
        inlier_mask=np.ones(data.n, dtype=bool),
        diagnostics=SolverDiagnostics(solver=METHOD, notes=(f"bearing: {m.bearing_source}",)),
        model="constant-depth",
        stderr=(math.sqrt(m.surface_bearing_stderr**2 + tilt_var), math.sqrt(var_h)),
        theta_covariance=None if math.isfinite(m.tilt_stderr) else theta_covariance(n, h, dn_db, dn_dt, cov),
    )
    if not isinstance(fit, PlaneFit):
        return None
    fit = assess_plane(fit, gamma, findings=tuple(findings), limits=opts.limits)
    return Surface(
        label=label,
        plane=fit,
        bearing=m.bearing,
        tilt=m.tilt,
        covariance=cov,
        bearing_source=m.bearing_source,
        steps=r.steps.copy(),
        n_echoes=r.n_echoes,
        rows=r.rows.copy(),
        capsules=r.capsules.copy(),
    )


def curved_as_a_line(m: Measured) -> str:
    """Why a region's ranges along the capsule stack say it may be a line across the stack, not a plane ("": they
    do not).

    A plane's ranges are linear in the capsule's offset ``x`` along the stack (curvature ``c = 0``); a line across
    the stack (a wall's junction with a floor or a ceiling) answers from its nearest point to each capsule,
    ``√(ρ² + x²)``, curved by ``c = 1/(2ρ)``.  Far away the two differ by less than a region tells at the
    classification's bar: where ``c`` lies beyond 3 σ of a plane's and within 3 σ of a line's, the evidence favours
    the line, and a plane fitted to its echoes leans to its slope and stands off the wall by ``ρ t²`` in the fan.
    """
    c, sc = m.curvature, m.curvature_stderr
    if not (math.isfinite(c) and math.isfinite(sc) and sc > 0 and m.depth > 0):
        return ""
    line = 1.0 / (2.0 * m.depth)
    if not (c > 3.0 * sc and abs(c - line) <= 3.0 * sc):
        return ""
    return (
        f"its ranges curve along the capsule stack (c = {c:.3f} ± {sc:.3f}/m), beyond 3 σ of a plane's straight "
        f"profile and within 3 σ of a line across the stack's (1/(2ρ) = {line:.3f}/m): it may be a line there"
    )


def bent_as_two_targets(m: Measured, sigmas: float) -> str:
    """Why a plane's region holds more than its plane along the capsule stack ("": it does not).

    A face that ends between the capsules is heard as a mirror by those whose foot falls on it and as its end's
    edge by the rest (:func:`~.evidence.bend_of_one_target`): the region's slope along the stack, so the plane's
    tilt, and its centre, so its bearing, mix the face with its end.
    """
    bend = bend_of_one_target(m)
    if not bend > sigmas:
        return ""
    return (
        f"its ranges bend along the capsule stack as no one target's ({bend:.1f} σ): a face that ends between the "
        "capsules, those past its end hearing its edge, so its tilt and bearing mix the face with its end"
    )


def place_own_mirrors(measured: list[Measured], others: set[int], reach: float) -> None:
    """Each plane's region without a bearing of its own that is another plane's own mirror, placed at that plane's
    bearing (in ``measured``; ``others``: the regions that are no plane).

    A mirror answers from its foot at its depth to every step whose beam reaches the foot (``reach``): a region
    past a nearer echo that cuts the plane's own, at that plane's depth and tilt (within 3 σ of both, the depth's at
    least the range noise's) and within reach of its foot, is that plane's echo, its foot where the plane's is (the
    best placed of those that match, and only better than the region's own span places it).
    """
    planes = [m for i, m in enumerate(measured) if i not in others and m.bearing_source != "undetermined"]
    for i, m in enumerate(measured):
        if i in others or m.bearing_source != "undetermined":
            continue
        best: tuple[float, Measured] | None = None
        for p in planes:
            depth_se = max(math.hypot(m.depth_stderr, p.depth_stderr), RANGE_FLOOR)
            tilt_se = math.hypot(m.tilt_stderr, p.tilt_stderr)
            miss = abs(m.depth - p.depth) / depth_se
            if (
                miss <= 3.0
                and p.surface_bearing_stderr < m.bearing_stderr
                and abs(m.tilt - p.tilt) <= 3.0 * tilt_se
                and heard_from_every_step(p.bearing, m, reach)
                and (best is None or p.surface_bearing_stderr < best[0])
            ):
                best = (p.surface_bearing_stderr, p)
        if best is not None:
            measured[i] = _at_its_planes_foot(m, best[1])


def _at_its_planes_foot(m: Measured, p: Measured) -> Measured:
    n = unit_normal(p.bearing, m.tilt)
    findings = tuple(f for f in m.findings if not (f[0] == UNRELIABLE and f[1].startswith("bearing not determined")))
    why = (
        f"bearing its plane's ({math.degrees(p.bearing):.1f}°): at that plane's depth and tilt within reach of its "
        "foot, its own mirror past a nearer echo"
    )
    return replace(
        m,
        bearing=p.bearing,
        bearing_stderr=p.bearing_stderr,
        bearing_source=p.bearing_source,
        depth=median(m.ranges + m.positions @ n),
        findings=(*findings, (DEGRADED, why)),
    )


def theta_covariance(n: np.ndarray, h: float, dn_db: np.ndarray, dn_dt: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """The covariance of ``θ = n/h`` (eq. 1) from that of (bearing, tilt, offset), to first order.

    Where the capsule stack does not constrain the tilt (one capsule per step), the ranges alone leave ``θ``
    undetermined along it; the surface's own error model (the tilt unknown to ±π/2) still bounds it.

    Parameters
    ----------
    n : (3,) array
        The unit normal at (bearing, tilt).
    h : float
        The offset, m.
    dn_db, dn_dt : (3,) arrays
        ``∂n/∂β`` and ``∂n/∂t``.
    cov : (3, 3) array
        Over (bearing rad, tilt rad, offset m).

    Returns
    -------
    (3, 3) array, 1/m².
    """
    jac = np.stack([dn_db / h, dn_dt / h, -n / (h * h)], axis=1)
    out = jac @ cov @ jac.T
    return 0.5 * (out + out.T)


def _joint_surface(
    label: str,
    m: Measured,
    joint: JointWall,
    caps: np.ndarray,
    beam: np.ndarray,
    d: np.ndarray,
    gamma: np.ndarray,
    opts: SurfaceOptions,
) -> Surface | None:
    n = unit_normal(joint.bearing, joint.tilt)
    cov = joint.covariance
    data = plane_data_of(caps[:, None, :], beam, d[:, None], m.region.rows, "a", n)
    fit = make_plane_fit(
        data,
        n / joint.offset,
        method=METHOD,
        inlier_mask=np.ones(data.n, dtype=bool),
        diagnostics=SolverDiagnostics(
            solver=METHOD, notes=(f"bearing: {m.bearing_source}", "joint corner model: tied to its corners")
        ),
        model="constant-depth",
        stderr=(math.sqrt(max(cov[0, 0] + cov[1, 1], 0.0)), math.sqrt(max(cov[2, 2], 0.0))),
    )
    if not isinstance(fit, PlaneFit):
        return None
    curved = curved_as_a_line(m) or bent_as_two_targets(m, opts.curvature_sigmas)
    findings = (*m.findings, (DEGRADED, curved)) if curved else m.findings
    fit = assess_plane(fit, gamma, findings=findings, limits=opts.limits)
    return Surface(
        label=label,
        plane=fit,
        bearing=joint.bearing,
        tilt=joint.tilt,
        covariance=cov.copy(),
        bearing_source=m.bearing_source,
        steps=m.region.steps.copy(),
        n_echoes=m.region.n_echoes,
        rows=m.region.rows.copy(),
        capsules=m.region.capsules.copy(),
    )


def _scatter(residuals: np.ndarray) -> float:
    """A robust σ of residuals (1.4826 MAD), the standard deviation where the MAD is 0, m."""
    if residuals.size < 2:
        return float("nan")
    mad = 1.4826 * median(np.abs(residuals - median(residuals)))
    return mad if mad > 0 else float(np.std(residuals, ddof=1))


def joint_fit(
    pairs: list[tuple[int, list[int]]], measured: list[Measured], opts: SurfaceOptions
) -> tuple[dict[int, JointWall], dict[int, str]]:
    """The walls joined at concave corners, fitted with their corners (:func:`.joint.joint_walls`).

    Returns the joint walls by region, and the regions whose beam-pattern bearing the corners dispute (more
    than 3 σ apart): those keep their own fit, and say so.  What pulled a disputed wall off its own bearing
    pulled the walls tied to it too, so the rest are fitted again without it and the corners it joins, until
    the corners dispute none of those left.
    """
    disputed: dict[int, str] = {}
    left = list(pairs)
    while True:
        fitted = _joint_round(left, measured, opts.beyond_cut)
        if fitted is None:
            return {}, disputed
        out: dict[int, JointWall] = {}
        new: dict[int, str] = {}
        for j, jw in fitted.items():
            mj = measured[j]
            gap = abs(wrap(jw.bearing - mj.bearing))
            if gap > 3 * mj.surface_bearing_stderr:
                new[j] = (
                    f"its corners' double bounce puts its bearing {math.degrees(gap):.1f}° from the beam pattern's "
                    f"(σ {math.degrees(mj.surface_bearing_stderr):.1f}°): fitted on its own echoes"
                )
            else:
                out[j] = jw
        if not new:
            return out, disputed
        disputed.update(new)
        left = [(i, ties) for i, ties in left if not set(ties[:2]) & set(new)]


def _heard(corner: Measured, a: Measured, b: Measured, reach: float) -> bool:
    """Whether the line where planes ``a`` and ``b`` meet lies within ``reach`` of every step of the corner's region
    (:func:`~.evidence.heard_from_every_step`)."""
    line = plane_line(a, b)
    if line is None:
        return False
    return heard_from_every_step(math.atan2(float(line[0][2]), float(line[0][1])), corner, reach)


def _joint_round(
    pairs: list[tuple[int, list[int]]], measured: list[Measured], reach: float
) -> dict[int, JointWall] | None:
    """One joint fit of the walls ``pairs`` ties (:func:`.joint.joint_walls`), by region; None: nothing to fit, or
    the fit failed.  ``reach``: rad, how far off a step's axis its beam hears a target (about the beam's
    half-width): a corner ties its walls only where every step of its region could hear their line."""
    pairs = [(i, ties) for i, ties in pairs if _heard(measured[i], measured[ties[0]], measured[ties[1]], reach)]
    walls = sorted({j for _, ties in pairs for j in ties[:2]})
    if not pairs or len(walls) < 2:
        return None
    index = {j: k for k, j in enumerate(walls)}
    evidence = []
    for j in walls:
        mj = measured[j]
        sigma = _scatter(mj.ranges + mj.positions @ unit_normal(mj.bearing, mj.tilt))
        if not (math.isfinite(sigma) and sigma > 0):
            return None
        evidence.append(
            WallEvidence(mj.positions, mj.ranges, mj.bearing, mj.surface_bearing_stderr, mj.tilt, mj.depth, sigma)
        )
    corners = []
    for i, ties in pairs:
        mi = measured[i]
        line = plane_line(measured[ties[0]], measured[ties[1]])
        if line is None:
            continue
        # The corner's scatter about the double bounce the walls predict: the capsules' distances to their line.
        rel = mi.positions - line[0][None, :]
        predicted = np.linalg.norm(rel - (rel @ line[1])[:, None] * line[1][None, :], axis=1)
        sigma = _scatter(mi.ranges - predicted)
        if not (math.isfinite(sigma) and sigma > 0):
            continue
        corners.append(CornerEvidence(mi.positions, mi.ranges, (index[ties[0]], index[ties[1]]), sigma))
    fitted = joint_walls(evidence, corners)
    if fitted is None:
        return None
    return dict(zip(walls, fitted, strict=True))
