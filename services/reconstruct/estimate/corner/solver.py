"""The joint Gauss-Newton of a corner model: both walls fitted at once on their labelled echoes, the edge's
double bounces tying them together, with the alternating assignment that refines a hypothesis."""

from __future__ import annotations

import numpy as np

from lelsonar.reconstruct.estimate.corner.model import (
    ECHO_EDGE,
    ECHO_OUTLIER,
    ECHO_WALL_A,
    ECHO_WALL_B,
    ScanPoints,
    Wall,
    assign_labels,
)
from lelsonar.reconstruct.estimate.normals import tangent_basis
from lelsonar.signal.compiled import kernel


def joint_residuals(wall_a: Wall, wall_b: Wall, pts: ScanPoints, labels: np.ndarray) -> np.ndarray:
    """Range residuals (m) of the labelled echoes under their models: wall a, wall b, then the edge."""
    lab = np.asarray(labels, dtype=np.intp)
    return joint_residuals_of(
        pts.capsule,
        pts.distance,
        labelled_order(lab),
        lab,
        np.asarray(wall_a.normal, dtype=np.float64),
        float(wall_a.offset),
        np.asarray(wall_b.normal, dtype=np.float64),
        float(wall_b.offset),
    )


@kernel
def labelled_order(labels: np.ndarray) -> np.ndarray:
    """Indices of the echoes labelled wall a, then wall b, then the edge, each in the scan's order."""
    m = 0
    for i in range(labels.shape[0]):
        if labels[i] == ECHO_WALL_A or labels[i] == ECHO_WALL_B or labels[i] == ECHO_EDGE:
            m += 1
    order = np.empty(m, dtype=np.intp)
    j = 0
    for k in (ECHO_WALL_A, ECHO_WALL_B, ECHO_EDGE):
        for i in range(labels.shape[0]):
            if labels[i] == k:
                order[j] = i
                j += 1
    return order


@kernel
def joint_residuals_of(
    capsule: np.ndarray,
    distance: np.ndarray,
    order: np.ndarray,
    labels: np.ndarray,
    na: np.ndarray,
    ha: float,
    nb: np.ndarray,
    hb: float,
) -> np.ndarray:
    """:func:`~lelsonar.reconstruct.estimate.corner.model.joint_residuals` of the echoes ``order`` lists (m)."""
    c = na[0] * nb[0] + na[1] * nb[1] + na[2] * nb[2]
    out = np.empty(order.shape[0])
    for o in range(order.shape[0]):
        i = order[o]
        p0, p1, p2 = capsule[i, 0], capsule[i, 1], capsule[i, 2]
        pa = p0 * na[0] + p1 * na[1] + p2 * na[2]
        pb = p0 * nb[0] + p1 * nb[1] + p2 * nb[2]
        a, b = ha - pa, hb - pb
        if labels[i] == ECHO_WALL_A:
            out[o] = pa + distance[i] - ha  # n·p_c + d − h, as mirror_residuals
        elif labels[i] == ECHO_WALL_B:
            out[o] = pb + distance[i] - hb
        elif 1.0 - c * c < 1e-18:  # walls parallel: no edge (joint_gauss_newton's min_sine²)
            out[o] = np.inf
        else:
            out[o] = distance[i] - np.sqrt(max(a * a + b * b - 2.0 * c * a * b, 0.0))
    return out


