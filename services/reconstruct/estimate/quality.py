"""The trust verdict on every plane: ``good``, ``degraded`` or ``unreliable``, with reasons.

A planner must never receive a wrong plane that claims to be good.  Each check
below looks for a way a fit can be wrong while its own residuals look fine,
and for the signs of a fit that is not what it claims.  Thresholds come from
the measurement model: ultrasonic range noise is 1–6 mm
(plus ±4.3 mm cycle slips), so a wall fitted to its own echoes has a
residual σ of at most ~6 mm; a plane whose σ is several times that runs
through echoes of more than one surface.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate.results import FailureReason, FitFailure, PlaneFit, PlaneResult
from lelsonar.signal.compiled import kernel

__all__ = [
    "QualityLimits",
    "assess_plane",
    "assess_beside_unexplained",
    "add_findings",
    "unexplained_finding",
    "cross_check",
    "recovery_finding",
    "published_verdicts",
    "GOOD",
    "DEGRADED",
    "UNRELIABLE",
]

GOOD, DEGRADED, UNRELIABLE = "good", "degraded", "unreliable"
_RANK = {GOOD: 0, DEGRADED: 1, UNRELIABLE: 2}


@dataclass(frozen=True)
class QualityLimits:
    """Where each check draws its lines.

    Parameters
    ----------
    range_noise : float
        m.  The largest range noise σ expected of a healthy sensor (6 mm).
    degraded_sigma, unreliable_sigma : float
        Residual σ over ``range_noise`` above which a plane is degraded /
        unreliable (a compromise between two surfaces).
    min_echoes, few_echoes : int
        Fewer wall echoes than ``min_echoes`` is unreliable, than
        ``few_echoes`` degraded.
    max_inlier_loss : float
        Largest share of the subset's points a plane may reject before it is
        degraded (the corner cluster may have won).
    max_normal_stderr : float
        rad.  A normal less certain than this is degraded (tilt unresolved).
    max_offset_stderr : float
        m.
    face_on_angle : float
        rad.  If no beam of the scan came within this of the wall's normal,
        its face-on echo was never seen: degraded, and unreliable when the
        edge was not seen either (nothing ties the wall to the corner, and a
        corner cluster looks like a wall at the edge's range).
    degraded_unexplained, unreliable_unexplained : float
        Share of the scan's echoes that neither wall nor their edge explains
        (the corner model's outliers): a healthy L scan leaves under 1 %; a
        model that leaves a wall's echoes unexplained has taken something else
        for that wall.  On a plane its other checks find good, only those a
        wall should have returned instead count (another surface's say nothing
        against it: :func:`assess_beside_unexplained`).
    """

    range_noise: float = 0.006
    degraded_sigma: float = 1.5
    unreliable_sigma: float = 2.5
    min_echoes: int = 12
    few_echoes: int = 30
    max_inlier_loss: float = 0.6
    max_normal_stderr: float = float(np.deg2rad(3.0))
    max_offset_stderr: float = 0.005
    face_on_angle: float = float(np.deg2rad(12.0))
    degraded_unexplained: float = 0.05
    unreliable_unexplained: float = 0.15

    def __post_init__(self) -> None:
        for name in ("range_noise", "degraded_sigma", "max_normal_stderr", "max_offset_stderr", "face_on_angle"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"QualityLimits.{name} must be > 0, got {getattr(self, name)!r}")
        if not (
            self.unreliable_sigma >= self.degraded_sigma
            and self.few_echoes >= self.min_echoes >= 0
            and 0 <= self.degraded_unexplained <= self.unreliable_unexplained <= 1
            and 0 <= self.max_inlier_loss <= 1
        ):
            raise ConfigError(
                "QualityLimits: each unreliable line must lie beyond its degraded line, and shares must be in [0, 1]"
            )


#: The limits every check uses unless given others (frozen: one instance serves every call).
_DEFAULT_LIMITS = QualityLimits()


def unexplained_finding(
    share: float, limits: QualityLimits | None = None, *, against: float | None = None
) -> tuple[tuple[str, str], ...]:
    """The finding against a plane of a scan whose model leaves ``share`` of the echoes unexplained.

    ``against``: the share of the scan's echoes among those that a wall of the model should have returned
    instead (:func:`~lelsonar.reconstruct.estimate.unexplained.echoes_against_walls`); the level rests on it, and
    the rest (another surface's) is only named, at level ``"good"``.  None: every unexplained echo counts.
    """
    lim = limits or _DEFAULT_LIMITS
    text = f"{100 * share:.0f} % of the scan's echoes fit neither wall nor their edge"
    if against is None:
        against = share
    elif share > lim.degraded_unexplained:
        text += (
            f" ({100 * against:.0f} % where a wall should have answered instead; the rest from beams "
            "beyond the walls' echoes or in front of walls seen nearer face-on: another surface)"
        )
    if against > lim.unreliable_unexplained:
        return ((UNRELIABLE, text + ": the walls explain the wrong echoes"),)
    if against > lim.degraded_unexplained:
        return ((DEGRADED, text),)
    if share > lim.degraded_unexplained:
        return ((GOOD, text),)
    return ()


def assess_beside_unexplained(
    plane: PlaneFit,
    scan_gamma: np.ndarray,
    share: float,
    against: float,
    *,
    edge_echoes: int | None = None,
    findings: tuple[tuple[str, str], ...] = (),
    at: int = 0,
    limits: QualityLimits | None = None,
) -> PlaneFit:
    """:func:`assess_plane` with the finding of the scan's unexplained echoes put at ``at`` among ``findings``.

    A plane its own evidence finds good (its echoes, residuals, σ, the estimator's findings) is judged only
    by the share ``against`` of echoes a wall should have returned instead: the rest, another surface's,
    says nothing against it.  On a plane with doubts of its own every unexplained echo (``share``) counts,
    since the same surface may be what it cost (it may hide the wall's face-on echoes, or have passed for
    some of them).
    """
    own = assess_plane(plane, scan_gamma, edge_echoes=edge_echoes, findings=findings, limits=limits)
    found = unexplained_finding(share, limits, against=against if own.quality == GOOD else None)
    if not found:
        return own
    return assess_plane(
        plane, scan_gamma, edge_echoes=edge_echoes, findings=findings[:at] + found + findings[at:], limits=limits
    )


def assess_plane(
    plane: PlaneFit,
    scan_gamma: np.ndarray,
    *,
    edge_echoes: int | None = None,
    findings: tuple[tuple[str, str], ...] = (),
    limits: QualityLimits | None = None,
) -> PlaneFit:
    """``plane`` with its verdict and reasons filled in.

    Parameters
    ----------
    plane : PlaneFit
    scan_gamma : (n_steps,) array
        Every step's γ (rad), to know which directions the scan looked in.
    edge_echoes : int, optional
        Echoes the joint model explained by the corner edge (None: not known,
        e.g. a per-subset method).
    findings : tuple of (level, reason)
        What the estimator itself found against the plane (level
        ``"degraded"`` or ``"unreliable"``; ``"good"``: a fact named
        without lowering the verdict).
    limits : QualityLimits, optional
    """
    lim = limits or _DEFAULT_LIMITS
    verdict, reasons = GOOD, []

    def flag(level: str, reason: str) -> None:
        nonlocal verdict
        reasons.append(reason)
        if _RANK[level] > _RANK[verdict]:
            verdict = level

    for level, reason in findings:
        flag(level, reason)
    if plane.sigma > lim.unreliable_sigma * lim.range_noise:
        flag(
            UNRELIABLE,
            f"residual σ {1000 * plane.sigma:.1f} mm is over {lim.unreliable_sigma:g}× the range noise: "
            "the plane runs through echoes of more than one surface",
        )
    elif plane.sigma > lim.degraded_sigma * lim.range_noise:
        flag(DEGRADED, f"residual σ {1000 * plane.sigma:.1f} mm is over {lim.degraded_sigma:g}× the range noise")
    k = plane.n_inliers
    if k < lim.min_echoes:
        flag(UNRELIABLE, f"only {k} wall echoes")
    elif k < lim.few_echoes:
        flag(DEGRADED, f"only {k} wall echoes")
    loss = 1.0 - k / max(plane.n_points, 1)
    if loss > lim.max_inlier_loss:
        flag(DEGRADED, f"{100 * loss:.0f} % of the subset rejected as outliers: the corner cluster may dominate it")
    if plane.normal_stderr > lim.max_normal_stderr:
        flag(DEGRADED, f"tilt unresolved: normal ±{np.rad2deg(plane.normal_stderr):.1f}°")
    if plane.offset_stderr > lim.max_offset_stderr:
        flag(DEGRADED, f"offset ±{1000 * plane.offset_stderr:.1f} mm")
    _, ny, nz = plane.normal.tolist()
    cos_nearest, seen = _nearest_beam_cosine(np.asarray(scan_gamma, dtype=np.float64).ravel(), ny, nz)
    if seen:
        nearest = float(np.arccos(min(max(cos_nearest, -1.0), 1.0)))
        if nearest > lim.face_on_angle:
            level = UNRELIABLE if edge_echoes is not None and edge_echoes == 0 else DEGRADED
            flag(
                level,
                f"wall never seen face-on: the nearest beam is {np.rad2deg(nearest):.0f}° from its normal"
                + ("; no edge echoes tie it to the corner" if level == UNRELIABLE else ""),
            )
    if edge_echoes is not None and edge_echoes == 0 and verdict == GOOD:
        flag(DEGRADED, "the corner edge was not seen: the walls are not tied together")
    return plane.replace_scalars(quality=verdict, quality_reasons=tuple(reasons))


@kernel
def _nearest_beam_cosine(gamma: np.ndarray, ny: float, nz: float) -> tuple[float, bool]:
    """The largest cosine between a beam of the finite ``gamma`` and a normal ``(·, ny, nz)``; False: no finite γ.

    The beams are ``(0, cos γ, sin γ)`` (:func:`lelsonar.geometry.boresight`): their cosines to the normal
    without building them, as ``(np.cos(g) * ny + np.sin(g) * nz).max()`` rounds them.
    """
    best = -np.inf
    seen = False
    for i in range(gamma.shape[0]):
        g = gamma[i]
        if np.isfinite(g):
            c = np.cos(g) * ny + np.sin(g) * nz
            if not seen or c > best:
                best = c
            seen = True
    return best, seen


def add_findings(plane: PlaneResult, findings: tuple[tuple[str, str], ...]) -> PlaneResult:
    """An assessed ``plane`` with more findings: its verdict at least each finding's level, their reasons added.

    For what only the whole scan shows (e.g. ranges that do not match the waveforms), found after the fit.
    """
    if not isinstance(plane, PlaneFit) or not findings:
        return plane
    verdict = plane.quality or GOOD
    for level, _ in findings:
        if _RANK[level] > _RANK[verdict]:
            verdict = level
    return plane.replace_scalars(quality=verdict, quality_reasons=plane.quality_reasons + tuple(r for _, r in findings))


def cross_check(
    plane: PlaneFit,
    reference: PlaneResult | None,
    *,
    max_angle: float = float(np.deg2rad(3.0)),
    max_distance: float = 0.02,
) -> PlaneFit:
    """``plane`` (a compared method's) checked against the method of record's ``reference`` of the same wall.

    A compared method can lock onto the corner cluster and still fit it
    cleanly (a tight, well-populated, wrong plane); its own residuals cannot
    show that.  So a compared plane is good only if a good reference agrees
    with it.  The disagreement is measured where it matters: the largest
    distance between the two planes over the reference's observed patch, and
    the angle between the normals.  Without a good reference (the method of
    record failed, or doubts its own plane of this wall) nothing can vouch for
    it: it is at most degraded.
    """
    if plane is reference:
        return plane
    if not isinstance(reference, PlaneFit) or reference.quality != GOOD or plane.label != reference.label:
        if plane.quality != GOOD:
            return plane
        what = "no plane" if not isinstance(reference, PlaneFit) else f"a {reference.quality} plane"
        reason = f"unchecked: the method of record has {what} of this wall to check it against"
        return plane.replace_scalars(quality=DEGRADED, quality_reasons=plane.quality_reasons + (reason,))
    angle = float(np.arccos(np.clip(plane.normal @ reference.normal, -1.0, 1.0)))
    gap = float(np.max(np.abs(reference.patch @ plane.normal - plane.offset)))
    if angle <= max_angle and gap <= max_distance:
        return plane
    reason = (
        f"disagrees with {reference.method} (good) by {100 * gap:.1f} cm and {np.rad2deg(angle):.1f}° "
        "over the observed patch"
    )
    level = DEGRADED if plane.quality == GOOD else plane.quality
    return plane.replace_scalars(quality=level, quality_reasons=plane.quality_reasons + (reason,))


def recovery_finding(
    plane: PlaneResult, without: PlaneResult | None, *, sigmas: float = 3.0
) -> tuple[tuple[str, str], ...]:
    """The finding against ``plane`` where the echoes recovered after a board's noise triggers turn it away from
    ``without``, the same wall fitted without them.

    The recovered ranges are timed on the waveforms' convention, their zero estimated; the board's own
    readings on its.  Both sets see the same wall: if the two fits differ by more than ``sigmas``
    of their combined standard errors (normal or offset), one of the two timings is off and neither plane's σ
    covers it.  Nothing to say where either is no plane, or ``without`` is unreliable (too few readings of the
    board's own to tell: most were noise).
    """
    if not isinstance(plane, PlaneFit) or not isinstance(without, PlaneFit) or without.quality == UNRELIABLE:
        return ()
    angle = float(np.arccos(min(max(float(plane.normal @ without.normal), -1.0), 1.0)))
    gap = abs(plane.offset - without.offset)
    angle_se = math.hypot(plane.normal_stderr, without.normal_stderr)
    offset_se = math.hypot(plane.offset_stderr, without.offset_stderr)
    if not (angle > sigmas * angle_se or gap > sigmas * offset_se):
        return ()
    return (
        (
            UNRELIABLE,
            f"the echoes recovered after the noise triggers turn it {np.rad2deg(angle):.1f}° and move it "
            f"{1000 * gap:.1f} mm from the fit of the board's own readings (over {sigmas:g}σ): the two "
            "timings disagree",
        ),
    )


def published_verdicts(
    record: tuple[PlaneResult, ...],
    compared: tuple[tuple[str, tuple[PlaneResult, ...]], ...],
    *,
    gamma: np.ndarray | None = None,
    findings: tuple[tuple[str, str], ...] = (),
    without: Mapping[str, PlaneResult] | None = None,
) -> tuple[PlaneResult, ...]:
    """Every published plane's verdict, applied here and nowhere else after the estimators.

    - A plane of record no estimator judged (a provisional, incremental one) gets its own verdict
      from the steps so far ``gamma`` (:func:`~lelsonar.reconstruct.estimate.quality.assess_plane`).
    - Where echoes were recovered after the board's noise triggers (``without``: the same walls fitted
      on the board's own readings), a plane of record they turn away from it is unreliable.
    - The scan's writer findings lower every plane to their level and name themselves.
    - A compared method's plane is checked against the plane of record of its wall (after the
      recovered echoes' check): one that disagrees with a good plane of record, or that no good plane
      of record can vouch for, is degraded (it may have locked onto the corner's echoes, which its own
      residuals cannot show); one that failed is reported under its method's name, never dropped.

    Returns the planes of record, then each compared method's, in order.
    """
    if gamma is not None:
        record = tuple(assess_plane(pl, gamma) if isinstance(pl, PlaneFit) and not pl.quality else pl for pl in record)
    by_label = {pl.label: pl for pl in record}
    if without is not None:
        by_label = {
            label: add_findings(pl, recovery_finding(pl, without[label]) if label in without else ())
            for label, pl in by_label.items()
        }
    planes: list[PlaneResult] = [add_findings(pl, findings) for pl in by_label.values()]
    for method, pls in compared:
        for pl in pls:
            if isinstance(pl, PlaneFit):
                reference = by_label.get(pl.label)
                if reference is None:  # (every method labels its planes a and b: not expected)
                    reference = FitFailure(FailureReason.TOO_FEW_POINTS, "no plane of record", pl.label)
                checked: PlaneResult = cross_check(pl, reference)
            elif pl.detail.startswith(f"{method}: "):
                checked = pl  # (the estimator named itself)
            else:
                checked = FitFailure(pl.reason, f"{method}: {pl.detail}", pl.label, pl.n_points)
            planes.append(add_findings(checked, findings))
    return tuple(planes)
