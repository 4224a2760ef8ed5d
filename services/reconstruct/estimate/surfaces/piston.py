"""A piston's echo profile across γ, fitted: ``log A = log P + log D(γ − β; ka)²`` by Levenberg–Marquardt.

Every echo of a rotating transceiver follows its beam's two-way pattern across γ; a baffled circular piston's
is ``D(ψ)² = (2·J1(x)/x)²``, ``x = ka·sin ψ``.  The beam-pattern flank bearings (:mod:`.flank_bearing`) fit it
to a sweep's profiles, a few to a few tens per sweep, each of 8 to 60 steps: :func:`piston_lm` fits them all in
one compiled call (:mod:`lelsonar.signal.compiled`), the profiles packed into rows (:class:`Profiles`).

``J0`` and ``J1`` come from their power series up to ``|x| = 12`` (the largest term there is 4·10³, so the sum
keeps 1e-12 absolute, 1e-16 over the main lobe, ``|x| < 3.83``) and from Hankel's asymptotic expansion past it
(its smallest term at ``|x| = 12`` is 1e-11): Abramowitz & Stegun 9.1.10 and 9.2.5.

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lelsonar.signal.compiled import kernel

__all__ = [
    "FTOL",
    "LM_CEILING",
    "LM_START",
    "MAX_ITERATIONS",
    "MIN_NOISE_DIFFERENCES",
    "XTOL",
    "PistonFit",
    "Profiles",
    "bessel_j01",
    "log_piston_point",
    "piston_lm",
]

#: Most Levenberg–Marquardt steps a row takes (SciPy's ``least_squares`` allows 100 evaluations per parameter).
MAX_ITERATIONS = 100
#: The parameters' relative change and the cost's relative decrease a fit stops under (MINPACK's defaults, as
#: SciPy's ``least_squares`` has them: the cost then lies within about 1e-8 of its minimum, the parameters
#: within 1e-4·√dof of their σ).
XTOL = 1e-8
FTOL = 1e-8
#: The damping's start (nearly Gauss–Newton from a warm start) and its ceiling (a row whose damping reaches it
#: cannot lower its cost: it is at its minimum to rounding).
LM_START = 1e-3
LM_CEILING = 1e16
#: Fewest second differences a robust noise estimate takes.
MIN_NOISE_DIFFERENCES = 5
#: Where the power series of J0 and J1 hands over to Hankel's expansion.
_SERIES_LIMIT = 12.0


@kernel
def bessel_j01(x: float) -> tuple[float, float]:
    """``J0(x)`` and ``J1(x)`` (Abramowitz & Stegun 9.1.10 below ``|x| = 12``, 9.2.5 past it).

    Parameters
    ----------
    x : float

    Returns
    -------
    (J0(x), J1(x))
    """
    ax = abs(x)
    if ax < _SERIES_LIMIT:
        q = 0.25 * x * x
        t0, t1 = 1.0, 1.0
        s0, s1 = 1.0, 1.0
        for k in range(1, 60):
            t0 *= -q / (k * k)
            t1 *= -q / (k * (k + 1))
            s0 += t0
            s1 += t1
            if abs(t0) < 1e-17 and abs(t1) < 1e-17:
                break
        return s0, 0.5 * x * s1
    # Hankel: J_ν(x) = √(2/(πx)) (P cos χ − Q sin χ), χ = x − (ν/2 + 1/4)π, P and Q alternating series in 1/x
    # with a_k(ν) = a_{k−1}(ν)·(4ν² − (2k − 1)²)/(8k); each stops at its smallest term.
    out = np.empty(2)
    for nu in range(2):
        mu = 4.0 * nu * nu
        p, q_sum = 1.0, 0.0
        a = 1.0
        last = 1.0
        for k in range(1, 40):
            a *= (mu - (2 * k - 1) ** 2) / (8.0 * k * ax)
            if abs(a) >= last:
                break
            last = abs(a)
            sign = 1.0 if (k // 2) % 2 == 0 else -1.0
            if k % 2 == 0:
                p += sign * a
            else:
                q_sum += sign * a
        chi = ax - (0.5 * nu + 0.25) * math.pi
        out[nu] = math.sqrt(2.0 / (math.pi * ax)) * (p * math.cos(chi) - q_sum * math.sin(chi))
    return out[0], (out[1] if x > 0 else -out[1])


@kernel
def log_piston_point(u: float, ka: float) -> tuple[float, float, float]:
    """A piston's two-way pattern in log, ``log D(u)²`` (``-inf`` at its nulls), and its slopes ``∂/∂u`` and
    ``∂/∂ka``.

    With ``x = ka·sin u`` and ``D = 2·J1(x)/x``: ``d log D/dx = J0(x)/J1(x) − 2/x`` (``−x/4`` as ``x → 0``),
    so ``∂ log D²/∂u = 2 (d log D/dx) ka cos u`` and ``∂ log D²/∂ka = 2 (d log D/dx) sin u``.

    Parameters
    ----------
    u : float
        Angle off the beam's axis, rad.
    ka : float
        The piston's wavenumber times radius.

    Returns
    -------
    (log D², ∂/∂u, ∂/∂ka)
    """
    s = math.sin(u)
    x = ka * s
    if abs(x) < 1e-6:
        log_d, dx = 0.0, -x / 4.0
    else:
        j0, j1 = bessel_j01(x)
        d = abs(2.0 * j1 / x)
        log_d = 2.0 * math.log(d) if d > 0 else -math.inf
        dx = j0 / j1 - 2.0 / x if j1 != 0 else math.inf
    return log_d, 2.0 * dx * ka * math.cos(u), 2.0 * dx * s


@dataclass(frozen=True)
class Profiles:
    """Echo profiles of different lengths packed left-aligned into rows, for one fit of them all.

    ``g`` and ``la``: (R, K) γ (rad) and ``log A``; ``w``: (R, K) which entries hold a step (the rest are
    never read); ``n``: (R,) steps per row.
    """

    g: np.ndarray
    la: np.ndarray
    w: np.ndarray
    n: np.ndarray

    @staticmethod
    def pack(profiles: list[tuple[np.ndarray, np.ndarray]]) -> Profiles:
        """Rows from ``(γ, log A)`` pairs, each in γ order."""
        n = np.array([p[0].size for p in profiles], dtype=np.intp)
        k = max(int(n.max(initial=0)), 1)
        w = np.arange(k) < n[:, None]
        g = np.zeros(w.shape)
        la = np.zeros(w.shape)
        if w.any():
            g[w] = np.concatenate([p[0] for p in profiles])
            la[w] = np.concatenate([p[1] for p in profiles])
        return Profiles(g, la, w, n)

    def rows(self, pick: list[int]) -> Profiles:
        """The rows ``pick``, in that order (one may repeat)."""
        return Profiles(self.g[pick], self.la[pick], self.w[pick], self.n[pick])

    def noise(self) -> np.ndarray:
        """Each row's log amplitude noise σ, robust, from its second differences (variance 6 σ² for white
        noise): 1.4826 times their median absolute deviation over √6; NaN from fewer than
        :data:`MIN_NOISE_DIFFERENCES` of them (the median absolute deviation of a few is near 0 by chance)."""
        if self.g.shape[1] < 3:
            return np.full(self.n.shape, np.nan)
        la = self.la
        second = la[:, 2:] - 2.0 * la[:, 1:-1] + la[:, :-2]
        m = np.maximum(self.n - 2, 0)
        second = np.where(np.arange(second.shape[1]) < m[:, None], second, np.nan)
        centre = _row_median(second, m)
        spread = _row_median(np.abs(second - centre[:, None]), m)
        return np.where(m >= MIN_NOISE_DIFFERENCES, 1.4826 * spread / math.sqrt(6.0), np.nan)


def _row_median(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Each row's median of its first ``m`` entries (NaN after them, sorted last), as :func:`np.median` takes
    it: the middle value, or the mean of the middle two."""
    s = np.sort(x, axis=1)
    rows = np.arange(x.shape[0])
    lo, hi = np.maximum((m - 1) // 2, 0), np.maximum(m // 2, 0)
    return np.where(m > 0, (s[rows, lo] + s[rows, hi]) / 2.0, np.nan)


@dataclass(frozen=True)
class PistonFit:
    """Each row's fit of :func:`piston_lm`: ``β``, ``ka``, whether it converged, and at the solution the
    residuals (R, K; 0 off the row's steps), their Jacobian (R, K, 2 or 3: over the level, β[, ka]; 0 off the
    row's steps) and their sum of squares."""

    bearing: np.ndarray
    ka: np.ndarray
    ok: np.ndarray
    residual: np.ndarray
    jacobian: np.ndarray
    cost: np.ndarray


def piston_lm(
    p: Profiles, bearing: np.ndarray, ka: np.ndarray, *, free_ka: bool, max_iter: int = MAX_ITERATIONS
) -> PistonFit:
    """Levenberg–Marquardt fits of the piston ``log A = log P + log D(γ − β; ka)²`` to each row of ``p``: over
    ``(log P, β, ka)`` (``free_ka``) or ``(log P, β)`` with each row's ``ka`` fixed.

    Each row starts at its largest ``log A``, its ``β`` and its ``ka``.  Steps solve
    ``(JᵀJ + λ diag JᵀJ) δ = −Jᵀr`` (2×2 or 3×3, by the adjugate), from λ = :data:`LM_START` (nearly
    Gauss–Newton); λ follows Nielsen's rule (Madsen, Nielsen & Tingleff, *Methods for non-linear least squares
    problems*, 2004): on a step that lowers the cost it shrinks by as much as the linear model predicted that
    decrease well, on one that does not (or that reaches a null of the pattern, where ``log D²`` is not
    finite) it grows by a factor that doubles with each failure in a row.  A row stops where its step falls
    under :data:`XTOL` of its parameters or its cost's relative decrease under :data:`FTOL`: far inside any σ
    the fit gives.

    Parameters
    ----------
    p : Profiles
    bearing, ka : (R,) arrays
        Each row's start (``ka`` fixed unless ``free_ka``).
    free_ka : bool
    max_iter : int

    Returns
    -------
    PistonFit; ``ok`` False where the start is not finite, a step is not, or the row has not converged.
    """
    b = np.asarray(bearing, dtype=np.float64)
    k = np.asarray(ka, dtype=np.float64)
    level = np.where(p.w, p.la, -np.inf).max(axis=1, initial=-np.inf)
    x = np.stack([level, b, k], axis=1) if free_ka else np.stack([level, b], axis=1)
    r = np.zeros(p.g.shape)
    jac = np.zeros((*p.g.shape, x.shape[1]))
    cost = np.zeros(b.shape)
    ok = np.zeros(b.shape, dtype=np.bool_)
    _fit_rows(
        np.ascontiguousarray(p.g), np.ascontiguousarray(p.la), p.n.astype(np.int64), x, np.ascontiguousarray(k),
        bool(free_ka), int(max_iter), r, jac, cost, ok,
    )  # fmt: skip
    return PistonFit(x[:, 1].copy(), x[:, 2].copy() if free_ka else k.copy(), ok, r, jac, cost)


@kernel
def _row_terms(g, la, m, x, ka, free, r, jac):
    """One row's residuals and Jacobian at ``x`` (level, β[, ka]; ``ka`` the fixed one where not ``free``),
    written into ``r`` and ``jac``; returns their sum of squares (``inf`` where not finite)."""
    k = x[2] if free else ka
    cost = 0.0
    for i in range(m):
        log_d, du, dk = log_piston_point(g[i] - x[1], k)
        r[i] = x[0] + log_d - la[i]
        jac[i, 0] = 1.0
        jac[i, 1] = -du
        if free:
            jac[i, 2] = dk
        cost += r[i] * r[i]
    return cost if math.isfinite(cost) else math.inf


@kernel
def _solve_small(a, rhs, out):
    """``a out = rhs`` for a symmetric 2×2 or 3×3 ``a``, by its adjugate; False where singular or not finite."""
    if a.shape[0] == 2:
        det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
        out[0] = (a[1, 1] * rhs[0] - a[0, 1] * rhs[1]) / det
        out[1] = (a[0, 0] * rhs[1] - a[1, 0] * rhs[0]) / det
    else:
        c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
        c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
        c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
        c11 = a[2, 2] * a[0, 0] - a[2, 0] * a[0, 2]
        c12 = a[2, 0] * a[0, 1] - a[2, 1] * a[0, 0]
        c22 = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
        det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
        out[0] = (c00 * rhs[0] + c01 * rhs[1] + c02 * rhs[2]) / det
        out[1] = (c01 * rhs[0] + c11 * rhs[1] + c12 * rhs[2]) / det
        out[2] = (c02 * rhs[0] + c12 * rhs[1] + c22 * rhs[2]) / det
    for j in range(out.size):
        if not math.isfinite(out[j]):
            return False
    return True


@kernel
def _fit_rows(g, la, n, x, ka, free, max_iter, r, jac, cost, ok):
    """:func:`piston_lm`'s rows, one after another: ``x`` (R, P) holds the starts and gets the solutions;
    ``r``, ``jac``, ``cost`` and ``ok`` are written."""
    n_rows, width = g.shape
    n_par = x.shape[1]
    nx = np.empty(n_par)
    nr = np.empty(width)
    njac = np.zeros((width, n_par))
    a = np.empty((n_par, n_par))
    damped = np.empty((n_par, n_par))
    grad = np.empty(n_par)
    step = np.empty(n_par)
    for row in range(n_rows):
        m = n[row]
        xr, rr, jr = x[row], r[row], jac[row]
        c = _row_terms(g[row], la[row], m, xr, ka[row], free, rr, jr)
        cost[row] = c
        if m == 0 or not math.isfinite(c):
            continue
        lam, grow = LM_START, 2.0
        done = False
        for _ in range(max_iter):
            for p in range(n_par):
                grad[p] = 0.0
                for q in range(n_par):
                    a[p, q] = 0.0
                for i in range(m):
                    grad[p] += jr[i, p] * rr[i]
                    for q in range(n_par):
                        a[p, q] += jr[i, p] * jr[i, q]
            for p in range(n_par):
                for q in range(n_par):
                    damped[p, q] = a[p, q]
                damped[p, p] += lam * a[p, p]
                grad[p] = -grad[p]
            if not _solve_small(damped, grad, step):
                break  # a step that is not finite: no fit
            small_step = True
            for p in range(n_par):
                if abs(step[p]) > XTOL * (abs(xr[p]) + XTOL):
                    small_step = False
            if small_step:
                done = True
                break
            for p in range(n_par):
                nx[p] = xr[p] + step[p]
            nc = _row_terms(g[row], la[row], m, nx, ka[row], free, nr, njac)
            # The gain ratio: the cost's decrease over the linear model's, δᵀ(λ·diag(JᵀJ)·δ − Jᵀr).
            predicted = 0.0
            for p in range(n_par):
                predicted += step[p] * (lam * a[p, p] * step[p] + grad[p])
            if nc <= c:
                small = c - nc <= FTOL * c
                gain = (c - nc) / predicted if predicted != 0 else 0.0
                gain = min(max(gain, 0.0), 1.0) if math.isfinite(gain) else (1.0 if gain > 0 else 0.0)
                for p in range(n_par):
                    xr[p] = nx[p]
                for i in range(m):
                    rr[i] = nr[i]
                    for p in range(n_par):
                        jr[i, p] = njac[i, p]
                c = nc
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
                grow = 2.0
                if small:
                    done = True
                    break
            else:
                lam *= grow
                grow *= 2.0
            if lam >= LM_CEILING:
                done = True
                break
        cost[row] = c
        ok[row] = done
