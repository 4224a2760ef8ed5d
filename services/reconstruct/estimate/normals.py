"""Unit normals and what is known of them: the cross product and a tangent basis (the Gauss-Newton steps on
the sphere), θ's covariance and the standard errors of the normal and offset it gives, and the patch of a
plane the echoes observed."""

from __future__ import annotations

import numpy as np

from lelsonar.signal.compiled import kernel

__all__ = [
    "norm",
    "cross3",
    "tangent_basis",
    "theta_covariance",
    "theta_covariance_of",
    "normal_offset_stderr",
    "normal_offset_stderr_of",
    "observed_patch",
    "observed_patch_of",
]


def norm(v: np.ndarray) -> float:
    """|v| of a 1-D vector: ``np.linalg.norm``'s ``sqrt(v · v)``, without its argument handling."""
    return float(np.sqrt(v @ v))


@kernel
def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of two 3-vectors, with the same roundings (each product rounded, then the difference)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def theta_covariance(
    theta: np.ndarray, points: np.ndarray, shift: np.ndarray | float = 0.0, mask: np.ndarray | None = None
) -> np.ndarray:
    """Covariance of θ from the inlier residuals (Gauss-Newton, 1/m²).

    ``C = σ² (JᵀJ)⁻¹`` with ``J = ∂r/∂θ`` of the metric residual
    (:func:`~lelsonar.reconstruct.estimate.fit.metric_residuals`) and ``σ² = Σ r² / (m − 3)`` over the ``m``
    inliers.  For the paper model at the solution this is
    ``σ_e² (VᵀV)⁻¹``, the textbook covariance of eq. (15).  For the
    constant-depth model ``J`` uses the capsule positions, so the covariance
    honestly reflects the short lever arm that pins the normal down.

    Returns a (3, 3) symmetric matrix; ``inf`` on the diagonal where the
    inliers do not constrain θ (fewer than 4 inliers or a singular ``JᵀJ``).
    """
    t = np.asarray(theta, dtype=np.float64)
    x = np.asarray(points, dtype=np.float64)
    sh = np.asarray(shift, dtype=np.float64)
    if mask is not None:  # (no mask: every point, used as it is — the same numbers as a copy's)
        m = np.asarray(mask, dtype=bool)
        x = x[m]
        sh = np.broadcast_to(sh, m.shape)[m] if sh.ndim else sh
    # A scalar shift (the paper model's 0) is added to every residual: the same sums as the broadcast array's.
    return theta_covariance_of(t, x, np.broadcast_to(sh, x.shape[:1]))


