"""The Least Entropy-Like (LEL) estimator (paper §2 and §5.2, eq. 1–8).

For points ``v_i`` and a parameter vector θ (plane ``θ · v = 1``, eq. 1) the
residuals are ``r_i = v_i · θ − 1`` (eq. 2), ``D = Σ r_i²`` (eq. 3),
``q_i = r_i² / D`` (eq. 4) and the entropy-like cost is

    H = −(1 / log N) Σ q_i log q_i   (eq. 6),   H = 0 if D = 0.

With ``s_i = r_i²`` and ``S = Σ s_i log s_i`` this is
``H = (log D − S / D) / log N``, and its gradient is

    ∂H/∂r_i = 2 r_i (S/D − log s_i) / (D log N),
    ∇_θ H   = (2 / (D log N)) Σ r_i v_i (S/D − log s_i).

The term ``r_i log s_i = 2 r_i log|r_i|`` tends to 0 with ``r_i``, so a zero
residual contributes nothing (it is taken as 0 exactly).

Two minimisers of eq. (8) are provided:

* :func:`lel_fit_nelder_mead` — the paper's procedure (§5.2): Nelder-Mead from
  six starts (θ_LS, two vectors orthogonal to it with the same norm, and the
  three opposites), keep the least ``H``.
* :func:`lel_fit_fast` — closed-form gradient and Hessian, a damped Newton
  solver (or SciPy's BFGS / L-BFGS-B with the gradient) from θ_LS and any
  extra starts.

Pure functions: arrays in, results out.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import optimize

from lelsonar.errors import ConfigError
from lelsonar.signal.compiled import kernel
from lelsonar.signal.summation import pairwise_sum

__all__ = [
    "entropy",
    "entropy_of_residuals",
    "residual_entropy",
    "entropy_and_gradient",
    "residual_gradient",
    "entropy_gradient_hessian",
    "newton_minimize",
    "six_starts",
    "LelResult",
    "lel_fit_nelder_mead",
    "lel_fit_fast",
    "front_start",
    "FAST_SOLVERS",
    "PERFECT_FIT",
    "pairwise_sum",
    "residual_entropy",
]


@kernel
def _cost_terms(r: np.ndarray) -> tuple[float, float, np.ndarray]:
    """The one implementation of eq. (6): ``H``, ``D = Σ s`` and ``log s_i`` for residuals ``r``, ``s = r²``.

    ``H = (log D − S/D) / log N`` with ``S = Σ s log s``.  ``log s_i`` is floored
    at ``log(1e-30 D)``: ``s log s`` is 0 at ``s = 0`` either way, and the floor
    keeps the derivatives finite.  ``H = 0`` when ``D = 0`` and ``inf`` when
    ``D`` is not finite.  A kernel (``D`` summed pairwise, as ``np.sum``): every
    plane fit reports its ``H``.
    """
    n = r.shape[0]
    s = r * r
    d = pairwise_sum(s, 0, n)
    if d == 0.0 or not np.isfinite(d):
        return (0.0 if d == 0.0 else np.inf), d, np.zeros_like(s)
    floor = 1e-30 * d
    logs = np.empty(n)
    for i in range(n):
        logs[i] = np.log(max(s[i], floor))
    return (np.log(d) - np.dot(s, logs) / d) / np.log(n), d, logs


def entropy_of_residuals(residuals: np.ndarray) -> float:
    """The entropy-like cost ``H`` of a residual vector, eq. (6).

    Parameters
    ----------
    residuals : (N,) array
        ``r_i`` of eq. (2), any unit (H is invariant to scaling them).

    Returns
    -------
    float
        ``H`` in [0, 1]; 0 when all residuals are 0 (``D = 0``).

    Raises
    ------
    ConfigError
        If ``N < 2`` (``log N`` would be 0) or a residual is not finite.
    """
    r = np.asarray(residuals, dtype=np.float64).ravel()
    n = r.size
    if n < 2:
        raise ConfigError(f"the entropy-like cost needs at least 2 residuals, got {n}")
    if not np.all(np.isfinite(r)):
        raise ConfigError("residuals must be finite")
    return residual_entropy(r)


@kernel
def residual_entropy(r: np.ndarray) -> float:
    """H (eq. 6) of at least 2 finite residuals: :func:`entropy_of_residuals` without its checks (a kernel, for
    the kernels that score a fit)."""
    # Scale first: H is scale-invariant, and this keeps r² from underflowing.
    scale = 0.0
    for x in r:
        scale = max(scale, abs(x))
    if scale == 0.0:
        return 0.0
    h, _, _ = _cost_terms(r / scale)
    return min(max(h, 0.0), 1.0)


#: Residuals of eq. (2) (relative to the "1" of eq. 1) this small are rounding
#: noise: a fit with all of them below it is perfect, ``D = 0`` and ``H = 0`` (eq. 6).
PERFECT_FIT = 1e-12


def entropy(theta: np.ndarray, points: np.ndarray) -> float:
    """``H(θ)`` for the plane ``θ · v = 1`` and points ``V`` (eq. 2–6).

    Residuals all below :data:`PERFECT_FIT` count as ``D = 0`` (``H = 0``):
    the paper's "the Least Squares fit is perfect" case of eq. (6), which
    rounding would otherwise turn into the entropy of rounding noise.

    Parameters
    ----------
    theta : (3,) array, 1/m
    points : (N, 3) array, m
    """
    v = np.asarray(points, dtype=np.float64)
    r = v @ np.asarray(theta, dtype=np.float64) - 1.0
    if r.size >= 2 and np.all(np.abs(r) <= PERFECT_FIT):
        return 0.0
    return entropy_of_residuals(r)


def residual_gradient(residuals: np.ndarray) -> tuple[float, np.ndarray]:
    """``H`` and ``∂H/∂r`` for a residual vector (eq. 6).

    ``∂H/∂r_i = 2 r_i (S/D − log s_i) / (D log N)`` with ``s = r²``,
    ``D = Σ s``, ``S = Σ s log s``; ``r_i log s_i`` is taken as 0 where
    ``r_i = 0``.  Chain with ``∂r/∂p`` to get the gradient in any
    parametrisation.  Returns ``(0, 0)`` when ``D = 0``.
    """
    r = np.asarray(residuals, dtype=np.float64)
    h, d, logs = _cost_terms(r)
    if d == 0.0 or not np.isfinite(d):
        return 0.0, np.zeros_like(r)
    a = float((r * r) @ logs) / d
    g = (2.0 / (d * np.log(r.size))) * r * (a - logs)
    return float(h), g


def entropy_and_gradient(theta: np.ndarray, points: np.ndarray) -> tuple[float, np.ndarray]:
    """``H(θ)`` and its closed-form gradient ``∇_θ H`` (eq. 6).

    ``∇_θ H = (2 / (D log N)) Σ r_i v_i (S/D − log s_i)``.

    Parameters
    ----------
    theta : (3,) array, 1/m
    points : (N, 3) array, m

    Returns
    -------
    (float, (3,) array)
    """
    v = np.asarray(points, dtype=np.float64)
    h, g = residual_gradient(v @ theta - 1.0)
    return h, g @ v


def entropy_gradient_hessian(theta: np.ndarray, points: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``H(θ)``, ``∇_θ H`` and the closed-form Hessian ``∇²_θ H`` (eq. 6).

    With ``a = S/D`` and ``b_i = log s_i − a``,

        ∂²H/∂r_i∂r_j = (2/(D log N)) [δ_ij (−b_i − 2) + (2 r_i r_j / D)(b_i + b_j + 1)],

    so ``∇²_θ H = Vᵀ diag(w) V + (4/(D² log N)) (c_b c_1ᵀ + c_1 c_bᵀ + c_1 c_1ᵀ)``
    with ``w_i = 2(−b_i − 2)/(D log N)``, ``c_1 = Σ r_i v_i`` and
    ``c_b = Σ b_i r_i v_i``.  ``w_i`` is +∞ where ``r_i = 0`` (the cost is C¹
    but not C² there); ``log s_i`` is floored at ``log(1e-30 D)`` to keep it
    finite.
    """
    v = np.asarray(points, dtype=np.float64)
    return _egh(np.asarray(theta, dtype=np.float64), v, np.ascontiguousarray(v.T))


