"""The method ``"corner"``: the joint corner model, then each wall refined on its own echoes.

:mod:`lelsonar.reconstruct.estimate.corner.model` labels every echo of the scan (wall a,
wall b, the edge, outlier) and fits both walls jointly.  Here each wall gets
its final plane — its direction in the rotation plane from where its echoes
are strongest (:func:`amplitude_pitch`), its yaw and offset from the ranges
(:func:`fixed_pitch_wall`), or the paper-corrected points checked against the
joint fit where the sweep never passed the amplitude peak — and its trust
verdict; the critical step is where the boresight meets the final planes'
edge (:func:`corner_edge`).
"""

from __future__ import annotations

import math
import time

import numpy as np

from lelsonar.errors import InternalError
from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate import fit as F
from lelsonar.reconstruct.estimate.corner.edge import (
    edge_alternatives,
    edge_shared_shares,
)
from lelsonar.reconstruct.estimate.corner.model import (
    ECHO_EDGE,
    ECHO_OUTLIER,
    ECHO_WALL_A,
    ECHO_WALL_B,
    Wall,
    echo_residuals,
    edge_line,
    scan_points,
)
from lelsonar.reconstruct.estimate.corner.pitch import (
    amplitude_pitch,
    fixed_pitch_wall,
    walk_stderr,
)
from lelsonar.reconstruct.estimate.corner.search import (
    fit_corner_model,
    roll_angle,
)
from lelsonar.reconstruct.estimate.corner.wall import (
    WallFit,
    corner_wall,
    edge_in_echo_window,
    single_wall,
    wall_echoes,
)
from lelsonar.reconstruct.estimate.correct import AXIS_Y, AXIS_Z
from lelsonar.reconstruct.estimate.estimators import fit_adaptive, run_estimator
from lelsonar.reconstruct.estimate.options import FitOptions, ScanFit
from lelsonar.reconstruct.estimate.quality import (
    DEGRADED,
    GOOD,
    UNRELIABLE,
    QualityLimits,
    assess_beside_unexplained,
    assess_plane,
)
from lelsonar.reconstruct.estimate.results import EdgeLine, FailureReason, FitFailure, PlaneFit, PlaneResult
from lelsonar.reconstruct.estimate.split import critical_step, split_subsets
from lelsonar.reconstruct.estimate.unexplained import echoes_against_walls

__all__ = ["corner_edge", "amplitude_pitch", "fixed_pitch_wall", "walk_stderr", "fit_corner", "joint_contradicted"]


def corner_edge(
    plane_a: PlaneResult, plane_b: PlaneResult, *, min_angle: float = np.deg2rad(5.0)
) -> EdgeLine | FitFailure:
    """The line where the two planes meet.

    Direction ``n_a × n_b`` (normalised) and the point of the line closest to
    the origin, as :func:`lelsonar.reconstruct.estimate.corner.model.edge_line` gives
    them, with first-order standard errors.

    Returns FitFailure if a plane is missing or the planes are within
    ``min_angle`` of parallel.
    """
    if not isinstance(plane_a, PlaneFit) or not isinstance(plane_b, PlaneFit):
        return FitFailure(FailureReason.TOO_FEW_POINTS, "the edge needs both planes", "edge", 0)
    na, nb = plane_a.normal, plane_b.normal
    angle = float(np.arccos(min(max(float(na @ nb), -1.0), 1.0)))  # (np.clip of a scalar costs more)
    line = edge_line(Wall(na, plane_a.offset), Wall(nb, plane_b.offset), min_angle)
    if line is None:
        return FitFailure(
            FailureReason.DEGENERATE_GEOMETRY,
            f"the planes are {np.rad2deg(angle):.1f}° apart, nearly parallel",
            "edge",
            0,
        )
    point, direction = line
    s = math.sin(angle)  # (math's sin and sqrt on floats: the same numbers as NumPy's, without the ufunc calls)
    # First order: an offset error δh moves the line by δh / sin(angle); a tilt δ of a normal moves it by h·δ
    # and turns it by δ / sin(angle).
    point_se = (
        math.sqrt(
            plane_a.offset_stderr**2
            + plane_b.offset_stderr**2
            + (plane_a.offset * plane_a.normal_stderr) ** 2
            + (plane_b.offset * plane_b.normal_stderr) ** 2
        )
        / s
    )
    direction_se = float(np.hypot(plane_a.normal_stderr, plane_b.normal_stderr) / s)
    # (edge_line's fresh arrays: a finite point and a unit direction of two valid planes, an angle in [0, π])
    return EdgeLine.from_owned(point, direction, angle, point_se, direction_se)


