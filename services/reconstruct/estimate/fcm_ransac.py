"""The method ``"fcm-ransac"``: the paper's baseline (§5.4) as a scan-level estimator.

Fuzzy C-Means in three clusters, drop the one with the highest energy ratio,
seeded RANSAC on the other two (:mod:`lelsonar.reconstruct.estimate.baseline` holds
both algorithms).
"""

from __future__ import annotations

import time

import numpy as np

from lelsonar.geometry import ArrayGeometry, beam_points
from lelsonar.reconstruct.estimate import fit as F
from lelsonar.reconstruct.estimate.baseline import fuzzy_c_means, ransac_plane
from lelsonar.reconstruct.estimate.correct import AXIS_Y, AXIS_Z
from lelsonar.reconstruct.estimate.estimators import diagnostics
from lelsonar.reconstruct.estimate.options import FitOptions, ScanFit
from lelsonar.reconstruct.estimate.results import FailureReason, FitFailure, PlaneResult

__all__ = ["fit_fcm_ransac"]


def fit_fcm_ransac(
    gamma: np.ndarray,
    distance: np.ndarray,
    ratio: np.ndarray,
    geometry: ArrayGeometry,
    opts: FitOptions,
    echo_amplitude: np.ndarray | None = None,
) -> ScanFit:
    """FCM with three clusters + RANSAC (paper §5.4, ref. [8]).

    Features per point: the raw point's y and z (eq. 9) and the R of its step,
    standardised (γ and d instead split the long plane-b arc in two and merge
    the corner with plane a).  The cluster with
    the highest mean R holds the spurious points.  Of the other two, the one
    at smaller mean γ is plane ``a`` (corrected with the ``y`` axis), the other
    plane ``b`` (``z`` axis).  RANSAC (seeded) fits each; the result's inliers
    are RANSAC's consensus set.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(opts.seed)
    g = np.asarray(gamma, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    n_steps, n_caps = d.shape
    gg = np.broadcast_to(g[:, None], d.shape)
    rr = np.broadcast_to(np.asarray(ratio, dtype=np.float64)[:, None], d.shape)
    steps = np.broadcast_to(np.arange(n_steps)[:, None], d.shape)
    ok = np.isfinite(d) & (d > 0) & np.isfinite(rr)
    if np.count_nonzero(ok) < 3 * opts.min_points:
        f = FitFailure(FailureReason.TOO_FEW_POINTS, f"fcm-ransac: {np.count_nonzero(ok)} valid points", "", 0)
        return ScanFit(FitFailure(f.reason, f.detail, "a", f.n_points), FitFailure(f.reason, f.detail, "b", f.n_points))
    raw = beam_points(geometry, g, np.where(ok, d, 0.0))
    feats = np.stack([raw[..., 1][ok], raw[..., 2][ok], rr[ok]], axis=1)
    sd = feats.std(axis=0)
    feats = (feats - feats.mean(axis=0)) / np.where(sd > 0, sd, 1.0)
    fcm = fuzzy_c_means(feats, 3, rng=rng)
    mean_r = np.array([rr[ok][fcm.labels == k].mean() if np.any(fcm.labels == k) else -np.inf for k in range(3)])
    spurious = int(np.argmax(mean_r))
    rest = [k for k in range(3) if k != spurious]
    mean_g = [gg[ok][fcm.labels == k].mean() if np.any(fcm.labels == k) else np.inf for k in rest]
    order = [rest[i] for i in np.argsort(mean_g)]
    out: list[PlaneResult] = []
    datas: list[F.PlaneData] = []
    for label, cluster, axis in zip(("a", "b"), order, (AXIS_Y, AXIS_Z)):
        sel = np.zeros(d.shape, dtype=bool)
        sel[ok] = fcm.labels == cluster
        st = np.unique(steps[sel])
        data = F.plane_data(geometry, g, np.where(sel, d, np.nan), st, label, axis)
        datas.append(data)
        fail = F.check_points(data.points, label, opts.min_points)
        if fail is not None:
            out.append(fail)
            continue
        rs = ransac_plane(data.points, threshold=opts.inlier_tolerance, rng=rng, n_iter=opts.ransac_iterations)
        if rs is None or rs.inliers.sum() < 3:
            out.append(FitFailure(FailureReason.SOLVER_FAILED, "fcm-ransac: RANSAC found no plane", label, data.n))
            continue
        out.append(
            F.make_plane_fit(
                data,
                rs.normal / rs.offset,
                method="fcm-ransac",
                inlier_mask=rs.inliers,
                diagnostics=diagnostics(
                    "fcm+ransac", t0, starts=rs.iterations, iterations=fcm.iterations, converged=fcm.converged
                ),
            )
        )
    return ScanFit(out[0], out[1], datas[0], datas[1])