def joint_gauss_newton(
    wall_a: Wall,
    wall_b: Wall,
    pts: ScanPoints,
    labels: np.ndarray,
    *,
    iterations: int = 3,
    covariance: bool = True,
    trials: int = 6,
    min_sine: float = 1e-9,
) -> tuple[tuple[Wall, Wall], np.ndarray]:
    """Least squares of all labelled echoes over both walls at once (6 parameters).

    Each wall is ``n = normalise(n₀ + u₁e₁ + u₂e₂)``, ``h``; the edge echoes tie
    the two walls together through their intersection, which pins down the
    pitch that each wall's own echoes (a few-cm lever arm) barely constrain.
    Levenberg-damped Gauss-Newton (up to ``trials`` dampings, ×10 each) with
    the exact Jacobian: ``∂r/∂u = p_c·e``, ``∂r/∂h = −1`` for the mirror rows,
    and for the edge rows ``r = d − √q``, ``q = a² + b² − 2abc``
    (:func:`edge_range_terms`), ``∂r/∂u_a = (p_c·e)(a − bc)/√q + (ab/√q)(n_b·e)``,
    ``∂r/∂h_a = −(a − bc)/√q`` and the same for wall b with a and b swapped.

    Returns the walls and the (6, 6) covariance of ``(u₁, u₂, h)`` of wall a
    then wall b (``σ² (JᵀJ)⁻¹``, σ² from the residuals; ``inf`` if
    unconstrained or not asked for with ``covariance=False``).
    """
    na, ha, nb, hb, cov, moved = joint_gauss_newton_of(
        pts.capsule,
        pts.distance,
        np.asarray(labels, dtype=np.intp),
        wall_a.normal,
        float(wall_a.offset),
        wall_b.normal,
        float(wall_b.offset),
        iterations,
        covariance,
        trials,
        min_sine,
    )
    return ((Wall(na, ha), Wall(nb, hb)) if moved else (wall_a, wall_b)), cov


@kernel
def _joint_cost(
    capsule: np.ndarray,
    distance: np.ndarray,
    labels: np.ndarray,
    na: np.ndarray,
    ha: float,
    nb: np.ndarray,
    hb: float,
    min_sine: float,
) -> tuple[float, bool]:
    """Sum of squares of the labelled echoes' range residuals (:func:`joint_residuals`), and whether all are finite."""
    # edge_range_terms' a, b and range, echo by echo (the solver's trials call this: no arrays allocated)
    c = na[0] * nb[0] + na[1] * nb[1] + na[2] * nb[2]
    edge = 1.0 - c * c >= min_sine * min_sine
    total = 0.0
    for i in range(labels.shape[0]):
        k = labels[i]
        if k != ECHO_WALL_A and k != ECHO_WALL_B and k != ECHO_EDGE:
            continue
        a = ha - (capsule[i, 0] * na[0] + capsule[i, 1] * na[1] + capsule[i, 2] * na[2])
        b = hb - (capsule[i, 0] * nb[0] + capsule[i, 1] * nb[1] + capsule[i, 2] * nb[2])
        if k == ECHO_WALL_A:
            r = distance[i] - a
        elif k == ECHO_WALL_B:
            r = distance[i] - b
        else:
            r = distance[i] - np.sqrt(max(a * a + b * b - 2.0 * c * a * b, 0.0)) if edge else np.inf
        total += r * r
    return total, np.isfinite(total)