def joint_contradicted(other: WallFit, label: str, outside: bool) -> tuple[tuple[str, str], ...]:
    """The finding against a wall whose direction is the joint fit's where the other wall's own evidence
    contradicts that fit (empty: it does not).

    The joint model fits both walls with their edge, whose echoes tie the two directions together: the
    other wall turned beyond its tilt window (``outside``), or its echoes' amplitudes putting its direction
    beyond the joint fit's σ, shows a joint fit that is off, and a direction that rests on it alone may be
    turned with it by as much.  Its σ, the joint fit's own, assumes that fit.

    Parameters
    ----------
    other : WallFit
        The other wall, as :func:`~lelsonar.reconstruct.estimate.corner.wall.corner_wall` refined it.
    label : str
        The other wall's label.
    outside : bool
        The joint fit turns the other wall beyond its tilt window.
    """
    if outside:
        why = f"it turns wall {label} beyond the tilt window"
    elif other.against_joint:
        why = f"wall {label}'s echoes are strongest beyond the σ of its direction"
    else:
        return ()
    return (
        (
            DEGRADED,
            f"its direction is the joint fit's, and {why}: the edge that ties the walls' directions may have "
            "turned this one too; read the wall from the sweep's surfaces, whose bearing the beam pattern gives",
        ),
    )


#: The quality limits the corner model's own findings use (frozen: one instance serves every scan).
_LIMITS = QualityLimits()


