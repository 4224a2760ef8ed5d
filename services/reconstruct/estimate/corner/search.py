"""The corner model's search: hypotheses from the dense bands of mirror-implied wall positions, each refined
and scored over all echoes (MSAC), the best kept (:func:`fit_corner_model`)."""

from __future__ import annotations

import math

import numpy as np

from lelsonar.geometry import rotation_x
from lelsonar.reconstruct.estimate.corner.model import (
    ECHO_OUTLIER,
    CornerModel,
    ScanPoints,
    Wall,
    assign_labels,
    band_offsets_of,
    msac_cost,
)
from lelsonar.reconstruct.estimate.corner.solver import (
    assigned_cost,
    joint_gauss_newton_from,
    refine_walls,
)
from lelsonar.reconstruct.estimate.normals import norm
from lelsonar.signal.compiled import kernel


def fit_corner_model(
    pts: ScanPoints,
    axis_a: np.ndarray,
    axis_b: np.ndarray,
    *,
    beam_half_angle: float = np.deg2rad(50.0),
    tolerance: float = 0.02,
    max_bands: int = 3,
    max_refined: int = 4,
    min_points: int = 8,
    max_tilt: float = np.deg2rad(15.0),
    good_enough: float = 0.02,
    recentre: int = 3,
    significance: float = 3.0,
) -> CornerModel | None:
    """The two walls and their edge that best explain all the echoes.

    Parameters
    ----------
    pts : ScanPoints
    axis_a, axis_b : (3,) arrays
        The walls' nominal normals (the paper's ``y`` and ``z``); hypotheses
        start there and are refined freely.
    beam_half_angle : float
        rad.  Largest angle between a boresight and a wall normal (or the
        direction to the edge) at which an echo is accepted; wide, since it
        only rules explanations out.
    tolerance : float
        m.  Inlier tolerance of the scoring (MSAC) and the final assignment:
        several times the range noise plus what a few degrees of tilt spread.
    max_bands : int
        Bands tried per wall.
    max_refined : int
        Band pairs refined (the lowest-cost ones at the loosest tolerance).
    min_points : int
        Fewest echoes a wall is refitted on.
    max_tilt : float
        rad.  Largest angle between a wall's normal and its nominal axis.
    good_enough : float
        Stop trying band pairs once one leaves at most this share of the
        echoes unexplained.
    significance : float
        A joint fit beyond ``max_tilt`` counts as leaving the window only if
        its angle from the axis exceeds this many of its standard errors
        (else the ranges cannot place the wall and the window stands).
    recentre : int
        How many times the nominal axes may follow a joint fit that leaves
        them by more than ``max_tilt``.  A common roll of the L about the
        rotation axis (a robot not square to the corner) moves both walls off
        the paper's axes together; the ranges still see it through the
        capsules' radial lever arm, so the joint fit points there.  When both
        walls' fits turn the same way (their rolls about x within ``max_tilt``
        of each other), both axes are turned about x by the mean roll and the
        model refitted; the refit is kept only if it explains the echoes
        better (lower MSAC cost over all echoes).  Walls pulled apart — one
        onto the corner cluster, which looks like a wall facing the edge —
        are not followed.

    Returns
    -------
    CornerModel, or None if neither wall has a band of echoes.  ``outside``
    says which walls' joint fit still wanted to leave the ``max_tilt`` window
    (their returned walls are held at the window and their covariance is
    ``inf``: the model cannot place them).
    """
    axis_a = np.asarray(axis_a, dtype=np.float64)
    axis_a = axis_a / norm(axis_a)
    axis_b = np.asarray(axis_b, dtype=np.float64)
    axis_b = axis_b / norm(axis_b)
    na, ha, nb, hb, labels, res, cost, hyps, cov, out_a, out_b, fa, fb = _corner_model(
        pts.capsule,
        pts.distance,
        pts.beam,
        axis_a,
        axis_b,
        math.cos(beam_half_angle),
        float(tolerance),
        int(max_bands),
        int(max_refined),
        int(min_points),
        float(max_tilt),
        math.cos(max_tilt),
        float(good_enough),
        float(significance),
    )
    if hyps == 0:
        return None
    outside = (bool(out_a), bool(out_b))
    model = CornerModel(Wall(na, ha), Wall(nb, hb), labels, res, tolerance, cost, int(hyps), cov, outside)
    if not (any(outside) and recentre > 0):
        return model
    roll_a, roll_b = roll_angle(fa, axis_a), roll_angle(fb, axis_b)
    # Only a turn of the whole L moves the axes: both walls turning the same way by about as much.  Walls
    # pulled apart (one onto the corner cluster, which looks like a wall facing the edge) stay flagged.
    if abs(roll_a - roll_b) <= max_tilt:
        rho = 0.5 * (roll_a + roll_b)
        turn = rotation_x(rho)
        moved = fit_corner_model(
            pts,
            turn @ axis_a,
            turn @ axis_b,
            beam_half_angle=beam_half_angle,
            tolerance=tolerance,
            max_bands=max_bands,
            max_refined=max_refined,
            min_points=min_points,
            max_tilt=max_tilt,
            good_enough=good_enough,
            recentre=recentre - 1,
            significance=significance,
        )
        if moved is not None and moved.cost < model.cost:
            return moved
    return model