def _egh(
    theta: np.ndarray, v: np.ndarray, vt: np.ndarray, c: float | np.ndarray = -1.0
) -> tuple[float, np.ndarray, np.ndarray]:
    # H, gradient and Hessian for the affine residuals r = V θ + c (c = −1: eq. 2).
    r = v @ theta + c
    h, d, logs = _cost_terms(r)
    if d == 0.0 or not np.isfinite(d):
        return 0.0, np.zeros(3), np.zeros((3, 3))
    a = float((r * r) @ logs) / d
    inv_l = 1.0 / np.log(r.size)
    b = logs - a
    c1 = vt @ r
    cb = vt @ (b * r)
    k = 2.0 * inv_l / d
    grad = -k * cb
    hess = (vt * (k * (-b - 2.0))) @ v
    m = cb[:, None] * c1
    hess += (2.0 * k / d) * (m + m.T + c1[:, None] * c1)
    return h, grad, hess


def _h(theta: np.ndarray, v: np.ndarray, c: float | np.ndarray = -1.0) -> float:
    return _cost_terms(v @ theta + c)[0]


def newton_minimize(
    theta0: np.ndarray,
    points: np.ndarray,
    *,
    gtol: float = 1e-12,
    maxiter: int = 100,
    offset: float | np.ndarray = -1.0,
    max_step: float | None = None,
) -> tuple[np.ndarray, float, int, int, bool]:
    """Minimise ``H`` (eq. 8) by a damped Newton method with the exact Hessian.

    The residuals are ``r = V θ + offset`` — ``offset = −1`` is the paper's
    eq. (2); any other affine model (e.g. the linearised constant-depth model)
    can be minimised the same way.

    Each step solves ``|∇²H| p = −∇H`` where ``|∇²H|`` takes the absolute
    values of the Hessian's eigenvalues (a saddle-free Newton step, so every
    step descends), followed by a backtracking Armijo line search.  Stops when
    ``|∇H|·|θ| < gtol`` or no step lowers ``H``.

    Returns
    -------
    theta, H, iterations, evaluations, converged
    """
    v = np.asarray(points, dtype=np.float64)
    vt = np.ascontiguousarray(v.T)
    theta = np.asarray(theta0, dtype=np.float64).copy()
    c = offset
    h, g, hess = _egh(theta, v, vt, c)
    evals, it, converged = 1, 0, False
    for it in range(1, maxiter + 1):  # noqa: B007  # read after the loop: the iterations run
        scale = max(math.sqrt(float(theta @ theta)), 1e-300) if max_step is None else max_step
        if math.sqrt(float(g @ g)) * scale < gtol:
            converged = True
            break
        lam, q = np.linalg.eigh(hess)
        lam = np.abs(lam)
        lam = np.maximum(lam, 1e-12 * max(float(lam.max()), 1e-300))
        p = -(q @ ((q.T @ g) / lam))
        slope = float(g @ p)
        if not (np.all(np.isfinite(p)) and slope < 0):
            p, slope = -g, -float(g @ g)
        # Never move θ by more than half its norm (or max_step) in one step.
        pn = math.sqrt(float(p @ p))
        if pn > 0.5 * scale:
            p = p * (0.5 * scale / pn)
            slope *= 0.5 * scale / pn
        step, hc = 1.0, np.inf
        for _ in range(50):
            hc = _h(theta + step * p, v, c)
            evals += 1
            if hc <= h + 1e-4 * step * slope:
                break
            step *= 0.5
        if not hc < h:
            converged = True  # no representable step lowers H: a minimum to machine precision
            break
        theta = theta + step * p
        h_old = h
        h, g, hess = _egh(theta, v, vt, c)
        evals += 1
        if h_old - h <= 1e-15 * h_old:
            converged = True
            break
    return theta, float(h), it, evals, converged


