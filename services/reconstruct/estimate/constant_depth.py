"""The constant-depth model's fits: the mirror-echo condition ``n · p_c + d = h`` solved for the wall's normal
and offset without assuming its direction, by least squares on the sphere (:func:`constant_depth_ls`) and by
least entropy (:func:`constant_depth_fit`, eq. 6–8 of its residuals)."""

from __future__ import annotations

import numpy as np

from lelsonar.reconstruct.estimate.lel import PERFECT_FIT, entropy_of_residuals, newton_minimize
from lelsonar.reconstruct.estimate.normals import norm, tangent_basis

__all__ = ["constant_depth_ls", "constant_depth_fit"]


def constant_depth_ls(
    capsules: np.ndarray,
    distance: np.ndarray,
    normal0: np.ndarray,
    offset0: float,
    mask: np.ndarray | None = None,
    *,
    max_outer: int = 20,
    tol: float = 1e-12,
) -> tuple[np.ndarray, float, int]:
    """Least squares for the constant-depth model: ``min Σ (n · p_c + d − h)²``, ``|n| = 1``.

    Gauss-Newton on the sphere: linearise ``n = normalise(n₀ + u₁e₁ + u₂e₂)``
    in the tangent plane at ``n₀`` — the residual is then affine in
    ``(u₁, u₂, h)`` — solve by LS, renormalise, repeat.

    Returns
    -------
    normal, offset, iterations
    """
    p = np.asarray(capsules, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    if mask is not None:
        p, d = p[np.asarray(mask, dtype=bool)], d[np.asarray(mask, dtype=bool)]
    n = np.asarray(normal0, dtype=np.float64) / norm(np.asarray(normal0, dtype=np.float64))
    h = float(offset0)
    it = 0
    for it in range(1, max_outer + 1):  # noqa: B007 — the iterations taken are returned
        e1, e2 = tangent_basis(n)
        a = np.stack([p @ e1, p @ e2, -np.ones_like(d)], axis=1)
        c = p @ n + d - h
        z, *_ = np.linalg.lstsq(a, -c, rcond=None)
        n_new = n + z[0] * e1 + z[1] * e2
        n = n_new / norm(n_new)
        h += float(z[2])
        if float(np.abs(z[:2]).max()) < tol and abs(float(z[2])) < tol:
            break
    return n, h, it


def constant_depth_fit(
    capsules: np.ndarray,
    distance: np.ndarray,
    normal0: np.ndarray,
    offset0: float,
    *,
    max_outer: int = 10,
    max_tilt_step: float = 0.05,
    tol: float = 1e-10,
) -> tuple[np.ndarray, float, float, int, int, bool]:
    """LEL fit of the constant-depth model ``n · p_c + d = h`` (eq. 6, 8 on its residuals).

    Minimises ``H`` of the residuals ``r_i = n · p_i + d_i − h`` over the unit
    normal ``n`` and ``h``: in the tangent plane at the current ``n`` the
    residual is affine in ``z = (u₁, u₂, h)``, so each outer step minimises
    ``H`` of that affine model with :func:`lelsonar.reconstruct.estimate.lel.newton_minimize`
    (exact Hessian), then renormalises ``n``.  Renormalising changes the
    residuals only to second order, so 2–4 outer steps converge.

    Parameters
    ----------
    capsules : (N, 3) array
        ``p_c``, m.
    distance : (N,) array
        ``d``, m.
    normal0, offset0
        Start, e.g. the paper-corrected LEL or LS plane.
    max_outer : int
    max_tilt_step : float
        Cap on one Newton step in the tangent coordinates (rad, and m for h).
    tol : float
        Stop when the outer step is below ``tol``.

    Returns
    -------
    normal, offset, H, iterations, evaluations, converged
    """
    p = np.asarray(capsules, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    n = np.asarray(normal0, dtype=np.float64) / norm(np.asarray(normal0, dtype=np.float64))
    h = float(offset0)
    its = evs = 0
    converged = False
    for _ in range(max_outer):
        e1, e2 = tangent_basis(n)
        a = np.stack([p @ e1, p @ e2, -np.ones_like(d)], axis=1)
        c = p @ n + d - h
        if np.all(np.abs(c) <= PERFECT_FIT * max(abs(h), 1.0)):  # D = 0 (eq. 6): a perfect fit
            converged = True
            break
        z, _, nit, nev, ok = newton_minimize(np.zeros(3), a, offset=c, max_step=max_tilt_step, gtol=1e-14)
        its += nit
        evs += nev
        n_new = n + z[0] * e1 + z[1] * e2
        n = n_new / norm(n_new)
        h += float(z[2])
        if float(np.abs(z).max()) < tol:
            converged = ok
            break
    r = p @ n + d - h
    hh = 0.0 if np.all(np.abs(r) <= PERFECT_FIT * max(abs(h), 1.0)) else entropy_of_residuals(r)
    return n, h, hh, its, evs, converged