@kernel
def _wall_bands(
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    axis: np.ndarray,
    cos_t: float,
    max_bands: int,
    min_points: int,
) -> np.ndarray:
    """Offsets (> 0) of the densest bands of ``w = axis·p_c + d`` over the echoes whose boresight sees ``axis``."""
    n = distance.shape[0]
    w = np.empty(n)
    k = 0
    for i in range(n):
        if beam[i, 0] * axis[0] + beam[i, 1] * axis[1] + beam[i, 2] * axis[2] >= cos_t:
            w[k] = capsule[i, 0] * axis[0] + capsule[i, 1] * axis[1] + capsule[i, 2] * axis[2] + distance[i]
            k += 1
    bands = band_offsets_of(w[:k], 0.01, max_bands, min_points)
    return bands[bands > 0]


@kernel
def _leaves_window(
    normal: np.ndarray, axis: np.ndarray, cov: np.ndarray, k: int, max_tilt: float, significance: float
) -> bool:
    """Whether a fitted wall lies beyond ``max_tilt`` of its axis *and* the echoes say so.

    A wall whose tilt the ranges barely constrain (capsules almost on the axis: no lever arm) can land
    anywhere; its departure is evidence only if it exceeds ``significance`` times its own standard error
    (``cov``'s tilt block of wall ``k``, 0 = a, 1 = b).
    """
    cos_angle = normal[0] * axis[0] + normal[1] * axis[1] + normal[2] * axis[2]
    angle = np.arccos(min(max(cos_angle, -1.0), 1.0))
    o = 3 * k
    c00, c01, c10, c11 = cov[o, o], cov[o, o + 1], cov[o + 1, o], cov[o + 1, o + 1]
    if np.isfinite(c00) and np.isfinite(c01) and np.isfinite(c10) and np.isfinite(c11):
        se = np.sqrt(max(c00 + c11, 0.0))
    else:
        se = np.inf
    return angle > max_tilt and angle > significance * se


