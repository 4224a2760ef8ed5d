"""The reconstruction pipeline and its registry of methods (paper §4–5).

``reconstruct(gamma, distance, sensor_energy, geometry, energy_model, method=...)``
runs the paper's steps on a full or partial scan:

1. energy ratio ``R`` (eq. 10–12) and the critical step (§4);
2. split into the subsets before and after it;
3. data points (eq. 9) and the reflection-direction correction (§4, Fig. 7);
4. one plane per subset with the chosen method;
5. the corner edge where the two planes meet.

Methods (``METHODS``, name → :class:`Method`):

``"ls"``
    Least squares on the corrected points, eq. (15).
``"lel-nm"``
    The paper's LEL (§5.2): six-start Nelder-Mead, no pre-filter.
``"paper"``
    The paper's full procedure: ``"lel-nm"``, the 10 % pre-filter, and a
    six-start Nelder-Mead LEL refit (§5.3).
``"lel"``
    Fast LEL (closed-form gradient and Hessian, Newton) with the outlier-cluster
    guard, no pre-filter.
``"lel-refit-lel"``
    Fast LEL + guard, 10 % pre-filter, fast LEL refit (the paper's procedure
    with the fast solver).
``"lel-refit-ls"``
    Fast LEL + guard, 10 % pre-filter, LS refit on the kept points.
``"constant-depth"``
    Starts from ``"lel-refit-ls"`` and fits the mirror-echo model
    ``n · p_c + d = h`` with the LEL cost, then pre-filters and refits it by LS.
    No axis-aligned assumption: unbiased on tilted walls.
``"adaptive"``
    ``"lel-refit-ls"``'s normal with the offset from the mirror-echo
    condition; replaced by the constant-depth LS fit on the same inliers when
    a χ² test on the normals shows the wall is tilted.
``"fcm-ransac"``
    The baseline of §5.4: FCM (3 clusters) + RANSAC, seeded.

:data:`DEFAULT_METHOD` is ``"adaptive"``, chosen by ``lelsonar bench estimators``
(``tools/bench_estimators.py``, 50 seeds × 5 scenes, planes a and b pooled):
on the paper's scenes it equals the LS refit's normal (median 0.055°,
p95 0.15°) with a slightly better offset (patch error median 0.020–0.021 cm,
0.55× the foot-point oracle); on tilted walls it is the only registered
method without a catastrophic (> 2°) fit on the preset and 8°-pitched scenes
(median 0.20° / 0.12°, where the paper-corrected methods are biased by the
tilt).  LEL alone: 0.068°, 0.028 cm; the paper's LEL refit after the
pre-filter: 0.057° median but 0.41° p95 and 0.076 cm (2× worse); the fast LEL
refit: 0.37°, 0.14 cm.

Warm start: ``warm_start=(θ_a, θ_b)`` (either may be None) adds the previous
estimate of each plane — e.g. from the last partial scan in the live service —
as an extra LEL start.  It never replaces θ_LS, so a stale warm start cannot
make the result worse in ``H``; it only helps the solver find the minimum the
previous call found.  ``"ls"``, ``"fcm-ransac"`` ignore it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry, beam_points

from . import fit as F
from .baseline import fuzzy_c_means, ransac_plane
from .corner_model import (ECHO_EDGE, ECHO_OUTLIER, ECHO_WALL_A, ECHO_WALL_B, Wall, fit_corner_model,
                           scan_points)
from .correct import AXIS_Y, AXIS_Z, corrected_points
from .energy import EnergyModel, energy_ratio, total_energy
from .lel import LelResult, lel_fit_fast, lel_fit_nelder_mead, six_starts
from .results import (EdgeLine, FailureReason, FitFailure, PlaneFit, PlaneResult, ScanReconstruction,
                      SolverDiagnostics, Timings)
from .quality import assess_plane
from .split import critical_step, split_subsets

__all__ = [
    "FitOptions",
    "ScanFit",
    "Method",
    "METHODS",
    "DEFAULT_METHOD",
    "register_method",
    "fit_plane",
    "corner_edge",
    "reconstruct",
]


@dataclass(frozen=True)
class FitOptions:
    """Tunables shared by the methods.

    Parameters
    ----------
    prefilter_fraction : float
        The pre-filter keeps ``|e| ≤ fraction · max|e|`` (§5.3: 10 %).
    min_points : int
        Fewer valid points in a subset give ``FitFailure(TOO_FEW_POINTS)``.
    guard : bool
        Run the outlier-cluster guard in the fast LEL methods.
    beam_half_angle : float
        rad.  The mirror-echo condition: a fitted normal further than this from
        every boresight of the subset cannot have produced the subset's echoes.
    inlier_tolerance : float
        m.  A point is an inlier of a candidate plane within this distance
        (guard and RANSAC).  ~3–5× the range noise.
    min_inlier_fraction : float
        The guard distrusts a LEL minimum with fewer inliers than this.
    lel_starts : {"ls", "six"}
        Starts of the fast LEL: θ_LS only (plus the warm start), or the paper's
        six (§5.2).
    tilt_test_sigma : float
        ``"adaptive"`` switches to the constant-depth model when the corrected
        points' normal is this many σ away from it.
    critical_peak_fraction : float
        0 takes the paper's argmax of ``R`` as the critical step; ``f > 0`` the
        centroid of the top ``f`` of the R peak
        (:func:`lelsonar.reconstruct.split.critical_step`).  On 50 seeds each of
        paper-test1/2, tilted and an 8°-pitched L, 4 % put the step within ±1
        of the truth in every scan, the argmax in 57 % overall; on an L rolled
        5° both sit 4–5 steps from the geometric truth (the R plateau moves
        with the walls' normals).
    seed : int
        Seeds the RANSAC/FCM generators (baseline and guard).
    ransac_iterations : int
    """

    prefilter_fraction: float = 0.1
    min_points: int = 8
    guard: bool = True
    beam_half_angle: float = float(np.deg2rad(35.0))
    inlier_tolerance: float = 0.01
    min_inlier_fraction: float = 0.5
    lel_starts: str = "ls"
    tilt_test_sigma: float = 3.0
    critical_peak_fraction: float = 0.04
    seed: int = 0
    ransac_iterations: int = 200
    corner_beam_half_angle: float = float(np.deg2rad(50.0))
    corner_tolerance: float = 0.02

    def __post_init__(self) -> None:
        if not 0 < self.prefilter_fraction <= 1:
            raise ConfigError(f"prefilter_fraction must be in (0, 1], got {self.prefilter_fraction}")
        if self.min_points < 4:
            raise ConfigError(f"min_points must be >= 4, got {self.min_points}")
        if not 0 < self.beam_half_angle < np.pi / 2:
            raise ConfigError(f"beam_half_angle must be in (0, π/2) rad, got {self.beam_half_angle}")
        if not self.inlier_tolerance > 0:
            raise ConfigError(f"inlier_tolerance must be > 0 m, got {self.inlier_tolerance}")
        if not 0 <= self.min_inlier_fraction <= 1:
            raise ConfigError(f"min_inlier_fraction must be in [0, 1], got {self.min_inlier_fraction}")
        if self.lel_starts not in ("ls", "six"):
            raise ConfigError(f"lel_starts must be 'ls' or 'six', got {self.lel_starts!r}")
        if not 0 <= self.critical_peak_fraction < 1:
            raise ConfigError(f"critical_peak_fraction must be in [0, 1), got {self.critical_peak_fraction}")
        if self.ransac_iterations < 1:
            raise ConfigError("ransac_iterations must be >= 1")


#: A plane estimator: (subset, warm start θ or None, options) -> PlaneFit | FitFailure.
PlaneEstimator = Callable[[F.PlaneData, "np.ndarray | None", FitOptions], PlaneResult]


@dataclass(frozen=True)
class Method:
    """One entry of the registry.

    Parameters
    ----------
    name : str
    summary : str
    fit_plane : callable or None
        Fits one subset (:data:`PlaneEstimator`); the pipeline splits the scan.
    fit_scan : callable or None
        Fits the whole scan itself (``"corner"`` and ``"fcm-ransac"``, which do
        their own segmentation): ``(gamma, distance, ratio, geometry, options)
        -> (plane_a, plane_b, critical_step or None)``; a critical step
        replaces the energy peak's (None keeps it).
    """

    name: str
    summary: str
    fit_plane: PlaneEstimator | None = None
    fit_scan: Callable[..., ScanFit] | None = None

    def __post_init__(self) -> None:
        if (self.fit_plane is None) == (self.fit_scan is None):
            raise ConfigError(f"method {self.name!r} needs exactly one of fit_plane and fit_scan")


@dataclass(frozen=True)
class ScanFit:
    """What a scan-level method (``Method.fit_scan``) returns.

    Parameters
    ----------
    plane_a, plane_b : PlaneFit or FitFailure
    data_a, data_b : PlaneData or None
        The points each plane was fitted on (its ``inlier_mask`` indexes them).
    critical_step : int or None
        Replaces the energy peak's critical step; None keeps it.
    """

    plane_a: PlaneResult
    plane_b: PlaneResult
    data_a: F.PlaneData | None = None
    data_b: F.PlaneData | None = None
    critical_step: int | None = None


_REGISTRY: dict[str, Method] = {}
#: Read-only view of the registry: method name → :class:`Method`.
METHODS: Mapping[str, Method] = MappingProxyType(_REGISTRY)


def register_method(method: Method) -> Method:
    """Add ``method`` to :data:`METHODS` (names are unique)."""
    if method.name in _REGISTRY:
        raise ConfigError(f"method {method.name!r} is already registered")
    _REGISTRY[method.name] = method
    return method


# --------------------------------------------------------------------------- plane estimators

def _diag(solver: str, t0: float, res: LelResult | None = None, starts: int = 1, iterations: int = 0,
          evaluations: int = 0, converged: bool = True, notes: tuple[str, ...] = ()) -> SolverDiagnostics:
    if res is not None:
        starts, iterations, evaluations, converged = res.starts, res.iterations, res.evaluations, res.converged
    return SolverDiagnostics(solver=solver, starts=starts, iterations=iterations, evaluations=evaluations,
                             time_s=time.perf_counter() - t0, converged=converged, notes=notes)


def _merge(a: SolverDiagnostics, b: LelResult | None, solver: str, t0: float,
           notes: tuple[str, ...] = ()) -> SolverDiagnostics:
    extra_s = b.starts if b is not None else 0
    extra_i = b.iterations if b is not None else 0
    extra_e = b.evaluations if b is not None else 1
    conv = b.converged if b is not None else a.converged
    return SolverDiagnostics(solver=solver, starts=a.starts + extra_s, iterations=a.iterations + extra_i,
                             evaluations=a.evaluations + extra_e, time_s=time.perf_counter() - t0,
                             converged=conv, notes=a.notes + notes)


def _warm(warm: np.ndarray | None) -> np.ndarray | None:
    if warm is None:
        return None
    w = np.asarray(warm, dtype=np.float64).reshape(3)
    return w[None, :] if np.all(np.isfinite(w)) and np.linalg.norm(w) > 0 else None


def _fit_ls(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    theta = F.ls_theta(data.points)
    return F.make_plane_fit(data, theta, method="ls", inlier_mask=np.ones(data.n, dtype=bool),
                            diagnostics=_diag("lstsq", t0))


def _fit_lel_nm(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    res = lel_fit_nelder_mead(data.points, F.ls_theta(data.points), extra_starts=_warm(warm))
    return F.make_plane_fit(data, res.theta, method="lel-nm", inlier_mask=np.ones(data.n, dtype=bool),
                            diagnostics=_diag("nelder-mead", t0, res))


def _prefiltered(data: F.PlaneData, theta: np.ndarray, opts: FitOptions) -> np.ndarray:
    return F.prefilter_mask(F.fitting_errors(data.points, theta), opts.prefilter_fraction)


def _fit_paper(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    first = lel_fit_nelder_mead(data.points, F.ls_theta(data.points), extra_starts=_warm(warm))
    mask = _prefiltered(data, first.theta, opts)
    if np.count_nonzero(mask) < 4:
        return FitFailure(FailureReason.TOO_FEW_POINTS, "paper: fewer than 4 points survive the pre-filter",
                          data.label, data.n)
    kept = data.points[mask]
    second = lel_fit_nelder_mead(kept, F.ls_theta(kept))
    d1 = _diag("nelder-mead", t0, first)
    return F.make_plane_fit(data, second.theta, method="paper", inlier_mask=mask,
                            diagnostics=_merge(d1, second, "nelder-mead x6, pre-filter, nelder-mead x6", t0))


def _guarded_lel(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions,
                 rng: np.random.Generator) -> tuple[np.ndarray, LelResult, tuple[str, ...]]:
    """Fast LEL (eq. 8) with the outlier-cluster guard.

    LEL is local, and its cost can have a minimum on a plane through the tight
    cluster of double-bounce echoes behind the corner (design notes §9).  Each
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
    extra = [] if _warm(warm) is None else [_warm(warm)]
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
        total = replace(res, starts=res.starts + alt.starts, iterations=res.iterations + alt.iterations,
                        evaluations=res.evaluations + alt.evaluations, time_s=res.time_s + alt.time_s,
                        candidates=np.asarray(cands), candidate_entropy=np.asarray(hs))
    pick = max(range(len(cands)), key=lambda i: (scores[i][0], scores[i][1], -hs[i]))
    if not scores[pick][0]:
        raise _Inconsistent(f"no LEL minimum has its normal within {np.rad2deg(opts.beam_half_angle):.0f}° of a "
                            "boresight of the subset: no wall seen face-on (is the corner reached yet?)")
    if pick == best:
        notes.append("guard: no better minimum found; kept the least-H one")
    else:
        notes.append(f"guard: switched to minimum {pick} (mirror-consistent={scores[pick][0]}, "
                     f"inliers={scores[pick][1]}/{data.n}, H {hs[best]:.4f} -> {hs[pick]:.4f})")
    return cands[pick], replace(total, theta=cands[pick], entropy=hs[pick]), tuple(notes)


class _Inconsistent(Exception):
    """No candidate plane satisfies the mirror-echo condition."""


def _rng(opts: FitOptions, label: str) -> np.random.Generator:
    return np.random.default_rng([opts.seed, ord(label[0]) if label else 0])


def _fit_lel(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    theta, res, notes = _guarded_lel(data, warm, opts, _rng(opts, data.label))
    mask = _prefiltered(data, theta, opts)  # reported inliers: the §5.3 criterion
    return F.make_plane_fit(data, theta, method="lel", inlier_mask=mask,
                            diagnostics=_diag("newton", t0, res, notes=notes))


def _lel_then_prefilter(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions, name: str,
                        t0: float) -> tuple[np.ndarray, np.ndarray, SolverDiagnostics] | FitFailure:
    theta, res, notes = _guarded_lel(data, warm, opts, _rng(opts, data.label))
    mask = _prefiltered(data, theta, opts)
    if np.count_nonzero(mask) < 4:
        return FitFailure(FailureReason.TOO_FEW_POINTS, f"{name}: fewer than 4 points survive the pre-filter",
                          data.label, data.n)
    return theta, mask, _diag("newton", t0, res, notes=notes)


def _fit_lel_refit_lel(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    first = _lel_then_prefilter(data, warm, opts, "lel-refit-lel", t0)
    if isinstance(first, FitFailure):
        return first
    theta, mask, d1 = first
    kept = data.points[mask]
    second = lel_fit_fast(kept, F.ls_theta(kept), extra_starts=theta[None, :])
    return F.make_plane_fit(data, second.theta, method="lel-refit-lel", inlier_mask=mask,
                            diagnostics=_merge(d1, second, "newton, pre-filter, newton", t0))


def _fit_lel_refit_ls(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    first = _lel_then_prefilter(data, warm, opts, "lel-refit-ls", t0)
    if isinstance(first, FitFailure):
        return first
    _, mask, d1 = first
    theta = F.ls_theta(data.points[mask])
    return F.make_plane_fit(data, theta, method="lel-refit-ls", inlier_mask=mask,
                            diagnostics=_merge(d1, None, "newton, pre-filter, lstsq", t0))


def _fit_constant_depth(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
    t0 = time.perf_counter()
    first = _lel_then_prefilter(data, warm, opts, "constant-depth", t0)
    if isinstance(first, FitFailure):
        return first
    theta0, mask0, d1 = first
    # Start on the paper-corrected LS refit (unbiased on axis-aligned walls, close otherwise).
    t_ls = F.ls_theta(data.points[mask0])
    n0, h0 = t_ls / np.linalg.norm(t_ls), 1.0 / np.linalg.norm(t_ls)
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
    diag = SolverDiagnostics(solver="newton, pre-filter, lstsq; constant-depth newton, pre-filter, gauss-newton",
                             starts=d1.starts + 1, iterations=d1.iterations + nit + nit2,
                             evaluations=d1.evaluations + nev + nit2, time_s=time.perf_counter() - t0,
                             converged=d1.converged and ok, notes=d1.notes + notes)
    return F.make_plane_fit(data, n2 / h2, method="constant-depth", inlier_mask=mask, diagnostics=diag,
                            model="constant-depth")


def _tilt_checked(data: F.PlaneData, first: PlaneFit, opts: FitOptions, method: str, *,
                  prefilter: bool = True) -> PlaneResult:
    """Keep ``first``'s corrected-points normal unless a χ² test shows a tilted wall (see ``"adaptive"``).

    Fits the constant-depth LS on ``first``'s inliers; if the corrected-points
    normal is more than ``opts.tilt_test_sigma`` σ from it, returns the
    constant-depth plane, else ``first``'s normal with the offset from the
    mirror-echo condition over the inliers.  ``prefilter`` re-selects the
    constant-depth inliers with the §5.3 pre-filter (for subsets that still hold
    outliers); without it the inliers stay ``first``'s.
    """
    t0 = time.perf_counter()
    mask = first.inlier_mask
    n_cd, h_cd, nit = F.constant_depth_ls(data.capsules, data.distance, first.normal, first.offset, mask)
    r = data.capsules @ n_cd + data.distance - h_cd
    mask_cd = F.prefilter_mask(r, opts.prefilter_fraction) if prefilter else mask
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
    note = (f"tilt test: corrected-points normal {angle:.2f}° from the constant-depth normal, "
            f"chi2 = {chi2:.1f} -> " + ("constant-depth plane" if tilted else "corrected-points normal, "
                                        "mirror-echo offset"))
    d = first.diagnostics
    diag = SolverDiagnostics(solver=d.solver + "; constant-depth gauss-newton", starts=d.starts,
                             iterations=d.iterations + nit, evaluations=d.evaluations + nit,
                             time_s=d.time_s + time.perf_counter() - t0, converged=d.converged,
                             notes=d.notes + (note,))
    if tilted:
        return F.make_plane_fit(data, theta_cd, method=method, inlier_mask=mask_cd, diagnostics=diag,
                                model="constant-depth")
    h = float(np.mean(data.capsules[mask] @ first.normal + data.distance[mask]))
    return F.make_plane_fit(data, first.normal / h, method=method, inlier_mask=mask, diagnostics=diag)


def _fit_adaptive(data: F.PlaneData, warm: np.ndarray | None, opts: FitOptions) -> PlaneResult:
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
    first = _fit_lel_refit_ls(data, warm, opts)
    if not isinstance(first, PlaneFit):
        return first
    return _tilt_checked(data, first, opts, "adaptive")


# --------------------------------------------------------------------------- joint corner model (scan level)

def _corner_wall(data: F.PlaneData, wall: Wall, wall_se: tuple[float, float], opts: FitOptions, t0: float,
                 note: str) -> PlaneResult:
    """One wall of the joint model, refined on its own echoes.

    The paper-corrected points (§4) give the most precise normal when the wall
    is axis-aligned; the joint model (mirror and edge echoes together) is
    unbiased whatever the tilt.  If the LS normal of the corrected points
    (eq. 15) agrees with the joint normal within ``opts.tilt_test_sigma`` of the
    joint standard error, keep it with the offset from the mirror-echo
    condition; otherwise keep the joint wall.  Either way the reported
    standard errors are the joint model's at least: the corrected points
    cannot see a tilt below that, so their own covariance would overclaim.
    """
    mask = np.ones(data.n, dtype=bool)
    theta_p = F.ls_theta(data.points)
    n_p = theta_p / np.linalg.norm(theta_p)
    se_n, se_h = wall_se
    angle = float(np.arccos(np.clip(n_p @ wall.normal, -1.0, 1.0)))
    agree = np.isfinite(se_n) and angle <= opts.tilt_test_sigma * se_n
    if agree:
        h = float(np.mean(data.capsules @ n_p + data.distance))
        theta, model = n_p / h, "paper"
    else:
        theta, model = wall.normal / wall.offset, "constant-depth"
    verdict = ("corrected-points normal, mirror-echo offset" if agree else "joint-model wall")
    diag = _diag("corner model; lstsq", t0, notes=(note, f"joint normal {np.rad2deg(angle):.2f}° from the "
                                                    f"corrected-points normal (joint σ {np.rad2deg(se_n):.2f}°) -> "
                                                    + verdict))
    fit = F.make_plane_fit(data, theta, method="corner", inlier_mask=mask, diagnostics=diag, model=model)
    if isinstance(fit, PlaneFit) and np.isfinite(se_n) and np.isfinite(se_h):
        fit = replace(fit, normal_stderr=max(fit.normal_stderr, se_n), offset_stderr=max(fit.offset_stderr, se_h))
    return fit


def _fit_corner(gamma: np.ndarray, distance: np.ndarray, ratio: np.ndarray, geometry: ArrayGeometry,
                opts: FitOptions) -> ScanFit:
    """Both walls and the edge from all the echoes (:mod:`lelsonar.reconstruct.corner_model`).

    The joint model labels every echo (wall a, wall b, edge, outlier); each
    wall is then refined on its own echoes exactly as ``"adaptive"`` refines
    its inliers: LS on the paper-corrected points (§4, eq. 15), the χ² tilt
    test against the constant-depth model, the mirror-echo offset.  The
    critical step is where the boresight points at the fitted edge, which
    does not scatter with the energy noise.  Where the joint model finds no
    bands (too few echoes), it falls back to ``"adaptive"`` on the energy split.
    """
    t0 = time.perf_counter()
    g = np.asarray(gamma, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    pts = scan_points(geometry, g, d)
    model = fit_corner_model(pts, AXIS_Y, AXIS_Z, beam_half_angle=opts.corner_beam_half_angle,
                             tolerance=opts.corner_tolerance, min_points=opts.min_points)
    if model is None:
        crit = critical_step(ratio, opts.critical_peak_fraction)
        split = split_subsets(g, crit)
        data = [F.plane_data(geometry, g, d, steps, label, axis)
                for steps, label, axis in ((split.steps_a, "a", AXIS_Y), (split.steps_b, "b", AXIS_Z))]
        out = [fit_plane(dd, "adaptive", options=opts) for dd in data]
        return ScanFit(out[0], out[1], data[0], data[1], crit)
    note = (f"corner model: {model.hypotheses} band pairs; echoes: {model.count(ECHO_WALL_A)} wall a, "
            f"{model.count(ECHO_WALL_B)} wall b, {model.count(ECHO_EDGE)} edge, "
            f"{model.count(ECHO_OUTLIER)} outliers (tolerance {1000 * model.tolerance:.0f} mm)")
    out: list[PlaneResult] = []
    datas: list[F.PlaneData] = []
    for k, label, axis, wall in ((ECHO_WALL_A, "a", AXIS_Y, model.wall_a), (ECHO_WALL_B, "b", AXIS_Z, model.wall_b)):
        sel = np.full(d.shape, np.nan)
        m = model.labels == k
        sel[pts.step[m], pts.capsule_index[m]] = pts.distance[m]
        data = F.plane_data(geometry, g, sel, np.unique(pts.step[m]), label, axis)
        datas.append(data)
        fail = F.check_points(data.points, label, opts.min_points)
        if fail is not None:
            out.append(FitFailure(fail.reason, f"corner: {int(np.count_nonzero(m))} echoes of wall {label}; "
                                  + fail.detail, label, fail.n_points))
            continue
        fit = _corner_wall(data, wall, model.wall_stderr(k), opts, t0, note)
        out.append(assess_plane(fit, g, edge_echoes=model.count(ECHO_EDGE)) if isinstance(fit, PlaneFit) else fit)
    # The critical step: where the boresight points at the edge of the final planes.  The common
    # roll of both walls about x barely changes any range, so the corrected-points normals (which
    # assume the walls are axis-aligned unless the data say otherwise) pin it better than the joint fit.
    edge = corner_edge(out[0], out[1])
    crit = None
    if isinstance(edge, EdgeLine):
        point = edge.point
        if abs(edge.direction[0]) > 1e-9:
            point = point - edge.direction * (point[0] / edge.direction[0])
        crit = int(np.argmin(np.abs(g - np.arctan2(point[2], point[1]))))
    return ScanFit(out[0], out[1], datas[0], datas[1], crit)


# --------------------------------------------------------------------------- baseline (scan level)

def _fit_fcm_ransac(gamma: np.ndarray, distance: np.ndarray, ratio: np.ndarray, geometry: ArrayGeometry,
                    opts: FitOptions) -> ScanFit:
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
        return ScanFit(FitFailure(f.reason, f.detail, "a", f.n_points),
                       FitFailure(f.reason, f.detail, "b", f.n_points))
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
        out.append(F.make_plane_fit(data, rs.normal / rs.offset, method="fcm-ransac", inlier_mask=rs.inliers,
                                    diagnostics=_diag("fcm+ransac", t0, starts=rs.iterations,
                                                      iterations=fcm.iterations, converged=fcm.converged)))
    return ScanFit(out[0], out[1], datas[0], datas[1])


# --------------------------------------------------------------------------- registry

register_method(Method("ls", "least squares on the corrected points (eq. 15)", fit_plane=_fit_ls))
register_method(Method("lel-nm", "paper §5.2: six-start Nelder-Mead LEL", fit_plane=_fit_lel_nm))
register_method(Method("paper", "paper §5.2-5.3: six-start Nelder-Mead LEL, 10 % pre-filter, LEL refit",
                       fit_plane=_fit_paper))
register_method(Method("lel", "fast LEL (Newton, closed-form derivatives) with the cluster guard",
                       fit_plane=_fit_lel))
register_method(Method("lel-refit-lel", "fast LEL + guard, 10 % pre-filter, fast LEL refit",
                       fit_plane=_fit_lel_refit_lel))
register_method(Method("lel-refit-ls", "fast LEL + guard, 10 % pre-filter, LS refit", fit_plane=_fit_lel_refit_ls))
register_method(Method("constant-depth", "mirror-echo model n·p_c + d = h: LEL, pre-filter, LS refit",
                       fit_plane=_fit_constant_depth))
register_method(Method("adaptive", "lel-refit-ls, or the constant-depth LS fit where a χ² test shows a tilted wall",
                       fit_plane=_fit_adaptive))
register_method(Method("corner", "joint model of both walls and the edge over all echoes, then adaptive refits",
                       fit_scan=_fit_corner))
register_method(Method("fcm-ransac", "paper §5.4 baseline: FCM (3 clusters) + RANSAC", fit_scan=_fit_fcm_ransac))

#: The method :func:`reconstruct` uses by default (chosen by the benchmark).
DEFAULT_METHOD = "corner"


# --------------------------------------------------------------------------- public API

def fit_plane(data: F.PlaneData, method: str = DEFAULT_METHOD, *, warm_start: np.ndarray | None = None,
              options: FitOptions | None = None) -> PlaneResult:
    """Fit one subset with a registered plane method.

    Parameters
    ----------
    data : PlaneData
        From :func:`lelsonar.reconstruct.fit.plane_data`.
    method : str
        A key of :data:`METHODS` with a ``fit_plane``.
    warm_start : (3,) array, optional
        A previous θ for this plane (extra LEL start).
    options : FitOptions, optional
    """
    m = _method(method)
    if m.fit_plane is None:
        raise ConfigError(f"method {method!r} fits whole scans; use reconstruct()")
    opts = options or FitOptions()
    fail = F.check_points(data.points, data.label, opts.min_points)
    if fail is not None:
        return fail
    try:
        return m.fit_plane(data, warm_start, opts)
    except _Inconsistent as exc:
        return FitFailure(FailureReason.DEGENERATE_GEOMETRY, f"{method}: {exc}", data.label, data.n)
    except np.linalg.LinAlgError as exc:
        return FitFailure(FailureReason.SOLVER_FAILED, f"{method}: {exc}", data.label, data.n)


def _method(name: str) -> Method:
    try:
        return METHODS[name]
    except KeyError:
        raise ConfigError(f"unknown reconstruction method {name!r}; choose one of {sorted(METHODS)}") from None


def corner_edge(plane_a: PlaneResult, plane_b: PlaneResult, *, min_angle: float = np.deg2rad(5.0)
                ) -> EdgeLine | FitFailure:
    """The line where the two planes meet.

    Direction ``n_a × n_b`` (normalised); point: the point of the line closest
    to the origin, solving ``n_a·x = h_a``, ``n_b·x = h_b``, ``dir·x = 0``.

    Returns FitFailure if a plane is missing or the planes are within
    ``min_angle`` of parallel.
    """
    if not isinstance(plane_a, PlaneFit) or not isinstance(plane_b, PlaneFit):
        return FitFailure(FailureReason.TOO_FEW_POINTS, "the edge needs both planes", "edge", 0)
    na, nb = plane_a.normal, plane_b.normal
    cr = np.cross(na, nb)
    s = float(np.linalg.norm(cr))
    angle = float(np.arccos(np.clip(na @ nb, -1.0, 1.0)))
    if s < np.sin(min_angle):
        return FitFailure(FailureReason.DEGENERATE_GEOMETRY,
                          f"the planes are {np.rad2deg(angle):.1f}° apart, nearly parallel", "edge", 0)
    direction = cr / s
    a = np.stack([na, nb, direction])
    point = np.linalg.solve(a, np.array([plane_a.offset, plane_b.offset, 0.0]))
    # First order: an offset error δh moves the line by δh / sin(angle); a tilt δ of a normal moves it by h·δ
    # and turns it by δ / sin(angle).
    point_se = float(np.sqrt(plane_a.offset_stderr**2 + plane_b.offset_stderr**2
                             + (plane_a.offset * plane_a.normal_stderr)**2
                             + (plane_b.offset * plane_b.normal_stderr)**2) / s)
    direction_se = float(np.hypot(plane_a.normal_stderr, plane_b.normal_stderr) / s)
    return EdgeLine(point=point, direction=direction, angle=angle, point_stderr=point_se,
                    direction_stderr=direction_se)


def _assessed(plane: PlaneResult, gamma: np.ndarray) -> PlaneResult:
    """The plane with its trust verdict (:mod:`lelsonar.reconstruct.quality`), unless it has one."""
    if isinstance(plane, PlaneFit) and not plane.quality:
        return assess_plane(plane, gamma)
    return plane


def _validate_inputs(gamma: np.ndarray, distance: np.ndarray, sensor_energy: np.ndarray,
                     geometry: ArrayGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    g = np.asarray(gamma, dtype=np.float64).ravel()
    d = np.asarray(distance, dtype=np.float64)
    e = np.asarray(sensor_energy, dtype=np.float64)
    n = g.shape[0]
    if d.shape != (n, geometry.n_capsules):
        raise ConfigError(f"distance must have shape ({n}, {geometry.n_capsules}), got {d.shape}")
    if e.shape not in ((n, geometry.n_capsules), (n,)):
        raise ConfigError(f"sensor_energy must have shape ({n}, {geometry.n_capsules}) or ({n},), got {e.shape}")
    if not np.all(np.isfinite(g)):
        raise ConfigError("gamma must be finite (rad)")
    if np.any(np.isinf(d)) or np.any(d[np.isfinite(d)] < 0):
        raise ConfigError("distances must be finite and >= 0 m, or NaN for no echo")
    return g, d, e


def reconstruct(gamma: np.ndarray, distance: np.ndarray, sensor_energy: np.ndarray, geometry: ArrayGeometry,
                energy_model: EnergyModel, method: str = DEFAULT_METHOD, *,
                warm_start: tuple[np.ndarray | None, np.ndarray | None] | None = None,
                options: FitOptions | None = None) -> ScanReconstruction:
    """Reconstruct the two planes of an L-shaped corner from a (partial) scan (paper §4–5).

    Parameters
    ----------
    gamma : (n_steps,) array
        Measured rotation of each step, rad.
    distance : (n_steps, n_capsules) array
        Ranges, m; NaN where a capsule got no echo.
    sensor_energy : (n_steps, n_capsules) or (n_steps,) array
        Per-capsule waveform energy ``E_i^γ`` (eq. 10), V²·s, or the step
        totals ``E^γ`` (eq. 11).
    geometry : ArrayGeometry
    energy_model : EnergyModel
        ``E0(d)`` of eq. (12).
    method : str
        A key of :data:`METHODS`; :data:`DEFAULT_METHOD` by default.
    warm_start : (θ_a, θ_b), optional
        Previous estimates (1/m), either may be None; used as extra LEL
        starts (the live service passes the last partial scan's planes).
    options : FitOptions, optional

    Returns
    -------
    ScanReconstruction
        Always returns; planes or the edge that cannot be estimated are
        :class:`FitFailure` with a reason.  Works on partial scans: with the
        corner not reached yet, the critical step is the best step so far and
        the missing subset is a ``TOO_FEW_POINTS`` failure.

    Raises
    ------
    ConfigError
        On malformed inputs (shapes, non-finite angles, negative ranges) or an
        unknown method.
    """
    t0 = time.perf_counter()
    m = _method(method)
    opts = options or FitOptions()
    g, d, e = _validate_inputs(gamma, distance, sensor_energy, geometry)
    step_energy = e if e.ndim == 1 else total_energy(e)
    ratio = energy_ratio(step_energy, d, energy_model) if g.size else np.zeros(0)
    crit = critical_step(ratio, opts.critical_peak_fraction) if g.size else None
    warm_a, warm_b = warm_start if warm_start is not None else (None, None)
    if crit is None:
        t1 = time.perf_counter()
        fa = FitFailure(FailureReason.TOO_FEW_POINTS, "no step with an echo yet", "a", 0)
        fb = FitFailure(FailureReason.TOO_FEW_POINTS, "no step with an echo yet", "b", 0)
        return ScanReconstruction(method, int(g.size), None, float("nan"), fa, fb, corner_edge(fa, fb),
                                  Timings(t1 - t0, 0.0, 0.0, t1 - t0))
    if m.fit_scan is not None:
        t1 = time.perf_counter()
        sf = m.fit_scan(g, d, ratio, geometry, opts)
        pa, pb = _assessed(sf.plane_a, g), _assessed(sf.plane_b, g)
        crit = crit if sf.critical_step is None else sf.critical_step
        t2 = time.perf_counter()
        ta = pa.diagnostics.time_s if isinstance(pa, PlaneFit) else 0.0
        edge = corner_edge(pa, pb)
        return ScanReconstruction(method, int(g.size), crit, float(g[crit]), pa, pb, edge,
                                  Timings(t1 - t0, ta, max(t2 - t1 - ta, 0.0), time.perf_counter() - t0),
                                  sf.data_a, sf.data_b)
    split = split_subsets(g, crit)
    data_a = F.plane_data(geometry, g, d, split.steps_a, "a", AXIS_Y)
    data_b = F.plane_data(geometry, g, d, split.steps_b, "b", AXIS_Z)
    t1 = time.perf_counter()
    pa = fit_plane(data_a, method, warm_start=warm_a, options=opts)
    t2 = time.perf_counter()
    pb = fit_plane(data_b, method, warm_start=warm_b, options=opts)
    pa, pb = _assessed(pa, g), _assessed(pb, g)
    t3 = time.perf_counter()
    edge = corner_edge(pa, pb)
    return ScanReconstruction(method, int(g.size), crit, float(g[crit]), pa, pb, edge,
                              Timings(t1 - t0, t2 - t1, t3 - t2, time.perf_counter() - t0), data_a, data_b)


# Re-exported for callers that want the raw points.
__all__ += ["beam_points", "corrected_points", "split_subsets", "critical_step"]