def fit_corner(
    gamma: np.ndarray,
    distance: np.ndarray,
    ratio: np.ndarray,
    geometry: ArrayGeometry,
    opts: FitOptions,
    echo_amplitude: np.ndarray | None = None,
) -> ScanFit:
    """The method ``"corner"``: both walls and the edge from all the echoes.

    The joint model (:func:`fit_corner_model`) labels every echo (wall a,
    wall b, edge, outlier); each wall is then refined on its own echoes
    (:func:`corner_wall`: its direction from the echoes' amplitudes where
    ``echo_amplitude`` is given and the peak was swept, else from the
    paper-corrected points checked against the joint fit) and given its trust
    verdict.  The critical step is where the boresight points at the final
    planes' edge, which does not scatter with the energy noise.  Where no pair
    of walls shows bands of echoes, it falls back to ``"adaptive"`` on the
    energy split (degraded), except for a wall that shows a band and whose
    amplitude peak was swept: that wall is fitted alone (:func:`single_wall`).

    Parameters
    ----------
    gamma, distance, ratio, geometry, opts
        As for every scan-level method (:class:`lelsonar.reconstruct.estimate.pipeline.Method`).
    echo_amplitude : (n_steps, n_capsules) array, optional
        Peak amplitude of each capsule's first echo alone, V.
    """
    t0 = time.perf_counter()
    g = np.asarray(gamma, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    pts = scan_points(geometry, g, d)
    model = fit_corner_model(
        pts,
        AXIS_Y,
        AXIS_Z,
        beam_half_angle=opts.corner_beam_half_angle,
        tolerance=opts.corner_tolerance,
        min_points=opts.min_points,
        significance=opts.tilt_test_sigma,
    )
    if model is None:
        crit = critical_step(ratio, opts.critical_peak_fraction)
        if crit is None:
            raise InternalError(
                "fit_corner: no step has a finite, positive R; the pipeline calls a scan method only once one has"
            )
        split = split_subsets(g, crit)
        subsets = [
            F.plane_data(geometry, g, d, steps, label, axis)
            for steps, label, axis in ((split.steps_a, "a", AXIS_Y), (split.steps_b, "b", AXIS_Z))
        ]
        adaptive = [run_estimator(fit_adaptive, "adaptive", dd, None, opts) for dd in subsets]
        # Nothing checked these planes against the other wall or the edge, and the energy split assumes both
        # walls and the corner were swept: a plane can be centimetres off with clean residuals.
        fallback = (
            (
                DEGRADED,
                "no pair of walls explains the scan's echoes (one wall, or none, shows a band): "
                "energy-split fallback, unchecked against the other wall and the edge",
            ),
        )
        planes = [assess_plane(p, g, findings=fallback) if isinstance(p, PlaneFit) else p for p in adaptive]
        for k, (label, axis) in enumerate((("a", AXIS_Y), ("b", AXIS_Z))):
            single = single_wall(pts, g, d, geometry, label, axis, opts, echo_amplitude, t0)
            if single is not None:
                planes[k], subsets[k] = single
        return ScanFit(planes[0], planes[1], subsets[0], subsets[1], crit)
    # Echoes per label, counted once: outliers (-1), wall a, wall b, edge.
    n_outlier, n_wall_a, n_wall_b, n_edge = np.bincount(model.labels - ECHO_OUTLIER, minlength=4).tolist()
    note = (
        f"corner model: {model.hypotheses} band pairs; echoes: {n_wall_a} wall a, {n_wall_b} wall b, "
        f"{n_edge} edge, {n_outlier} outliers (tolerance {1000 * model.tolerance:.0f} mm)"
    )
    amplitudes = None if echo_amplitude is None else np.asarray(echo_amplitude, dtype=np.float64)
    out: list[PlaneResult] = []
    datas: list[F.PlaneData] = []
    # Echoes a wall could have returned as well as the edge can move the offset by up to the tolerance; a
    # share of them beyond max_offset_stderr / tolerance could move it past what a good plane may miss by.
    limits = _LIMITS
    shared_limit = limits.max_offset_stderr / model.tolerance
    residuals = echo_residuals(model.wall_a, model.wall_b, pts, opts.corner_beam_half_angle)  # (3, N), once
    # Of the echoes no part explains, those a wall should have returned instead (not another surface's); only
    # asked where the share could degrade a plane (under it neither share is named).
    unexplained, against = n_outlier / pts.n, n_outlier / pts.n
    if unexplained > limits.degraded_unexplained:
        own = np.stack([model.labels == ECHO_WALL_A, model.labels == ECHO_WALL_B])
        cosines = np.stack([pts.beam @ model.wall_a.normal, pts.beam @ model.wall_b.normal])
        against = (
            np.count_nonzero(
                echoes_against_walls(residuals[:2], cosines, own, model.labels == ECHO_OUTLIER, opts.min_points)
            )
            / pts.n
        )
    shares = edge_shared_shares(model, pts, opts.corner_beam_half_angle, residuals)
    edge_is_walls = shares[ECHO_EDGE] > shared_limit
    alternatives = edge_alternatives(model, pts, opts.corner_beam_half_angle, opts.min_points)
    leaks = edge_in_echo_window(model, pts, opts.corner_beam_half_angle, residuals)
    # Each echo's own peak amplitude, once a scan (NaN: none)
    echo_amp = None if amplitudes is None else amplitudes[pts.step, pts.capsule_index]
    walk: list[tuple[float, float]] = []
    # Per wall: the share of its echoes the edge explains as well, and whether the corner's double bounces
    # (with the wall where they put it) explain the scan about as well: either way the wall may be the
    # corner cluster.  The same share of echoes as above could hold the offset; an alternative leaving no
    # more than the share of unexplained echoes that already degrades a plane explains the scan about as well.
    edge_shared = {k: shares[k] > shared_limit for k in (ECHO_WALL_A, ECHO_WALL_B)}
    joint_walls = {ECHO_WALL_A: (model.wall_a.normal, AXIS_Y), ECHO_WALL_B: (model.wall_b.normal, AXIS_Z)}
    as_cluster = {
        k: alternatives[k][0] > shared_limit and alternatives[k][1] <= limits.degraded_unexplained * pts.n
        for k in (ECHO_WALL_A, ECHO_WALL_B)
    }

    def walk_se(k: int) -> float:
        # Three more joint fits: only for a wall whose direction rests on the ranges, once a scan.
        if not walk:
            walk.append((0.0, 0.0) if echo_amp is None else walk_stderr(model, pts, echo_amp))
        return walk[0][k]

    # Each wall refined on its own echoes first, its verdict once both are known: a joint fit one wall's own
    # evidence contradicts says something against the other wall's direction too.
    walls: list[tuple[WallFit, tuple[tuple[str, str], ...], int] | FitFailure] = []
    for k, label, axis, wall in ((ECHO_WALL_A, "a", AXIS_Y, model.wall_a), (ECHO_WALL_B, "b", AXIS_Z, model.wall_b)):
        rows, amplitude = wall_echoes(model.labels, k, leaks, pts, echo_amp)
        # The wall's echoes one by one, in the scan's order (step, then capsule) as plane_data keeps them.
        data = F.plane_data_of(*rows, label, axis)
        datas.append(data)
        fail = F.check_points(data.points, label, opts.min_points)
        if fail is not None:
            walls.append(
                FitFailure(
                    fail.reason,
                    f"corner: {rows[0].shape[0]} echoes of wall {label}; " + fail.detail,
                    label,
                    fail.n_points,
                )
            )
            continue
        flags: list[str] = []
        if model.outside[k]:
            flags.append(
                "the joint fit turns it beyond the tilt window around its nominal axis: the model cannot place it"
            )
        other = ECHO_WALL_B if k == ECHO_WALL_A else ECHO_WALL_A
        fit = corner_wall(
            data,
            wall,
            model.wall_stderr(k),
            opts,
            t0,
            note,
            amplitude,
            flags,
            edge_is_walls,
            walk_se=lambda k=k: walk_se(k),
            tie_suspect=edge_shared[other] or as_cluster[other],
            common_roll=roll_angle(*joint_walls[other]),
        )
        findings = tuple((UNRELIABLE, f) for f in flags)
        shared = shares[k]
        if edge_shared[k]:
            findings += (
                (
                    DEGRADED,
                    f"{100 * shared:.0f} % of its echoes fit the corner edge as well (within "
                    f"{1000 * model.tolerance:.0f} mm): the corner cluster may hold its offset",
                ),
            )
        as_edge, lost = alternatives[k]
        if as_cluster[k]:
            findings += (
                (
                    DEGRADED,
                    f"{100 * as_edge:.0f} % of its echoes are the corner's double bounces with the "
                    f"wall where they put it, a pair that explains all but {max(lost, 0)} of the "
                    "echoes the model explains: the corner cluster may have passed for the wall",
                ),
            )
        walls.append((fit, findings, len(flags)))
    for k, entry in enumerate(walls):
        if isinstance(entry, FitFailure):
            out.append(entry)
            continue
        fit, findings, n_flags = entry
        if not isinstance(fit.plane, PlaneFit):
            out.append(fit.plane)
            continue
        assessed = assess_beside_unexplained(
            fit.plane, g, unexplained, against, edge_echoes=n_edge, findings=findings, at=n_flags
        )
        # Said where it takes a good verdict away, as the sweep's other checks of a good plane are.
        # (walls[k] is wall a then b: the echo labels ECHO_WALL_A, ECHO_WALL_B index them)
        other_entry = walls[1 - k]
        if assessed.quality == GOOD and fit.joint_direction and not isinstance(other_entry, FitFailure):
            against_it = joint_contradicted(other_entry[0], "ab"[1 - k], model.outside[1 - k])
            if against_it:
                assessed = assess_beside_unexplained(
                    fit.plane, g, unexplained, against, edge_echoes=n_edge, findings=findings + against_it, at=n_flags
                )
        out.append(assessed)
    # The critical step: where the boresight points at the edge of the final planes.  A common roll
    # of both walls about x barely changes any range, so the final normals (amplitude peaks, or the
    # corrected points) place the edge's direction better than the joint fit's.
    edge = corner_edge(out[0], out[1])
    crit = None
    if isinstance(edge, EdgeLine):
        point = edge.point
        if abs(edge.direction[0]) > 1e-9:
            point = point - edge.direction * (point[0] / edge.direction[0])
        crit = int(np.argmin(np.abs(g - np.arctan2(point[2], point[1]))))
    return ScanFit(out[0], out[1], datas[0], datas[1], crit, edge)