def six_starts(theta_ls: np.ndarray) -> np.ndarray:
    """The paper's six starting points for the LEL minimisation (§5.2).

    θ_LS, two vectors orthogonal to it (and to each other) with the same norm,
    and the opposites of these three.

    Returns
    -------
    (6, 3) array
    """
    t = np.asarray(theta_ls, dtype=np.float64)
    norm = float(np.linalg.norm(t))
    if not (np.isfinite(norm) and norm > 0):
        raise ConfigError("the LS solution must be a finite non-zero vector to build the six starts")
    u = t / norm
    # Orthonormal completion, deterministic: the axis least aligned with u.
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(u)))] = 1.0
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    first = np.stack([t, norm * e1, norm * e2])
    return np.concatenate([first, -first])


@dataclass(frozen=True)
class LelResult:
    """Outcome of one LEL minimisation (eq. 8).

    Parameters
    ----------
    theta : (3,) array
        The minimiser, 1/m.
    entropy : float
        ``H(θ)``.
    starts : int
        Starting points tried.
    iterations, evaluations : int
        Summed over the starts.
    time_s : float
    converged : bool
        The best start's solver reported success.
    candidates : (k, 3) array
        The local minimum reached from each start, in start order.
    candidate_entropy : (k,) array
        ``H`` of each candidate.
    """

    theta: np.ndarray
    entropy: float
    starts: int
    iterations: int
    evaluations: int
    time_s: float
    converged: bool
    candidates: np.ndarray
    candidate_entropy: np.ndarray

    def __post_init__(self) -> None:
        for name in ("theta", "candidates", "candidate_entropy"):
            a = np.array(getattr(self, name), dtype=np.float64)
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        if self.theta.shape != (3,) or not np.all(np.isfinite(self.theta)):
            raise ConfigError(f"LelResult.theta must be a finite (3,) vector, got {self.theta}")