@kernel
def theta_covariance_of(t: np.ndarray, x: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """:func:`theta_covariance` of the points ``x`` (every one an inlier), ``shift`` one per point."""
    k = x.shape[0]
    unconstrained = np.diag(np.full(3, np.inf))
    if k <= 3:
        return unconstrained
    nt = np.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
    nt3 = nt**3
    jtj = np.zeros((3, 3))
    ss = 0.0
    jac = np.empty(3)
    for i in range(k):
        q = x[i, 0] * t[0] + x[i, 1] * t[1] + x[i, 2] * t[2] - 1.0
        r = q / nt + shift[i]
        ss += r * r
        for u in range(3):
            jac[u] = x[i, u] / nt - q * t[u] / nt3
        for u in range(3):
            for v in range(u, 3):  # the upper triangle (jac[u]·jac[v] rounds as jac[v]·jac[u]), mirrored below
                jtj[u, v] += jac[u] * jac[v]
    for u in range(3):
        for v in range(u):
            jtj[u, v] = jtj[v, u]
    s2 = ss / (k - 3)
    sv = np.linalg.svd(jtj)[1]  # np.linalg.cond(jtj) (0/0 counts as inf), without its bookkeeping
    if sv[-1] == 0.0 or not sv[0] / sv[-1] <= 1e15:
        return unconstrained
    cov = s2 * np.linalg.inv(jtj)
    return 0.5 * (cov + cov.T)


def normal_offset_stderr(theta: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    """Standard errors of the normal direction (rad) and offset (m) from ``cov(θ)``.

    ``n = θ/|θ|`` has Jacobian ``(I − n nᵀ)/|θ|``; the returned angle error is
    the root of the trace of ``cov(n)`` (the RMS tilt of the normal).
    ``h = 1/|θ|`` has gradient ``−h² n``.
    """
    return normal_offset_stderr_of(np.asarray(theta, dtype=np.float64), np.asarray(cov, dtype=np.float64))


@kernel
def normal_offset_stderr_of(t: np.ndarray, c: np.ndarray) -> tuple[float, float]:
    """:func:`normal_offset_stderr` of θ ``t`` and its covariance ``c`` (float arrays; a kernel)."""
    if not np.isfinite(c).all():
        return np.inf, np.inf
    nt = np.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
    n = t / nt
    h = 1.0 / nt
    # trace(J C Jᵀ) with J = (I − n nᵀ)/|θ|, and n·C·n, written out (3×3 BLAS calls cost more than their
    # arithmetic; the sums round as they did to within a few ulp).
    jn = np.empty((3, 3))
    for u in range(3):
        for v in range(3):
            jn[u, v] = ((1.0 if u == v else 0.0) - n[u] * n[v]) / nt
    var_n = 0.0
    ncn = 0.0
    for u in range(3):
        cn = 0.0
        for w in range(3):
            t_uw = 0.0
            for v in range(3):
                t_uw += jn[u, v] * c[v, w]
            var_n += t_uw * jn[u, w]
            cn += n[w] * c[w, u]
        ncn += cn * n[u]
    var_h = h**4 * ncn
    return np.sqrt(max(var_n, 0.0)), np.sqrt(max(var_h, 0.0))


def observed_patch(normal: np.ndarray, offset: float, foot: np.ndarray) -> np.ndarray:
    """Corners of the bounding rectangle of ``foot`` points projected on the plane.

    The rectangle's sides follow the rotation axis x (projected on the plane)
    and ``n × x``.  Returns (4, 3) corners in order around the rectangle, m.
    """
    return observed_patch_of(np.asarray(normal, dtype=np.float64), float(offset), np.asarray(foot, dtype=np.float64))


@kernel
def observed_patch_of(n: np.ndarray, offset: float, foot: np.ndarray) -> np.ndarray:
    """:func:`observed_patch` of a unit normal ``n`` and float ``foot`` points (a kernel)."""
    u = -n[0] * n
    u[0] += 1.0  # x − (x·n) n
    nu = np.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
    if nu < 1e-6:
        u = -n[1] * n
        u[1] += 1.0
        nu = np.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
    u /= nu
    w = cross3(n, u)
    a0 = b0 = np.inf
    a1 = b1 = -np.inf
    for i in range(foot.shape[0]):
        s = foot[i, 0] * n[0] + foot[i, 1] * n[1] + foot[i, 2] * n[2] - offset
        p0, p1, p2 = foot[i, 0] - s * n[0], foot[i, 1] - s * n[1], foot[i, 2] - s * n[2]
        a = p0 * u[0] + p1 * u[1] + p2 * u[2]
        b = p0 * w[0] + p1 * w[1] + p2 * w[2]
        a0, a1, b0, b1 = min(a0, a), max(a1, a), min(b0, b), max(b1, b)
    ca = (a0, a1, a1, a0)
    cb = (b0, b0, b1, b1)
    out = np.empty((4, 3))
    for j in range(4):
        for v in range(3):
            out[j, v] = offset * n[v] + ca[j] * u[v] + cb[j] * w[v]  # o + ca·u + cb·w, element by element
    return out


@kernel
def tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal ``e₁, e₂`` of the plane normal to the unit ``n`` (``e₁`` away from ``n``'s smallest axis).

    Every Gauss-Newton step on the sphere builds one (the constant-depth fits, the joint corner model).
    """
    k = 0
    for j in (1, 2):
        if abs(n[j]) < abs(n[k]):  # np.argmin: the first smallest
            k = j
    helper = np.zeros(3)
    helper[k] = 1.0
    e1 = cross3(n, helper)
    e1 /= np.sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2])
    return e1, cross3(n, e1)