@kernel
def _joint_normal_equations(
    capsule: np.ndarray,
    distance: np.ndarray,
    labels: np.ndarray,
    na: np.ndarray,
    ha: float,
    nb: np.ndarray,
    hb: float,
    ea1: np.ndarray,
    ea2: np.ndarray,
    eb1: np.ndarray,
    eb2: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``JᵀJ`` and ``Jᵀr`` of the labelled echoes, with :func:`joint_gauss_newton`'s Jacobian.

    A wall's mirror rows ``(p_c·e₁, p_c·e₂, −1)`` touch only its own 3×3 block: their sums are
    kept apart from the edge rows' (which touch all six parameters) and added at the end.
    """
    c = na[0] * nb[0] + na[1] * nb[1] + na[2] * nb[2]
    # Per wall: Σx₁², Σx₁x₂, Σx₁, Σx₂², Σx₂, count, then Σx₁r, Σx₂r, Σr — scalars, echo by echo in the
    # scan's order (no per-echo array views: their reference counting cost more than the sums).
    a11 = a12 = a1 = a22 = a2 = a0 = ar1 = ar2 = ar = 0.0
    b11 = b12 = b1 = b22 = b2 = b0 = br1 = br2 = br = 0.0
    jtj = np.zeros((6, 6))
    g = np.zeros(6)
    row = np.zeros(6)
    # n_b·e (wall a's tangents) and n_a·e (wall b's): how the other wall's normal turns the edge's range.
    nb_ea1 = nb[0] * ea1[0] + nb[1] * ea1[1] + nb[2] * ea1[2]
    nb_ea2 = nb[0] * ea2[0] + nb[1] * ea2[1] + nb[2] * ea2[2]
    na_eb1 = na[0] * eb1[0] + na[1] * eb1[1] + na[2] * eb1[2]
    na_eb2 = na[0] * eb2[0] + na[1] * eb2[1] + na[2] * eb2[2]
    for i in range(labels.shape[0]):
        k = labels[i]
        if k != ECHO_WALL_A and k != ECHO_WALL_B and k != ECHO_EDGE:
            continue
        p0, p1, p2 = capsule[i, 0], capsule[i, 1], capsule[i, 2]
        # edge_range_terms' a and b, echo by echo (no arrays allocated)
        a = ha - (p0 * na[0] + p1 * na[1] + p2 * na[2])
        b = hb - (p0 * nb[0] + p1 * nb[1] + p2 * nb[2])
        if k == ECHO_WALL_A:
            r = distance[i] - a
            x1 = p0 * ea1[0] + p1 * ea1[1] + p2 * ea1[2]
            x2 = p0 * ea2[0] + p1 * ea2[1] + p2 * ea2[2]
            a11 += x1 * x1
            a12 += x1 * x2
            a1 += x1
            a22 += x2 * x2
            a2 += x2
            a0 += 1.0
            ar1 += x1 * r
            ar2 += x2 * r
            ar += r
        elif k == ECHO_WALL_B:
            r = distance[i] - b
            x1 = p0 * eb1[0] + p1 * eb1[1] + p2 * eb1[2]
            x2 = p0 * eb2[0] + p1 * eb2[1] + p2 * eb2[2]
            b11 += x1 * x1
            b12 += x1 * x2
            b1 += x1
            b22 += x2 * x2
            b2 += x2
            b0 += 1.0
            br1 += x1 * r
            br2 += x2 * r
            br += r
        else:
            rng = np.sqrt(max(a * a + b * b - 2.0 * c * a * b, 0.0))
            r = distance[i] - rng
            inv = 1.0 / max(rng, 1e-12)
            ga, gb, gab = (a - b * c) * inv, (b - a * c) * inv, a * b * inv
            row[0] = (p0 * ea1[0] + p1 * ea1[1] + p2 * ea1[2]) * ga + gab * nb_ea1
            row[1] = (p0 * ea2[0] + p1 * ea2[1] + p2 * ea2[2]) * ga + gab * nb_ea2
            row[2] = -ga
            row[3] = (p0 * eb1[0] + p1 * eb1[1] + p2 * eb1[2]) * gb + gab * na_eb1
            row[4] = (p0 * eb2[0] + p1 * eb2[1] + p2 * eb2[2]) * gb + gab * na_eb2
            row[5] = -gb
            for u in range(6):
                g[u] += row[u] * r
                for v in range(u, 6):
                    jtj[u, v] += row[u] * row[v]
    jtj[0, 0] += a11
    jtj[0, 1] += a12
    jtj[0, 2] -= a1
    jtj[1, 1] += a22
    jtj[1, 2] -= a2
    jtj[2, 2] += a0
    g[0] += ar1
    g[1] += ar2
    g[2] -= ar
    jtj[3, 3] += b11
    jtj[3, 4] += b12
    jtj[3, 5] -= b1
    jtj[4, 4] += b22
    jtj[4, 5] -= b2
    jtj[5, 5] += b0
    g[3] += br1
    g[4] += br2
    g[5] -= br
    for u in range(6):
        for v in range(u):
            jtj[u, v] = jtj[v, u]
    return jtj, g


@kernel
def lu_solve(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """``a⁻¹ b`` (b one or more columns) by LU with partial pivoting, as LAPACK's ``gesv``; False if ``a`` is
    singular."""
    n = a.shape[0]
    lu = a.copy()
    x = b.copy()
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(lu[i, k]) > abs(lu[p, k]):
                p = i
        if lu[p, k] == 0.0:
            return x, False
        if p != k:
            for j in range(n):
                lu[k, j], lu[p, j] = lu[p, j], lu[k, j]
            for j in range(x.shape[1]):
                x[k, j], x[p, j] = x[p, j], x[k, j]
        for i in range(k + 1, n):
            f = lu[i, k] / lu[k, k]
            for j in range(k + 1, n):
                lu[i, j] -= f * lu[k, j]
            for j in range(x.shape[1]):
                x[i, j] -= f * x[k, j]
    for k in range(n - 1, -1, -1):
        for j in range(x.shape[1]):
            s = x[k, j]
            for i in range(k + 1, n):
                s -= lu[k, i] * x[i, j]
            x[k, j] = s / lu[k, k]
    return x, True


@kernel
def joint_gauss_newton_of(
    capsule: np.ndarray,
    distance: np.ndarray,
    labels: np.ndarray,
    normal_a: np.ndarray,
    offset_a: float,
    normal_b: np.ndarray,
    offset_b: float,
    iterations: int,
    covariance: bool,
    trials: int,
    min_sine: float,
) -> tuple[np.ndarray, float, np.ndarray, float, np.ndarray, bool]:
    """:func:`joint_gauss_newton` on arrays; the last value says whether the walls moved from the start."""
    return joint_gauss_newton_from(
        capsule,
        distance,
        labels,
        normal_a,
        offset_a,
        normal_b,
        offset_b,
        iterations,
        covariance,
        trials,
        min_sine,
        np.nan,
    )


@kernel
def assigned_cost(labels: np.ndarray, residuals: np.ndarray) -> float:
    """:func:`_joint_cost` of the walls an assignment was made with, from its residuals (the same terms in the
    same order: :func:`echo_residual` computes each labelled echo's residual as :func:`_joint_cost` does)."""
    total = 0.0
    for i in range(labels.shape[0]):
        k = labels[i]
        if k == ECHO_WALL_A or k == ECHO_WALL_B or k == ECHO_EDGE:
            total += residuals[i] * residuals[i]
    return total


@kernel
def joint_gauss_newton_from(
    capsule: np.ndarray,
    distance: np.ndarray,
    labels: np.ndarray,
    normal_a: np.ndarray,
    offset_a: float,
    normal_b: np.ndarray,
    offset_b: float,
    iterations: int,
    covariance: bool,
    trials: int,
    min_sine: float,
    cost0: float,
) -> tuple[np.ndarray, float, np.ndarray, float, np.ndarray, bool]:
    """:func:`joint_gauss_newton_of` given the start's :func:`_joint_cost` ``cost0`` (finite; NaN: work it out)."""
    cov = np.full((6, 6), np.inf)
    na, ha, nb, hb = normal_a.copy(), offset_a, normal_b.copy(), offset_b
    m = 0
    for i in range(labels.shape[0]):
        if labels[i] == ECHO_WALL_A or labels[i] == ECHO_WALL_B or labels[i] == ECHO_EDGE:
            m += 1
    if m < 7:
        return na, ha, nb, hb, cov, False
    if np.isnan(cost0):
        c0, finite = _joint_cost(capsule, distance, labels, na, ha, nb, hb, min_sine)
    else:
        c0, finite = cost0, True
    if not finite:
        return na, ha, nb, hb, cov, False
    lam = 1e-6
    for _ in range(iterations):
        ea1, ea2 = tangent_basis(na)
        eb1, eb2 = tangent_basis(nb)
        jtj, g = _joint_normal_equations(capsule, distance, labels, na, ha, nb, hb, ea1, ea2, eb1, eb2)
        rhs = np.empty((6, 1))
        for u in range(6):
            rhs[u, 0] = -g[u]
        accepted = False
        for _attempt in range(trials):
            damped = jtj.copy()
            for u in range(6):
                damped[u, u] = jtj[u, u] + lam * (jtj[u, u] + 1e-12)
            dz, ok = lu_solve(damped, rhs)
            if not ok:
                lam *= 10
                continue
            ta = na + ea1 * dz[0, 0] + ea2 * dz[1, 0]
            ta /= np.sqrt(ta[0] * ta[0] + ta[1] * ta[1] + ta[2] * ta[2])
            tb = nb + eb1 * dz[3, 0] + eb2 * dz[4, 0]
            tb /= np.sqrt(tb[0] * tb[0] + tb[1] * tb[1] + tb[2] * tb[2])
            tha, thb = ha + dz[2, 0], hb + dz[5, 0]
            c1, finite1 = _joint_cost(capsule, distance, labels, ta, tha, tb, thb, min_sine)
            if finite1 and c1 <= c0:
                na, ha, nb, hb, c0 = ta, tha, tb, thb, c1
                lam = max(lam / 10, 1e-9)
                accepted = True
                break
            lam *= 10
        if not accepted:
            break
    if covariance:
        ea1, ea2 = tangent_basis(na)
        eb1, eb2 = tangent_basis(nb)
        jtj, _g = _joint_normal_equations(capsule, distance, labels, na, ha, nb, hb, ea1, ea2, eb1, eb2)
        inv, ok = lu_solve(jtj, np.eye(6))
        if ok:
            cov = c0 / (m - 6) * inv
    return na, ha, nb, hb, cov, True


@kernel
def refine_walls(
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    na: np.ndarray,
    ha: float,
    nb: np.ndarray,
    hb: float,
    tolerances: np.ndarray,
    cos_t: float,
    min_points: int,
    axis_a: np.ndarray,
    axis_b: np.ndarray,
    cos_max_tilt: float,
    first_labels: np.ndarray,
    first_residuals: np.ndarray,
) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Alternate assignment and one joint Gauss-Newton step at each (tolerance, edge tolerance) of ``tolerances``.

    ``first_labels``, ``first_residuals``: the first stage's assignment of the starting walls, if the caller
    made it already (empty: made here).
    """
    for s in range(tolerances.shape[0]):
        if s == 0 and first_labels.shape[0] > 0:
            labels, res = first_labels.copy(), first_residuals  # (the labels are changed below; the residuals not)
        else:
            labels, res = assign_labels(
                capsule, distance, beam, na, ha, nb, hb, cos_t, tolerances[s, 0], tolerances[s, 1]
            )
        for k in (ECHO_WALL_A, ECHO_WALL_B):
            if np.count_nonzero(labels == k) < min_points:
                labels[labels == k] = ECHO_OUTLIER  # too few to move this wall
        fa, fha, fb, fhb, _cov, _moved = joint_gauss_newton_from(
            capsule, distance, labels, na, ha, nb, hb, 1, False, 6, 1e-9, assigned_cost(labels, res)
        )
        # Keep each wall within max_tilt of its nominal axis: beyond, the solver is chasing the other
        # wall's or the edge's echoes.
        if fa[0] * axis_a[0] + fa[1] * axis_a[1] + fa[2] * axis_a[2] >= cos_max_tilt and fha > 0:
            na, ha = fa, fha
        if fb[0] * axis_b[0] + fb[1] * axis_b[1] + fb[2] * axis_b[2] >= cos_max_tilt and fhb > 0:
            nb, hb = fb, fhb
    return na, ha, nb, hb