def _check_points(points: np.ndarray) -> np.ndarray:
    v = np.asarray(points, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ConfigError(f"points must have shape (N, 3), got {v.shape}")
    if v.shape[0] < 4:
        raise ConfigError(f"LEL needs at least 4 points, got {v.shape[0]}")
    if not np.all(np.isfinite(v)):
        raise ConfigError("points must be finite")
    return v


def _ls(v: np.ndarray) -> np.ndarray:
    theta, *_ = np.linalg.lstsq(v, np.ones(v.shape[0]), rcond=None)
    return theta


def lel_fit_nelder_mead(
    points: np.ndarray,
    theta_ls: np.ndarray | None = None,
    *,
    extra_starts: np.ndarray | None = None,
    xatol: float = 1e-4,
    fatol: float = 1e-4,
    maxiter: int = 2000,
) -> LelResult:
    """The paper's LEL minimisation (§5.2, eq. 8): six-start Nelder-Mead.

    Parameters
    ----------
    points : (N, 3) array
        The subset's (corrected) points ``v_i``, m.
    theta_ls : (3,) array, optional
        θ_LS of eq. (15); computed if omitted.
    extra_starts : (k, 3) array, optional
        Further starts tried after the six (e.g. a warm start).
    xatol, fatol, maxiter
        Passed to :func:`scipy.optimize.minimize` (method ``"Nelder-Mead"``);
        the defaults are SciPy's.

    Returns
    -------
    LelResult
        The start with the least ``H`` wins.
    """
    t0 = time.perf_counter()
    v = _check_points(points)
    t_ls = _ls(v) if theta_ls is None else np.asarray(theta_ls, dtype=np.float64)
    if np.all(np.abs(v @ t_ls - 1.0) <= PERFECT_FIT):  # D = 0: eq. (6), nothing to minimise
        return LelResult(t_ls, 0.0, 0, 0, 1, time.perf_counter() - t0, True, t_ls[None, :], np.zeros(1))
    starts = six_starts(t_ls)
    if extra_starts is not None:
        starts = np.concatenate([starts, np.asarray(extra_starts, dtype=np.float64).reshape(-1, 3)])

    def fun(th: np.ndarray) -> float:
        r = v @ th - 1.0
        s = r * r
        d = s.sum()
        if d == 0.0:
            return 0.0
        logs = np.log(s, out=np.zeros_like(s), where=s > 0)
        return float((np.log(d) - (s @ logs) / d) / np.log(v.shape[0]))

    cands, hs, its, evs, oks = [], [], 0, 0, []
    for x0 in starts:
        res = optimize.minimize(
            fun, x0, method="Nelder-Mead", options={"xatol": xatol, "fatol": fatol, "maxiter": maxiter}
        )
        cands.append(res.x)
        hs.append(float(res.fun))
        its += int(res.nit)
        evs += int(res.nfev)
        oks.append(bool(res.success))
    hs_arr = np.asarray(hs)
    best = int(np.argmin(hs_arr))
    return LelResult(
        theta=cands[best],
        entropy=hs[best],
        starts=len(starts),
        iterations=its,
        evaluations=evs,
        time_s=time.perf_counter() - t0,
        converged=oks[best],
        candidates=np.asarray(cands),
        candidate_entropy=hs_arr,
    )


def _scipy_qn(
    v: np.ndarray, x0: np.ndarray, method: str, gtol: float, maxiter: int
) -> tuple[np.ndarray, float, int, int, bool]:
    def fg(th: np.ndarray) -> tuple[float, np.ndarray]:
        return entropy_and_gradient(th, v)

    opts: dict[str, float | int] = {"gtol": gtol, "maxiter": maxiter}
    if method == "L-BFGS-B":
        opts["ftol"] = 1e-15
    with warnings.catch_warnings():
        # "Desired error not necessarily achieved due to precision loss" just means
        # the line search hit machine precision at the minimum.
        warnings.simplefilter("ignore", RuntimeWarning)
        res = optimize.minimize(fg, x0, jac=True, method=method, options=opts)
    x = res.x if np.all(np.isfinite(res.x)) else np.asarray(x0, dtype=np.float64)
    ok = bool(res.success) or (method == "BFGS" and res.status == 2)
    return x, entropy(x, v), int(res.nit), int(res.nfev), ok


#: Solvers accepted by :func:`lel_fit_fast`.
FAST_SOLVERS = ("newton", "bfgs", "l-bfgs-b")


def front_start(points: np.ndarray, theta_ls: np.ndarray) -> np.ndarray:
    """LS (eq. 15) on the points in front of the LS plane (``e_i ≤ median e``, eq. 20).

    Multiple-reflection outliers are always *behind* the wall (their path is
    longer), so they drag θ_LS backwards; the half of the points in front of
    θ_LS is mostly wall.  A cheap second start that lands in the wall's basin
    when θ_LS lands in the outlier cluster's.
    """
    v = np.asarray(points, dtype=np.float64)
    e = v @ theta_ls - 1.0
    keep = e <= np.median(e)
    if np.count_nonzero(keep) < 4:
        return np.asarray(theta_ls, dtype=np.float64)
    theta, *_ = np.linalg.lstsq(v[keep], np.ones(int(np.count_nonzero(keep))), rcond=None)
    return theta


def lel_fit_fast(
    points: np.ndarray,
    theta_ls: np.ndarray | None = None,
    *,
    extra_starts: np.ndarray | None = None,
    solver: str = "newton",
    front: bool = True,
    gtol: float = 1e-12,
    maxiter: int = 200,
    polish: bool = False,
) -> LelResult:
    """Fast LEL minimisation (eq. 8) with the closed-form derivatives.

    From each start — θ_LS, then (``front=True``) :func:`front_start`, then
    ``extra_starts`` — a local solver minimises ``H``:

    * ``"newton"`` (default): :func:`newton_minimize`, damped Newton with the
      closed-form Hessian, about 10–20 iterations on 300 points;
    * ``"bfgs"`` / ``"l-bfgs-b"``: SciPy's quasi-Newton solvers with the
      closed-form gradient (:func:`entropy_and_gradient`); same minima, but
      SciPy's per-call overhead makes them dearer.

    The start with the least ``H`` wins.  On 500 simulated plane subsets
    (``lelsonar bench estimators``) θ_LS alone ended above the six-start
    Nelder-Mead ``H`` in 49 (all on a plane pitched 8°, where it fell into the
    outlier cluster's basin); with the front start, in none.

    Parameters
    ----------
    points : (N, 3) array, m
    theta_ls : (3,) array, optional
        θ_LS (eq. 15); computed if omitted.
    extra_starts : (k, 3) array, optional
        E.g. a warm start from the previous partial scan, or the paper's other
        five starts (``six_starts(θ_LS)[1:]``).
    solver : {"newton", "bfgs", "l-bfgs-b"}
    front : bool
        Also start from :func:`front_start`.
    gtol, maxiter
        Stop when ``|∇H|·|θ| < gtol``; iteration cap per start.
    polish : bool
        Finish with a tight Nelder-Mead run on a tiny simplex around the best
        minimum (only ever lowers ``H``).  Not needed in practice.

    Returns
    -------
    LelResult
    """
    if solver not in FAST_SOLVERS:
        raise ConfigError(f"unknown LEL solver {solver!r}; choose one of {FAST_SOLVERS}")
    t0 = time.perf_counter()
    v = _check_points(points)
    t_ls = _ls(v) if theta_ls is None else np.asarray(theta_ls, dtype=np.float64)
    if np.all(np.abs(v @ t_ls - 1.0) <= PERFECT_FIT):  # D = 0: eq. (6), nothing to minimise
        return LelResult(t_ls, 0.0, 0, 0, 1, time.perf_counter() - t0, True, t_ls[None, :], np.zeros(1))
    starts = [t_ls]
    if front:
        starts.append(front_start(v, t_ls))
    if extra_starts is not None:
        starts.extend(np.asarray(extra_starts, dtype=np.float64).reshape(-1, 3))
    cands, hs, its, evs, oks = [], [], 0, 0, []
    for x0 in starts:
        if solver == "newton":
            x, h, nit, nev, ok = newton_minimize(x0, v, gtol=gtol, maxiter=maxiter)
        else:
            x, h, nit, nev, ok = _scipy_qn(v, x0, "BFGS" if solver == "bfgs" else "L-BFGS-B", gtol, maxiter)
        cands.append(x)
        hs.append(h)
        its += nit
        evs += nev
        oks.append(ok)
    hs_arr = np.asarray(hs)
    best = int(np.argmin(hs_arr))
    theta, h_best = cands[best], hs[best]
    if polish:
        scale = max(float(np.linalg.norm(theta)), 1e-12)
        simplex = theta + np.vstack([np.zeros(3), 1e-6 * scale * np.eye(3)])
        res = optimize.minimize(
            lambda th: entropy(th, v),
            theta,
            method="Nelder-Mead",
            options={"initial_simplex": simplex, "xatol": 1e-12 * scale, "fatol": 1e-15, "maxiter": 400},
        )
        its += int(res.nit)
        evs += int(res.nfev)
        if float(res.fun) < h_best:
            theta, h_best = res.x, float(res.fun)
            cands[best], hs_arr[best] = theta, h_best
    return LelResult(
        theta=theta,
        entropy=h_best,
        starts=len(starts),
        iterations=its,
        evaluations=evs,
        time_s=time.perf_counter() - t0,
        converged=oks[best],
        candidates=np.asarray(cands),
        candidate_entropy=hs_arr,
    )