@kernel
def _corner_model(
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    axis_a: np.ndarray,
    axis_b: np.ndarray,
    cos_t: float,
    tolerance: float,
    max_bands: int,
    max_refined: int,
    min_points: int,
    max_tilt: float,
    cos_max_tilt: float,
    good_enough: float,
    significance: float,
):
    """One pass of :func:`fit_corner_model` about the axes ``axis_a``, ``axis_b`` (unit), as a kernel.

    Hypotheses are the pairs of the walls' bands (:func:`band_offsets`); beyond ``max_refined`` of them
    the lowest MSAC costs at the loosest stage are refined (alternating assignment and a joint step at
    each stage of the schedule), the best by MSAC over all echoes at ``tolerance`` kept (stopping early
    once one leaves at most ``good_enough`` of the echoes unexplained), then two joint Gauss-Newton
    iterations with the covariance.

    Returns
    -------
    normal_a, offset_a, normal_b, offset_b, labels, residuals, cost, hypotheses (0: no pair of bands),
    covariance, outside_a, outside_b, and the joint fit's normals (before the ``max_tilt`` window).
    """
    n = distance.shape[0]
    bands_a = _wall_bands(capsule, distance, beam, axis_a, cos_t, max_bands, min_points)
    bands_b = _wall_bands(capsule, distance, beam, axis_b, cos_t, max_bands, min_points)
    n_hyps = bands_a.shape[0] * bands_b.shape[0]
    if n_hyps == 0:
        empty = np.zeros(0)
        return (
            axis_a.copy(),
            0.0,
            axis_b.copy(),
            0.0,
            np.zeros(0, dtype=np.intp),
            empty,
            np.inf,
            0,
            np.full((6, 6), np.inf),
            False,
            False,
            axis_a.copy(),
            axis_b.copy(),
        )
    hyp_a = np.empty(n_hyps)
    hyp_b = np.empty(n_hyps)
    for i in range(bands_a.shape[0]):
        for j in range(bands_b.shape[0]):
            hyp_a[i * bands_b.shape[0] + j] = bands_a[i]
            hyp_b[i * bands_b.shape[0] + j] = bands_b[j]
    schedule = np.empty((3, 2))
    schedule[0, 0], schedule[0, 1] = 2.5 * tolerance, 8 * tolerance
    schedule[1, 0], schedule[1, 1] = 1.5 * tolerance, 3 * tolerance
    schedule[2, 0], schedule[2, 1] = tolerance, tolerance
    order = np.arange(n_hyps)
    # The loosest stage's assignment of each pair's starting walls, where the ranking below made it (the
    # refinement's first stage reuses it: the same walls and tolerances).
    loose_labels = np.zeros((n_hyps, 0), dtype=np.intp)
    loose_res = np.zeros((n_hyps, 0))
    if n_hyps > max_refined:
        # Rank by the MSAC cost at the loosest stage (the nominal normals are off by up to the tilt), refine the best.
        loose = np.empty(n_hyps)
        loose_labels = np.empty((n_hyps, n), dtype=np.intp)
        loose_res = np.empty((n_hyps, n))
        for h in range(n_hyps):
            loose_labels[h], loose_res[h] = assign_labels(
                capsule, distance, beam, axis_a, hyp_a[h], axis_b, hyp_b[h], cos_t, schedule[0, 0], schedule[0, 1]
            )
            loose[h] = msac_cost(loose_res[h], schedule[0, 0])
        order = np.argsort(loose, kind="mergesort")[:max_refined]
    best_cost = np.inf
    wa, wha, wb, whb = axis_a.copy(), 0.0, axis_b.copy(), 0.0
    labels = np.zeros(0, dtype=np.intp)
    res = np.zeros(0)
    for h in order:
        ra, rha, rb, rhb = refine_walls(
            capsule,
            distance,
            beam,
            axis_a.copy(),
            hyp_a[h],
            axis_b.copy(),
            hyp_b[h],
            schedule,
            cos_t,
            min_points,
            axis_a,
            axis_b,
            cos_max_tilt,
            loose_labels[h],
            loose_res[h],
        )
        lab, r = assign_labels(capsule, distance, beam, ra, rha, rb, rhb, cos_t, tolerance, tolerance)
        cost = msac_cost(r, tolerance)
        if h == order[0] or cost < best_cost:
            best_cost, wa, wha, wb, whb, labels, res = cost, ra, rha, rb, rhb, lab, r
        if np.count_nonzero(lab == ECHO_OUTLIER) <= good_enough * n:
            break  # the most promising pair already explains (nearly) every echo: no other can do better
    # (the assignment is a pure function of the walls: kept, not redone)
    fa, fha, fb, fhb, cov, _moved = joint_gauss_newton_from(
        capsule, distance, labels, wa, wha, wb, whb, 2, True, 6, 1e-9, assigned_cost(labels, res)
    )
    out_a = _leaves_window(fa, axis_a, cov, 0, max_tilt, significance)
    out_b = _leaves_window(fb, axis_b, cov, 1, max_tilt, significance)
    if (
        fa[0] * axis_a[0] + fa[1] * axis_a[1] + fa[2] * axis_a[2] >= cos_max_tilt
        and fb[0] * axis_b[0] + fb[1] * axis_b[1] + fb[2] * axis_b[2] >= cos_max_tilt
    ):
        wa, wha, wb, whb = fa, fha, fb, fhb
        labels, res = assign_labels(capsule, distance, beam, wa, wha, wb, whb, cos_t, tolerance, tolerance)
    elif out_a or out_b:
        # The covariance belongs to (fa, fb), not to the walls held at the window: it would overclaim.
        cov = np.full((6, 6), np.inf)
    return (
        wa,
        wha,
        wb,
        whb,
        labels,
        res,
        msac_cost(res, tolerance),
        min(n_hyps, max_refined),
        cov,
        out_a,
        out_b,
        fa,
        fb,
    )


def roll_angle(normal: np.ndarray, axis: np.ndarray) -> float:
    """Signed angle about x from ``axis`` to ``normal``, both projected onto the rotation plane (y, z), rad."""
    z = complex(normal[1], normal[2]) * complex(axis[1], -axis[2])
    # np.angle(z), without its array round trip (NumPy's own arctan2: math.atan2 differs in the last bit)
    return float(np.arctan2(z.imag, z.real))
