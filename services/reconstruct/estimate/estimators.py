"""Plane estimators that fit one subset of the scan (the paper's §5 family and its refinements).

Each is a :data:`PlaneEstimator`: ``(PlaneData, warm start θ or None,
FitOptions) -> PlaneFit | FitFailure``; the registry in
:mod:`lelsonar.reconstruct.estimate.pipeline` names them (``ls``, ``lel-nm``, ``paper``,
``lel``, ``lel-refit-lel``, ``lel-refit-ls``, ``constant-depth``, ``adaptive``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from lelsonar.reconstruct.estimate import fit as F
from lelsonar.reconstruct.estimate.baseline import ransac_plane
from lelsonar.reconstruct.estimate.lel import LelResult, lel_fit_fast, lel_fit_nelder_mead, six_starts
from lelsonar.reconstruct.estimate.options import FitOptions
from lelsonar.reconstruct.estimate.results import (
    FailureReason,
    FitFailure,
    PlaneFit,
    PlaneResult,
    SolverDiagnostics,
)

__all__ = [
    "PlaneEstimator",
    "Inconsistent",
    "diagnostics",
    "run_estimator",
    "fit_ls",
    "fit_lel_nm",
    "fit_paper",
    "fit_lel",
    "fit_lel_refit_lel",
    "fit_lel_refit_ls",
    "fit_constant_depth",
    "fit_adaptive",
]

#: A plane estimator: (subset, warm start θ or None, options) -> PlaneFit | FitFailure.
PlaneEstimator = Callable[[F.PlaneData, "np.ndarray | None", FitOptions], PlaneResult]


def run_estimator(
    estimator: PlaneEstimator, name: str, data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions
) -> PlaneResult:
    """Run ``estimator`` on ``data``; too few points and solver breakdowns become typed failures."""
    fail = F.check_points(data.points, data.label, opts.min_points)
    if fail is not None:
        return fail
    try:
        return estimator(data, warm, opts)
    except Inconsistent as exc:
        return FitFailure(FailureReason.DEGENERATE_GEOMETRY, f"{name}: {exc}", data.label, data.n)
    except np.linalg.LinAlgError as exc:
        return FitFailure(FailureReason.SOLVER_FAILED, f"{name}: {exc}", data.label, data.n)


def diagnostics(
    solver: str,
    t0: float,
    res: LelResult | None = None,
    starts: int = 1,
    iterations: int = 0,
    evaluations: int = 0,
    converged: bool = True,
    notes: tuple[str, ...] = (),
) -> SolverDiagnostics:
    if res is not None:
        starts, iterations, evaluations, converged = res.starts, res.iterations, res.evaluations, res.converged
    return SolverDiagnostics(
        solver=solver,
        starts=starts,
        iterations=iterations,
        evaluations=evaluations,
        time_s=time.perf_counter() - t0,
        converged=converged,
        notes=notes,
    )


def _merge(
    a: SolverDiagnostics, b: LelResult | None, solver: str, t0: float, notes: tuple[str, ...] = ()
) -> SolverDiagnostics:
    extra_s = b.starts if b is not None else 0
    extra_i = b.iterations if b is not None else 0
    extra_e = b.evaluations if b is not None else 1
    conv = b.converged if b is not None else a.converged
    return SolverDiagnostics(
        solver=solver,
        starts=a.starts + extra_s,
        iterations=a.iterations + extra_i,
        evaluations=a.evaluations + extra_e,
        time_s=time.perf_counter() - t0,
        converged=conv,
        notes=a.notes + notes,
    )


def _warm(warm: np.ndarray | None) -> np.ndarray | None:
    if warm is None:
        return None
    w = np.asarray(warm, dtype=np.float64).reshape(3)
    return w[None, :] if np.all(np.isfinite(w)) and np.linalg.norm(w) > 0 else None


def fit_ls(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    theta = F.ls_theta(data.points)
    return F.make_plane_fit(
        data, theta, method="ls", inlier_mask=np.ones(data.n, dtype=bool), diagnostics=diagnostics("lstsq", t0)
    )


def fit_lel_nm(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    res = lel_fit_nelder_mead(data.points, F.ls_theta(data.points), extra_starts=_warm(warm))
    return F.make_plane_fit(
        data,
        res.theta,
        method="lel-nm",
        inlier_mask=np.ones(data.n, dtype=bool),
        diagnostics=diagnostics("nelder-mead", t0, res),
    )


def _prefiltered(data: F.PlaneData, theta: np.ndarray, opts: FitOptions) -> np.ndarray:
    return F.prefilter_mask(F.fitting_errors(data.points, theta), opts.prefilter_fraction)


def fit_paper(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    first = lel_fit_nelder_mead(data.points, F.ls_theta(data.points), extra_starts=_warm(warm))
    mask = _prefiltered(data, first.theta, opts)
    if np.count_nonzero(mask) < 4:
        return FitFailure(
            FailureReason.TOO_FEW_POINTS, "paper: fewer than 4 points survive the pre-filter", data.label, data.n
        )
    kept = data.points[mask]
    second = lel_fit_nelder_mead(kept, F.ls_theta(kept))
    d1 = diagnostics("nelder-mead", t0, first)
    return F.make_plane_fit(
        data,
        second.theta,
        method="paper",
        inlier_mask=mask,
        diagnostics=_merge(d1, second, "nelder-mead x6, pre-filter, nelder-mead x6", t0),
    )


def _guarded_lel(
    data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions, rng: np.random.Generator
) -> tuple[np.ndarray, LelResult, tuple[str, ...]]:
    """Fast LEL (eq. 8) with the outlier-cluster guard.

    LEL is local, and its cost can have a minimum on a plane through the tight
    cluster of double-bounce echoes behind the corner.  Each
    LEL minimum found (from θ_LS, the warm start, and with
    ``opts.lel_starts == "six"`` the paper's other five starts) is scored by

    * the mirror-echo condition: its normal must be within
      ``beam_half_angle`` of some boresight of the subset — a wall whose normal
      no beam ever pointed along cannot have echoed;
    * its inlier count: points within ``inlier_tolerance``.

    The least-``H`` minimum is kept if it passes the mirror-echo test, holds at
    least ``min_inlier_fraction`` of the points and at least 90 % of the best
    inlier count among the minima.  Otherwise a competing minimum is sought
    from a seeded RANSAC plane, and the mirror-consistent minimum with the
    most inliers wins (least ``H`` on a tie).  If no minimum satisfies the
    mirror-echo condition the subset holds no wall seen face-on (typically a
    partial scan that has not reached the corner) and the plane is a
    ``DEGENERATE_GEOMETRY`` failure.  Every decision is logged in the
    diagnostics' notes.
    """
    v = data.points
    t_ls = F.ls_theta(v)
    warm_start = _warm(warm)
    extra: list[np.ndarray] = [] if warm_start is None else [warm_start]
    if opts.lel_starts == "six":
        extra.append(six_starts(t_ls)[1:])
    res = lel_fit_fast(v, t_ls, extra_starts=np.concatenate(extra) if extra else None)
    if not opts.guard:
        return res.theta, res, ()

    def score(theta: np.ndarray) -> tuple[bool, int]:
        nt = np.linalg.norm(theta)
        if not (np.isfinite(nt) and nt > 0):
            return False, -1
        ok = F.mirror_consistent(theta / nt, data.beam, opts.beam_half_angle)
        return ok, F.inlier_count(F.metric_residuals(theta, v), opts.inlier_tolerance)

    cands = list(res.candidates)
    hs = list(res.candidate_entropy)
    scores = [score(c) for c in cands]
    best = int(np.argmin(hs))
    ok_b, k_b = scores[best]
    k_max = max((k for ok, k in scores if ok), default=-1)
    if ok_b and k_b >= opts.min_inlier_fraction * data.n and k_b >= 0.9 * k_max:
        return res.theta, res, ()
    notes = [f"guard: least-H minimum suspicious (mirror-consistent={ok_b}, inliers={k_b}/{data.n})"]
    total = res
    rs = ransac_plane(v, threshold=opts.inlier_tolerance, rng=rng, n_iter=opts.ransac_iterations)
    if rs is not None:
        alt = lel_fit_fast(v, rs.normal / rs.offset)
        cands.append(alt.theta)
        hs.append(alt.entropy)
        scores.append(score(alt.theta))
        total = replace(
            res,
            starts=res.starts + alt.starts,
            iterations=res.iterations + alt.iterations,
            evaluations=res.evaluations + alt.evaluations,
            time_s=res.time_s + alt.time_s,
            candidates=np.asarray(cands),
            candidate_entropy=np.asarray(hs),
        )
    pick = max(range(len(cands)), key=lambda i: (scores[i][0], scores[i][1], -hs[i]))
    if not scores[pick][0]:
        raise Inconsistent(
            f"no LEL minimum has its normal within {np.rad2deg(opts.beam_half_angle):.0f}° of a "
            "boresight of the subset: no wall seen face-on (is the corner reached yet?)"
        )
    if pick == best:
        notes.append("guard: no better minimum found; kept the least-H one")
    else:
        notes.append(
            f"guard: switched to minimum {pick} (mirror-consistent={scores[pick][0]}, "
            f"inliers={scores[pick][1]}/{data.n}, H {hs[best]:.4f} -> {hs[pick]:.4f})"
        )
    return cands[pick], replace(total, theta=cands[pick], entropy=hs[pick]), tuple(notes)


class Inconsistent(Exception):
    """No candidate plane satisfies the mirror-echo condition."""


def _rng(opts: FitOptions, label: str) -> np.random.Generator:
    return np.random.default_rng([opts.seed, ord(label[0]) if label else 0])


def fit_lel(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    theta, res, notes = _guarded_lel(data, warm, opts, _rng(opts, data.label))
    mask = _prefiltered(data, theta, opts)  # reported inliers: the §5.3 criterion
    return F.make_plane_fit(
        data, theta, method="lel", inlier_mask=mask, diagnostics=diagnostics("newton", t0, res, notes=notes)
    )


def _lel_then_prefilter(
    data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions, name: str, t0: float
) -> tuple[np.ndarray, np.ndarray, SolverDiagnostics] | FitFailure:
    theta, res, notes = _guarded_lel(data, warm, opts, _rng(opts, data.label))
    mask = _prefiltered(data, theta, opts)
    if np.count_nonzero(mask) < 4:
        return FitFailure(
            FailureReason.TOO_FEW_POINTS, f"{name}: fewer than 4 points survive the pre-filter", data.label, data.n
        )
    return theta, mask, diagnostics("newton", t0, res, notes=notes)


def fit_lel_refit_lel(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    first = _lel_then_prefilter(data, warm, opts, "lel-refit-lel", t0)
    if isinstance(first, FitFailure):
        return first
    theta, mask, d1 = first
    kept = data.points[mask]
    second = lel_fit_fast(kept, F.ls_theta(kept), extra_starts=theta[None, :])
    return F.make_plane_fit(
        data,
        second.theta,
        method="lel-refit-lel",
        inlier_mask=mask,
        diagnostics=_merge(d1, second, "newton, pre-filter, newton", t0),
    )


def fit_lel_refit_ls(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    first = _lel_then_prefilter(data, warm, opts, "lel-refit-ls", t0)
    if isinstance(first, FitFailure):
        return first
    _, mask, d1 = first
    theta = F.ls_theta(data.points[mask])
    return F.make_plane_fit(
        data,
        theta,
        method="lel-refit-ls",
        inlier_mask=mask,
        diagnostics=_merge(d1, None, "newton, pre-filter, lstsq", t0),
    )


def fit_constant_depth(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    first = _lel_then_prefilter(data, warm, opts, "constant-depth", t0)
    if isinstance(first, FitFailure):
        return first
    theta0, mask0, d1 = first
    # Start on the paper-corrected LS refit (unbiased on axis-aligned walls, close otherwise).
    t_ls = F.ls_theta(data.points[mask0])
    n0, h0 = t_ls / np.linalg.norm(t_ls), 1.0 / float(np.linalg.norm(t_ls))
    n1, h1, _, nit, nev, ok = F.constant_depth_fit(data.capsules, data.distance, n0, h0)
    r = data.capsules @ n1 + data.distance - h1
    mask = F.prefilter_mask(r, opts.prefilter_fraction)
    notes: tuple[str, ...] = ()
    if np.count_nonzero(mask) < 4 or not F.mirror_consistent(n1, data.beam, opts.beam_half_angle):
        notes = ("constant-depth: LEL minimum rejected; refit from the corrected-points plane",)
        n1, h1, mask = n0, h0, mask0
    n2, h2, nit2 = F.constant_depth_ls(data.capsules, data.distance, n1, h1, mask)
    if not F.mirror_consistent(n2, data.beam, opts.beam_half_angle):
        notes += ("constant-depth: LS refit leaves the beam; kept the corrected-points plane",)
        n2, h2 = n0, h0
    diag = SolverDiagnostics(
        solver="newton, pre-filter, lstsq; constant-depth newton, pre-filter, gauss-newton",
        starts=d1.starts + 1,
        iterations=d1.iterations + nit + nit2,
        evaluations=d1.evaluations + nev + nit2,
        time_s=time.perf_counter() - t0,
        converged=d1.converged and ok,
        notes=d1.notes + notes,
    )
    return F.make_plane_fit(
        data, n2 / h2, method="constant-depth", inlier_mask=mask, diagnostics=diag, model="constant-depth"
    )


def _tilt_checked(data: F.PlaneData, first: PlaneFit, opts: FitOptions, method: str) -> PlaneResult:
    """Keep ``first``'s corrected-points normal unless a χ² test shows a tilted wall (see ``"adaptive"``).

    Fits the constant-depth LS on ``first``'s inliers; if the corrected-points
    normal is more than ``opts.tilt_test_sigma`` σ from it, returns the
    constant-depth plane, else ``first``'s normal with the offset from the
    mirror-echo condition over the inliers.
    """
    t0 = time.perf_counter()
    mask = first.inlier_mask
    n_cd, h_cd, nit = F.constant_depth_ls(data.capsules, data.distance, first.normal, first.offset, mask)
    r = data.capsules @ n_cd + data.distance - h_cd
    mask_cd = F.prefilter_mask(r, opts.prefilter_fraction)
    if np.count_nonzero(mask_cd) >= 4:
        n_cd, h_cd, nit2 = F.constant_depth_ls(data.capsules, data.distance, n_cd, h_cd, mask_cd)
        nit += nit2
    else:
        mask_cd = mask
    theta_cd = n_cd / h_cd
    cov = F.theta_covariance(theta_cd, data.capsules, data.distance, mask_cd)
    jn = (np.eye(3) - np.outer(n_cd, n_cd)) * h_cd
    cov_n = jn @ cov @ jn.T
    dn = first.normal - n_cd
    chi2 = float(dn @ np.linalg.pinv(cov_n, rcond=1e-10, hermitian=True) @ dn) if np.all(np.isfinite(cov_n)) else 0.0
    tilted = chi2 > opts.tilt_test_sigma**2 and F.mirror_consistent(n_cd, data.beam, opts.beam_half_angle)
    angle = np.rad2deg(np.arccos(np.clip(first.normal @ n_cd, -1.0, 1.0)))
    note = f"tilt test: corrected-points normal {angle:.2f}° from the constant-depth normal, chi2 = {chi2:.1f} -> " + (
        "constant-depth plane" if tilted else "corrected-points normal, mirror-echo offset"
    )
    d = first.diagnostics
    diag = SolverDiagnostics(
        solver=d.solver + "; constant-depth gauss-newton",
        starts=d.starts,
        iterations=d.iterations + nit,
        evaluations=d.evaluations + nit,
        time_s=d.time_s + time.perf_counter() - t0,
        converged=d.converged,
        notes=d.notes + (note,),
    )
    if tilted:
        return F.make_plane_fit(
            data, theta_cd, method=method, inlier_mask=mask_cd, diagnostics=diag, model="constant-depth"
        )
    h = float(np.mean(data.capsules[mask] @ first.normal + data.distance[mask]))
    return F.make_plane_fit(data, first.normal / h, method=method, inlier_mask=mask, diagnostics=diag)


def fit_adaptive(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    """``"lel-refit-ls"`` on the corrected points, checked against the mirror-echo model.

    The paper's correction assumes the wall's normal is an axis.  On such a
    wall its points are exact and spread over the whole pseudo-patch, so the
    fitted normal is as precise as it gets (~0.05°).  The constant-depth model
    ``n · p_c + d = h`` needs no assumption, but only the capsules' few-cm lever
    arm pins its normal down (~0.6° median, up to 2°), while its offset given a
    normal is very precise.  So:

    1. fit ``"lel-refit-ls"`` (normal ``n_p``) and, on the same inliers, the
       constant-depth LS (normal ``n_c`` with covariance ``C``);
    2. if ``n_p`` is more than ``opts.tilt_test_sigma`` σ from ``n_c``
       (χ² = Δnᵀ C⁺ Δn, 2 dof) the wall is tilted where the correction cannot
       see it: return the constant-depth plane;
    3. otherwise keep ``n_p`` and take the offset from the mirror-echo
       condition, ``h = mean(n_p · p_c + d)`` over the inliers — this removes the
       correction's offset bias on walls it gets the direction of (e.g. a wall
       yawed about z, where the corrected points sit on a plane ~2 mm too near).
    """
    first = fit_lel_refit_ls(data, warm, opts)
    if not isinstance(first, PlaneFit):
        return first
    return _tilt_checked(data, first, opts, "adaptive")
