"""Plane fitting blocks: LS, fitting errors, MAD, pre-filter, covariance, the
constant-depth model, the outlier-cluster guard, and :class:`PlaneFit` assembly.

Paper references: LS is eq. (15); the fitting error is eq. (20); MAD and σ are
eq. (21)–(22); the pre-filter is §5.3.  Two plane models share one residual:

* **paper model** — points ``v`` (the paper's corrected points, §4) on the plane
  ``θ · v = 1``; metric residual ``(θ · v − 1) / |θ|``;
* **constant-depth model** — the mirror-echo condition ``n · p_c + d = h``
 : the perpendicular distance from the capsule ``p_c`` to the
  wall equals the measured range ``d``.  With ``θ = n / h`` its metric residual
  is ``(θ · p_c − 1) / |θ| + d``, i.e. the paper model with the capsules as
  points, shifted by the range.  It needs no assumption on the wall's
  direction, so it stays unbiased on tilted walls where the paper's correction
  (which assumes ``n`` is an axis) is not.

In both cases the relative error of eq. (20) is the metric residual times
``|θ| = 1/h``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry, boresight
from lelsonar.reconstruct.estimate.constant_depth import constant_depth_fit, constant_depth_ls
from lelsonar.reconstruct.estimate.correct import COS_MAX_CORRECTION, corrected_point
from lelsonar.reconstruct.estimate.lel import residual_entropy
from lelsonar.reconstruct.estimate.normals import (
    norm,
    normal_offset_stderr,
    normal_offset_stderr_of,
    observed_patch,
    observed_patch_of,
    theta_covariance,
    theta_covariance_of,
)
from lelsonar.reconstruct.estimate.results import FailureReason, FitFailure, PlaneFit, SolverDiagnostics
from lelsonar.reconstruct.estimate.robust import MAD_K, fast_median, mad, mad_of, mad_sigma, prefilter_mask
from lelsonar.signal.compiled import kernel

__all__ = [
    "MAD_K",
    "PlaneData",
    "plane_data",
    "plane_data_of",
    "check_points",
    "ls_theta",
    "fitting_errors",
    "metric_residuals",
    "mad",
    "mad_sigma",
    "prefilter_mask",
    "theta_covariance",
    "normal_offset_stderr",
    "observed_patch",
    "constant_depth_fit",
    "constant_depth_ls",
    "mirror_consistent",
    "inlier_count",
    "make_plane_fit",
]


def _ro(a: np.ndarray, dtype: type = np.float64) -> np.ndarray:
    out: np.ndarray = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


@dataclass(frozen=True)
class PlaneData:
    """The valid points of one subset, with what each model needs.

    Parameters
    ----------
    label : str
        ``"a"`` or ``"b"``.
    axis : (3,) array
        The normal assumed by the paper's correction (``y`` for a, ``z`` for b).
    points : (N, 3) array
        The paper's corrected points ``v_i`` (§4), m.
    capsules : (N, 3) array
        Capsule position ``p_c`` of each point, m.
    distance : (N,) array
        Measured range ``d`` of each point, m.
    beam : (N, 3) array
        Unit boresight of each point.
    step : (N,) int array
        Step index of each point in the scan.
    """

    label: str
    axis: np.ndarray
    points: np.ndarray
    capsules: np.ndarray
    distance: np.ndarray
    beam: np.ndarray
    step: np.ndarray

    def __post_init__(self) -> None:
        for name in ("axis", "points", "capsules", "distance", "beam"):
            object.__setattr__(self, name, _ro(getattr(self, name)))
        object.__setattr__(self, "step", _ro(self.step, np.intp))
        n = self.points.shape[0]
        if (
            self.points.shape != (n, 3)
            or self.capsules.shape != (n, 3)
            or self.beam.shape != (n, 3)
            or self.distance.shape != (n,)
            or self.step.shape != (n,)
        ):
            raise ConfigError("PlaneData arrays must agree: points, capsules, beam (N, 3); distance, step (N,)")
        if not (
            np.isfinite(self.points).all() and np.isfinite(self.capsules).all() and np.isfinite(self.distance).all()
        ):
            raise ConfigError("PlaneData holds only valid (finite) points")

    @property
    def n(self) -> int:
        return int(self.points.shape[0])

    def subset(self, mask: np.ndarray) -> PlaneData:
        m = np.asarray(mask, dtype=bool)
        if m.shape != (self.n,):
            raise ConfigError(f"a subset mask must have shape ({self.n},), got {m.shape}")
        # Valid points stay valid, and boolean indexing copies; the axis is frozen, so shared.
        return PlaneData._owned(
            self.label, self.axis, self.points[m], self.capsules[m], self.distance[m], self.beam[m], self.step[m]
        )

    @classmethod
    def _owned(
        cls,
        label: str,
        axis: np.ndarray,
        points: np.ndarray,
        capsules: np.ndarray,
        distance: np.ndarray,
        beam: np.ndarray,
        step: np.ndarray,
    ) -> PlaneData:
        """Wrap arrays valid by construction that nothing else holds (fresh boolean-indexed copies).

        What ``__init__`` checks holds already (the valid points :func:`plane_data` kept), and the
        arrays are this object's alone: they are made read-only in place rather than copied and
        checked again on the fit's hot path.
        """
        obj = object.__new__(cls)
        for name, a in (
            ("axis", axis),
            ("points", points),
            ("capsules", capsules),
            ("distance", distance),
            ("beam", beam),
            ("step", step),
        ):
            a.setflags(write=False)
            object.__setattr__(obj, name, a)
        object.__setattr__(obj, "label", label)
        return obj

    @classmethod
    def prefix(
        cls,
        label: str,
        axis: np.ndarray,
        n: int,
        points: np.ndarray,
        capsules: np.ndarray,
        distance: np.ndarray,
        beam: np.ndarray,
        step: np.ndarray,
    ) -> PlaneData:
        """The first ``n`` rows of append-only buffers of valid points (rows written once, by
        :func:`plane_data`'s output, and never again): read-only views, neither copied nor checked again.

        What a plane growing point by point hands a fit or a message in O(1), where a copy would cost
        O(points) on every estimate.
        """
        return cls._owned(label, axis, points[:n], capsules[:n], distance[:n], beam[:n], step[:n])


def plane_data(
    geometry: ArrayGeometry, gamma: np.ndarray, distance: np.ndarray, steps: np.ndarray, label: str, axis: np.ndarray
) -> PlaneData:
    """Gather the valid points of the given steps (eq. 9 and the §4 correction).

    Parameters
    ----------
    geometry : ArrayGeometry
    gamma : (n_steps,) array, rad
    distance : (n_steps, n_capsules) array, m (NaN = no echo)
    steps : (k,) int array
        The subset's step indices (from :func:`lelsonar.reconstruct.estimate.split.split_subsets`).
    label : str
    axis : (3,) array
        The paper's assumed normal for this subset.
    """
    steps = np.asarray(steps, dtype=np.intp)
    g = np.asarray(gamma, dtype=np.float64)[steps]
    d = np.asarray(distance, dtype=np.float64)[steps]
    if d.shape != g.shape + (geometry.n_capsules,):
        raise ConfigError(f"distance must have shape {g.shape + (geometry.n_capsules,)}, got {d.shape}")
    return plane_data_of(geometry.capsule_positions(g), boresight(g), d, steps, label, axis)


def plane_data_of(
    capsules: np.ndarray, beam: np.ndarray, distance: np.ndarray, steps: np.ndarray, label: str, axis: np.ndarray
) -> PlaneData:
    """:func:`plane_data` from capsule positions and boresights the caller already has.

    Parameters
    ----------
    capsules : (k, n_capsules, 3) array
        ``p_c`` of each echo slot, m.
    beam : (k, 3) array
        Boresight of each row.
    distance : (k, n_capsules) array, m (NaN = no echo)
    steps : (k,) int array
        Step index of each row.
    label, axis
        As for :func:`plane_data`.

    The rows may be steps (``n_capsules`` slots each), or single echoes (``n_capsules = 1``): the
    corner model's echoes of one wall, with the same numbers as from their steps.
    """
    d = np.asarray(distance, dtype=np.float64)
    ax = np.asarray(axis, dtype=np.float64)
    # One kernel: the corrected points (correct.py's correction, reusing p_c and b) and the kept ones
    # gathered with their boresights and steps, row-major as boolean indexing orders them.  Finite
    # (v = p_c + ... is finite only where p_c is) and of agreeing shapes by construction; the arrays are
    # fresh, so this PlaneData's own (the axis is copied: it may be AXIS_Y).
    points, caps, dist, bm, st = _valid_corrected(
        np.ascontiguousarray(capsules, dtype=np.float64),
        np.ascontiguousarray(beam, dtype=np.float64),
        d,
        np.ascontiguousarray(steps, dtype=np.intp),
        ax / norm(ax),
        COS_MAX_CORRECTION,
    )
    return PlaneData._owned(label, ax.copy(), points, caps, dist, bm, st)


@kernel
def _valid_corrected(
    capsules: np.ndarray, beam: np.ndarray, distance: np.ndarray, steps: np.ndarray, axis: np.ndarray, cos_max: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The valid echoes' corrected points (§4), capsules, ranges, boresights and steps, in row-major order.

    Valid: a finite positive range and a finite corrected point (:func:`corrected_point`).
    """
    k, c = distance.shape
    points = np.empty((k * c, 3))
    caps = np.empty((k * c, 3))
    dist = np.empty(k * c)
    bm = np.empty((k * c, 3))
    st = np.empty(k * c, dtype=np.intp)
    m = 0
    v = np.empty(3)
    for i in range(k):
        for j in range(c):
            dij = distance[i, j]
            if not (np.isfinite(dij) and dij > 0):
                continue
            corrected_point(capsules[i, j], beam[i], dij, axis, cos_max, v)
            if not (np.isfinite(v[0]) and np.isfinite(v[1]) and np.isfinite(v[2])):
                continue
            points[m, 0], points[m, 1], points[m, 2] = v[0], v[1], v[2]
            caps[m, 0], caps[m, 1], caps[m, 2] = capsules[i, j, 0], capsules[i, j, 1], capsules[i, j, 2]
            dist[m] = dij
            bm[m, 0], bm[m, 1], bm[m, 2] = beam[i, 0], beam[i, 1], beam[i, 2]
            st[m] = steps[i]
            m += 1
    return points[:m].copy(), caps[:m].copy(), dist[:m].copy(), bm[:m].copy(), st[:m].copy()


def check_points(points: np.ndarray, label: str, min_points: int = 8) -> FitFailure | None:
    """A typed failure if ``points`` cannot define a plane ``θ · v = 1``, else None.

    Too few points (< ``min_points``); collinear or coincident points (second
    singular value of the centred cloud < 1e-6 of the first, or < 1 mm RMS);
    or a best plane through the scanner (|h| < 1 mm), which eq. (1) cannot
    represent.
    """
    v = np.asarray(points, dtype=np.float64)
    n = v.shape[0]
    if n < max(min_points, 4):
        return FitFailure(FailureReason.TOO_FEW_POINTS, f"{n} valid points, need {max(min_points, 4)}", label, n)
    sv0, sv1 = _spread(v)
    if sv1 < max(1e-6 * sv0, 1e-3):
        return FitFailure(
            FailureReason.DEGENERATE_GEOMETRY,
            f"points are collinear or coincident (spread {sv0:.3g} m × {sv1:.3g} m)",
            label,
            n,
        )
    return None


@kernel
def _spread(v: np.ndarray) -> tuple[float, float]:
    """The two largest RMS spreads of the centred cloud ``v`` (its singular values over ``√N``), m.

    The singular values of the centred ``V`` are the roots of the eigenvalues of its 3×3 scatter
    matrix ``VᵀV`` (a spread ≥ 1 mm of one ≤ a few m squares to a condition far inside float64's).
    """
    n = v.shape[0]
    mean = np.zeros(3)
    for i in range(n):  # the row-by-row sums of v.mean(axis=0)
        for u in range(3):
            mean[u] += v[i, u]
    mean /= n
    scatter = np.zeros((3, 3))
    for i in range(n):
        for u in range(3):
            cu = v[i, u] - mean[u]
            for w in range(u, 3):
                scatter[u, w] += cu * (v[i, w] - mean[w])
    for u in range(3):
        for w in range(u):
            scatter[u, w] = scatter[w, u]
    ev = np.linalg.eigvalsh(scatter)  # ascending
    return np.sqrt(max(ev[2], 0.0) / n), np.sqrt(max(ev[1], 0.0) / n)


def ls_theta(points: np.ndarray) -> np.ndarray:
    """Least-squares θ, eq. (15): ``θ = (GᵀG)⁻¹ Gᵀ u``.

    Solved with :func:`numpy.linalg.lstsq` (the same minimiser, better
    conditioned than forming ``GᵀG``).

    Parameters
    ----------
    points : (N, 3) array
        The rows of ``G``, m.

    Returns
    -------
    (3,) array, 1/m
    """
    g = np.asarray(points, dtype=np.float64)
    theta, *_ = np.linalg.lstsq(g, np.ones(g.shape[0]), rcond=None)
    return theta


def fitting_errors(points: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The fitting error ``e_i = v_i · θ − 1`` of eq. (20), unitless."""
    return np.asarray(points, dtype=np.float64) @ np.asarray(theta, dtype=np.float64) - 1.0


def metric_residuals(theta: np.ndarray, points: np.ndarray, shift: np.ndarray | float = 0.0) -> np.ndarray:
    """Signed metric residuals ``(θ · x − 1)/|θ| + shift``, m.

    With ``points`` the corrected points and ``shift = 0`` this is the
    point-to-plane distance (paper model); with the capsule positions and
    ``shift = d`` it is the mirror-echo residual ``n · p_c + d − h``
    (constant-depth model).
    """
    t = np.asarray(theta, dtype=np.float64)
    return (np.asarray(points, dtype=np.float64) @ t - 1.0) / norm(t) + shift


def mirror_consistent(normal: np.ndarray, beam: np.ndarray, half_angle: float) -> bool:
    """The mirror-echo condition: a wall echoes only if its normal lies in the beam.

    True if ``normal`` is within ``half_angle`` (rad) of at least one of the
    subset's boresights ``beam`` (N, 3).
    """
    b = np.asarray(beam, dtype=np.float64)
    if b.size == 0:
        return False
    return bool(np.max(b @ np.asarray(normal, dtype=np.float64)) >= np.cos(half_angle))


def inlier_count(residuals_m: np.ndarray, tolerance: float) -> int:
    """Points with a metric residual within ``tolerance`` (m)."""
    return int(np.count_nonzero(np.abs(np.asarray(residuals_m)) <= tolerance))


def make_plane_fit(
    data: PlaneData,
    theta: np.ndarray,
    *,
    method: str,
    inlier_mask: np.ndarray,
    diagnostics: SolverDiagnostics,
    model: str = "paper",
    stderr: tuple[float, float] | None = None,
    theta_covariance: np.ndarray | None = None,
) -> PlaneFit | FitFailure:
    """Assemble a :class:`PlaneFit` for ``θ`` (eq. 1) on ``data``.

    Parameters
    ----------
    data : PlaneData
    theta : (3,) array
        The estimate, 1/m.
    method : str
    inlier_mask : (N,) bool array
        The points the final fit used.
    diagnostics : SolverDiagnostics
    model : {"paper", "constant-depth"}
        Which residual defines ``e_i``: the corrected points (eq. 20) or the
        mirror-echo condition (``e_i = (n · p_c + d − h)/h``).  The covariance
        uses the same residual.
    stderr : (float, float), optional
        Standard errors of the normal (rad) and offset (m) to report instead of
        the covariance's (a caller's own error model), validated as
        :meth:`PlaneFit.replace_scalars` validates them.
    theta_covariance : (3, 3) array, optional
        With ``stderr``: the covariance of ``θ`` from the caller's own error model, reported where the points
        alone do not constrain ``θ`` (one capsule per step leaves the tilt to a prior); unused where they do.

    Returns
    -------
    PlaneFit, or FitFailure (SOLVER_FAILED) if θ is not a usable plane.
    """
    t = np.asarray(theta, dtype=np.float64)
    nt = norm(t)
    if not 1e-3 < nt < 1e3:  # (also a NaN or infinite θ: its norm is not finite, so no comparison holds)
        return FitFailure(FailureReason.SOLVER_FAILED, f"{method}: no usable plane (θ = {t})", data.label, data.n)
    if model == "paper":
        x, shift = data.points, None
    elif model == "constant-depth":
        x, shift = data.capsules, data.distance
    else:
        raise ConfigError(f"unknown plane model {model!r}")
    mask = np.asarray(inlier_mask, dtype=bool)
    if mask.shape != (data.n,):
        raise ConfigError(f"inlier mask must have shape ({data.n},), got {mask.shape}")
    k = int(np.count_nonzero(mask))
    if k < 3:
        return FitFailure(FailureReason.SOLVER_FAILED, f"{method}: fewer than 3 inliers", data.label, data.n)
    n, ordered, cov, se_n, se_h, sigma_relative, sigma, patch, entropy = _fit_statistics(
        t, x, np.zeros(data.n) if shift is None else shift, mask, shift is not None
    )
    if not (math.isfinite(se_n) and math.isfinite(se_h)):  # (floats: math's test, not a ufunc's)
        if stderr is None or theta_covariance is None or not np.all(np.isfinite(theta_covariance)):
            return FitFailure(
                FailureReason.DEGENERATE_GEOMETRY,
                f"{method}: the inliers do not constrain the plane",
                data.label,
                data.n,
            )
        # The caller's error model stands in for the points' own covariance: the rest is the points' as ever.
        e = ordered
        ordered = np.sort(e)
        cov = 0.5 * (theta_covariance + theta_covariance.T)
        xi, si, ei = x[mask], (np.zeros(data.n) if shift is None else shift)[mask], e[mask]
        sigma_relative, sigma = MAD_K * mad_of(ei), MAD_K * mad_of(ei / nt)
        patch = observed_patch_of(n, 1.0 / nt, xi + si[:, None] * n if shift is not None else xi)
        entropy = residual_entropy(e) if data.n >= 2 else 0.0
    # Every array is fresh and every check of PlaneFit's constructor holds by construction (see
    # PlaneFit.from_owned); the mask is copied, since the caller may hold (and later change) it.
    fit = PlaneFit.from_owned(
        label=data.label,
        method=method,
        normal=n,
        offset=1.0 / nt,
        entropy=entropy,
        sigma_relative=sigma_relative,
        sigma=sigma,
        inlier_mask=mask.copy(),
        sorted_residuals=ordered,
        theta_covariance=cov,
        normal_stderr=se_n if stderr is None else stderr[0],
        offset_stderr=se_h if stderr is None else stderr[1],
        patch=patch,
        diagnostics=diagnostics,
    )
    if stderr is not None:
        fit._check_scalars(_STDERR_FIELDS)
    return fit


_STDERR_FIELDS = frozenset({"normal_stderr", "offset_stderr"})


@kernel
def _fit_statistics(
    t: np.ndarray, x: np.ndarray, shift: np.ndarray, mask: np.ndarray, mirror: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float, float, float, np.ndarray, float]:
    """What :func:`make_plane_fit` reports of ``θ`` on the points ``x``, in one kernel.

    The metric residuals ``r = (θ·x − 1)/|θ| + shift`` (:func:`metric_residuals`), the errors
    ``e = r·|θ|`` of eq. (20), their sorted copy, the covariance of θ over the inliers ``mask``
    (:func:`theta_covariance`) and the standard errors (:func:`normal_offset_stderr`), σ of eq.
    (21)–(22) of ``e`` and of ``r`` over the inliers (:func:`mad_sigma`) and the observed patch
    (:func:`observed_patch`) of the inliers' feet: the points themselves, or with ``mirror`` (the
    constant-depth model: ``x`` the capsules, ``shift`` the ranges) ``p_c + d·n``, and the entropy-like
    cost ``H`` of eq. (6) of all the errors ``e`` (0 below 2 points).

    Returns
    -------
    n, sorted e, cov, σ_n, σ_h, σ_relative, σ, patch, H (σ_n, σ_h inf: the inliers do not constrain θ;
    the rest is then unset; e itself is not returned: nothing keeps it but its sorted copy)
    """
    m = x.shape[0]
    nt = np.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
    n = t / nt
    r = np.empty(m)
    e = np.empty(m)
    for i in range(m):
        r[i] = (x[i, 0] * t[0] + x[i, 1] * t[1] + x[i, 2] * t[2] - 1.0) / nt + shift[i]
        e[i] = r[i] * nt
    every = True
    for i in range(m):
        every = every and mask[i]
    if every:  # (the same numbers as the copies below, which nothing writes to)
        xi, si, ri, ei = x, shift, r, e
    else:
        xi, si, ri, ei = x[mask], shift[mask], r[mask], e[mask]  # (copies: x may be a frozen PlaneData's)
    cov = theta_covariance_of(t, xi, si)
    se_n, se_h = normal_offset_stderr_of(t, cov)
    if not (np.isfinite(se_n) and np.isfinite(se_h)):
        return n, e, cov, se_n, se_h, np.nan, np.nan, np.empty((4, 3)), np.nan
    foot = xi + si.reshape(-1, 1) * n if mirror else xi
    ordered = np.sort(e)
    if every:
        # e's median is its sorted copy's middle: the order statistics fast_median finds, exactly (e is finite:
        # the points, θ and the shifts are), so mad_of(e) without selecting them again.
        k = m // 2
        med = ordered[k] if m % 2 else (ordered[k - 1] + ordered[k]) / 2.0
        mad_e = fast_median(np.abs(e - med))
    else:
        mad_e = mad_of(ei)
    return (
        n,
        ordered,
        cov,
        se_n,
        se_h,
        MAD_K * mad_e,
        MAD_K * mad_of(ri),
        observed_patch_of(n, 1.0 / nt, foot),
        residual_entropy(e) if m >= 2 else 0.0,
    )
