"""Each wall's direction in the rotation plane and its uncertainty: the pitch from where its echoes are
strongest (:func:`amplitude_pitch`), the wall at a fixed pitch from the ranges (:func:`fixed_pitch_wall`), and
the standard errors of the amplitude window's bias and of a range walk (:func:`walk_stderr`)."""

from __future__ import annotations

import numpy as np

from lelsonar.reconstruct.estimate.corner.model import (
    CornerModel,
    ScanPoints,
    Wall,
)
from lelsonar.reconstruct.estimate.corner.solver import (
    joint_gauss_newton_of,
    joint_residuals_of,
    labelled_order,
    lu_solve,
)
from lelsonar.reconstruct.estimate.robust import fast_median
from lelsonar.signal.compiled import kernel
from lelsonar.signal.summation import pairwise_sum


def amplitude_pitch(
    gamma: np.ndarray,
    amplitude: np.ndarray,
    distance: np.ndarray,
    *,
    top_db: float = 10.0,
    min_steps_each_side: int = 2,
) -> tuple[float, float] | None:
    """The direction a wall faces in the rotation plane, from where its echoes are strongest.

    A mirror echo's amplitude is ``∝ D(ψ)²/(2d)``, ψ the
    angle between the beam and the wall's normal, so amplitude times ``d``
    peaks where the boresight ``(0, cos γ, sin γ)`` faces the wall.  Near the
    peak ``log D²`` is a parabola in γ whatever the capsule, so the vertex of
    ``log(A·d) = aγ² + bγ + c`` fitted to the echoes within ``top_db`` of the
    strongest is the wall's direction ``φ = −b/2a`` (``n ∝ (·, cos φ, sin φ)``).
    The ranges barely constrain this angle (a few-cm lever arm) and cannot see
    a common roll of both walls at all; the amplitudes pin it down.

    Parameters
    ----------
    gamma, amplitude, distance : (N,) arrays
        γ (rad), the echo's own peak amplitude
        (:func:`lelsonar.signal.energy.echo_amplitude`, V) and range (m)
        of one wall's echoes.
    top_db : float
        Echoes within this many dB of the strongest enter the fit.
    min_steps_each_side : int
        The peak must be inside the observed directions: at least this many
        distinct γ on each side of the vertex.

    Returns
    -------
    (φ, σ_φ) in rad, or None when the peak was not observed (a truncated sweep,
    or a σ_φ wider than the directions the fit saw) or the fit is not a peak.
    σ_φ counts the bias of a lopsided window (:func:`window_bias_stderr`).
    Clipped echoes (:func:`clipped_echoes`) are left out: their amplitude is
    only a lower bound, and a parabola through the plateau they form puts its
    vertex anywhere inside it.
    """
    phi, sigma, found = _amplitude_pitch(
        np.asarray(gamma, dtype=np.float64),
        np.asarray(amplitude, dtype=np.float64),
        np.asarray(distance, dtype=np.float64),
        float(top_db),
        int(min_steps_each_side),
    )
    return (phi, sigma) if found else None


@kernel
def _amplitude_pitch(
    g: np.ndarray, a: np.ndarray, d: np.ndarray, top_db: float, min_steps_each_side: int
) -> tuple[float, float, bool]:
    """:func:`amplitude_pitch` as a kernel: ``(φ, σ_φ, found)``."""
    e = a * d
    ok = np.isfinite(g) & np.isfinite(e) & (e > 0)
    if not np.any(ok):
        return np.nan, np.nan, False
    ok &= ~clipped_echoes(np.where(ok, a, np.nan))
    if np.count_nonzero(ok) < 8:
        return np.nan, np.nan, False
    g, le = g[ok], np.log(e[ok])
    top = le >= le.max() - top_db * np.log(10.0) / 20.0  # dB of amplitude
    phi, se, curvature, found = _parabola_vertex(g[top], le[top], min_steps_each_side)
    if not found:
        return np.nan, np.nan, False
    # The vertex is unbiased only where the window is symmetric about it (below): on a truncated or lopsided
    # window the pattern's departure from a parabola shifts it, which the fit's own σ does not count.
    lo, hi = g[top].min(), g[top].max()
    sym = top & (np.abs(g - phi) <= min(phi - lo, hi - phi))
    shift, se_sym, found = _symmetric_vertex(g[sym] - phi, le[sym], curvature)
    if not found:
        return np.nan, np.nan, False  # the peak at the very end of the sweep: nothing on one side of it
    sigma = window_bias_stderr(phi, se, phi + shift, se_sym)
    if sigma > hi - lo:
        return np.nan, np.nan, False  # not located within the directions the fit saw: no peak was observed
    return phi, sigma, True


#: Echoes whose amplitudes agree with the largest to this fraction form a plateau: the receiver clipped them.
CLIP_TOLERANCE = 1e-4
#: Echoes at the largest amplitude it takes to call them clipped (two may tie by symmetry of the beam).
CLIP_MIN_ECHOES = 3


@kernel
def clipped_echoes(amplitude: np.ndarray) -> np.ndarray:
    """Mask of the echoes an ADC or amplifier clipped: those at the largest amplitude, if a plateau forms there.

    A mirror echo's amplitude varies continuously with the
    beam's angle to the wall, the range and the noise, so two echoes of a scan
    hardly ever share their largest amplitude; a receiver that saturates gives
    every echo stronger than its full scale the same peak ``|w|``
    (:func:`lelsonar.signal.energy.echo_amplitude`), within a code.  At
    least :data:`CLIP_MIN_ECHOES` echoes within :data:`CLIP_TOLERANCE` of the
    largest are taken as that plateau.

    Parameters
    ----------
    amplitude : (N,) array
        Peak amplitude of each echo, V; NaN where none.
    """
    finite = np.isfinite(amplitude)
    if not np.any(finite):
        return np.zeros(amplitude.shape, dtype=np.bool_)
    top = finite & (amplitude >= np.max(amplitude[finite]) * (1.0 - CLIP_TOLERANCE))
    return top if np.count_nonzero(top) >= CLIP_MIN_ECHOES else np.zeros(amplitude.shape, dtype=np.bool_)


@kernel
def _parabola_vertex(g: np.ndarray, le: np.ndarray, min_steps_each_side: int) -> tuple[float, float, float, bool]:
    """Vertex ``−b/2a`` of ``le = aγ² + bγ + c``, its standard error and ``a``; False if not a significant peak
    inside."""
    steps = np.unique(g)
    if steps.size < 2 * min_steps_each_side + 1:
        return np.nan, np.nan, np.nan, False
    # The parabola about the mean γ of those echoes (the same vertex, better conditioned than in γ itself):
    # least squares by its normal equations, covariance σ² (XᵀX)⁻¹ with σ² over N − 3 degrees of freedom.
    n = g.shape[0]
    centre = pairwise_sum(g, 0, n) / n
    t = g - centre
    xtx = np.zeros((3, 3))
    xtl = np.zeros(3)
    row = np.ones(3)
    for i in range(n):
        row[0], row[1] = t[i] * t[i], t[i]
        for u in range(3):
            xtl[u] += row[u] * le[i]
            for v in range(3):
                xtx[u, v] += row[u] * row[v]
    inv, ok = lu_solve(xtx, np.eye(3))
    if not ok:
        return np.nan, np.nan, np.nan, False
    coef = inv @ xtl
    res = le - (coef[0] * t * t + coef[1] * t + coef[2])
    cov = (res @ res) / (n - 3) * inv
    a2, b1 = coef[0], coef[1]
    # A peak, and a significant one: amplitudes that do not fall off (a receiver without a beam
    # pattern, saturation everywhere) give a curvature lost in its own error.
    if not (a2 < 0 and -a2 > 3.0 * np.sqrt(max(cov[0, 0], 0.0))):
        return np.nan, np.nan, np.nan, False
    phi = centre - b1 / (2.0 * a2)
    if np.count_nonzero(steps < phi) < min_steps_each_side or np.count_nonzero(steps > phi) < min_steps_each_side:
        return np.nan, np.nan, np.nan, False
    j0, j1 = b1 / (2.0 * a2 * a2), -1.0 / (2.0 * a2)
    var = j0 * (cov[0, 0] * j0 + cov[0, 1] * j1) + j1 * (cov[1, 0] * j0 + cov[1, 1] * j1)
    if not (np.isfinite(var) and var >= 0):
        return np.nan, np.nan, np.nan, False
    return phi, np.sqrt(var), a2, True


@kernel
def _symmetric_vertex(x: np.ndarray, le: np.ndarray, curvature: float) -> tuple[float, float, bool]:
    """Shift of the vertex and its standard error over a window ``x = γ − φ`` symmetric about ``φ``.

    The curvature ``a`` is the full window's (a narrow window hardly measures it); the slope ``b`` of
    ``le − a x²`` at ``x = 0`` (least squares of a line) moves the vertex by ``−b/2a``.  False without an
    echo on each side.
    """
    if not (np.any(x < 0) and np.any(x > 0)):
        return np.nan, np.nan, False
    n = x.shape[0]
    y = le - curvature * x * x
    xc = x - pairwise_sum(x, 0, n) / n
    sxx = xc @ xc  # the slope's unscaled variance is 1/Σ(x − x̄)²
    slope = (xc @ y) / sxx
    r = y - (slope * x + (pairwise_sum(y, 0, n) / n - slope * (pairwise_sum(x, 0, n) / n)))
    s2 = (r @ r) / max(n - 2, 1)
    shift = -slope / (2.0 * curvature)
    se = np.sqrt(max(s2 / sxx, 0.0)) / (2.0 * abs(curvature))
    return shift, se, np.isfinite(shift) and np.isfinite(se)


@kernel
def window_bias_stderr(phi: float, se: float, phi_sym: float, se_sym: float) -> float:
    """Standard error of the amplitude peak's direction ``φ`` with the bias of a lopsided window.

     ``D(ψ)`` is even in the angle ψ between the beam and the wall's normal
    , so ``log D²`` is even about the wall's direction: a
     parabola fitted over echoes symmetric about it has its vertex there
     whatever the pattern's shape (the odd moments of the window vanish).  Over
     a lopsided window — the peak near the end of the sweep, or echoes of one
     side cut by the 10 dB floor — the pattern's quartic and higher terms
     move the vertex toward the longer side; the fit's own σ (white amplitude
     noise about a parabola) does not see that.  The vertex ``φ_sym`` of the
     window made symmetric about ``φ`` (with the full window's curvature:
     :func:`_symmetric_vertex`) measures it: with no bias, ``φ − φ_sym`` is
     noise of variance ``σ_sym² − σ²`` (the full window's fit is the more
     precise of two nested unbiased ones, as in a Hausman test), so only the
     excess is bias: ``σ_φ² = σ² + max(0, (φ − φ_sym)² − (σ_sym² − σ²))``.

     Parameters
     ----------
     phi, se : float
         Vertex and standard error over the full window (rad).
     phi_sym, se_sym : float
         The same over the window symmetric about ``phi`` (rad).
    """
    excess = (phi - phi_sym) ** 2 - max(se_sym**2 - se**2, 0.0)
    return float(np.sqrt(se**2 + max(excess, 0.0)))


#: Range step (m per unit of a walk's regressor) by which :func:`walk_stderr` measures the joint fit's response.
_WALK_STEP = 1.0e-3


def walk_stderr(model: CornerModel, pts: ScanPoints, amplitude: np.ndarray) -> tuple[float, float]:
    """How far each wall's joint normal may be from the truth for ranges that walk with the echoes' amplitude.

    Without the amplitude peak a wall's direction in the rotation plane rests on the ranges' change across
    the sweep through the capsules' radial lever arm ``r`` (``∂d/∂φ = r·sin(γ − φ)``, eq. 9: with ``r`` ≈ 2 cm,
    0.1 mm of range across the wall's echoes is ~1°).  A range error that follows the echo's amplitude —
    a comparator's walk, or what is left of it after constant-fraction re-timing, whose
    noisy peak reads high on weak echoes by about the noise (a bias ∝ 1/A) — follows the beam's angle to
    the wall, so over the echoes of one side of the normal it looks like a roll, and the joint fit's
    covariance (white range noise) does not count it.  Here the joint least squares (eq. 15's mirror-echo
    rows and the edge rows, :func:`~lelsonar.reconstruct.estimate.corner.model.joint_gauss_newton`) gets two more
    columns, ``ln A`` and ``1/A`` (V, centred): by linearity each column's response — the normals' turn
    ``D`` and the residuals' change ``(I − H)x`` per unit of it — gives the walk ``β̂ = M⁻¹Xᵀr`` with
    ``M = Xᵀ(I − H)X`` and its covariance ``s²M⁻¹``.  A normal kept without the walk then misses by
    ``|Dβ̂|`` and has the added variance ``tr(D s²M⁻¹ Dᵀ)`` of a walk the ranges cannot tell from the
    geometry (Schur complement); the result is the root of their sum.  Echoes without an amplitude count
    with a walk of 0 (their regressors at the mean).

    Parameters
    ----------
    model : CornerModel
    pts : ScanPoints
    amplitude : (N,) array
        Each echo's peak amplitude, V (:func:`~lelsonar.signal.energy.echo_amplitude`); NaN: none.

    Returns
    -------
    (σ_a, σ_b) in rad, to add in quadrature to the joint normals' standard errors, at most π (no direction
    at all: also where a walk cannot be told from the walls); 0 where too few echoes were labelled.
    """
    sa, sb = _walk_stderr(
        pts.capsule,
        pts.distance,
        np.asarray(model.labels, dtype=np.intp),
        np.asarray(amplitude, dtype=np.float64),
        model.wall_a.normal,
        float(model.wall_a.offset),
        model.wall_b.normal,
        float(model.wall_b.offset),
        _WALK_STEP,
    )
    return sa, sb


@kernel
def _walk_stderr(
    capsule: np.ndarray,
    distance: np.ndarray,
    labels: np.ndarray,
    amplitude: np.ndarray,
    normal_a: np.ndarray,
    offset_a: float,
    normal_b: np.ndarray,
    offset_b: float,
    step: float,
) -> tuple[float, float]:
    """:func:`walk_stderr` as one kernel (``step``: :data:`_WALK_STEP`)."""
    n = labels.shape[0]
    order = labelled_order(labels)  # wall a's echoes, wall b's, then the edge's (joint_residuals' order)
    m = order.shape[0]
    ok = np.empty(n, dtype=np.bool_)
    n_ok = 0
    for i in range(n):
        ok[i] = np.isfinite(amplitude[i]) and amplitude[i] > 0
        n_ok += ok[i]
    n_used = 0
    for j in range(m):
        n_used += ok[order[j]]
    if m < 8 or n_used < 8:
        return 0.0, 0.0
    strong = np.empty(n_ok)
    j = 0
    for i in range(n):
        if ok[i]:
            strong[j] = amplitude[i]
            j += 1
    typical = fast_median(strong)
    # The regressors ln A and 1/A (scaled by the median amplitude), centred over the labelled echoes that
    # have one; 0 (the mean) where an echo has none.
    columns = np.zeros((2, n))
    raw = np.empty((2, n))
    for i in range(n):
        safe = amplitude[i] if ok[i] else 1.0
        raw[0, i] = np.log(safe)
        raw[1, i] = typical / safe
    used = np.empty(n_used)
    for c in range(2):
        j = 0
        for o in range(m):
            if ok[order[o]]:
                used[j] = raw[c, order[o]]
                j += 1
        mean = pairwise_sum(used, 0, n_used) / n_used
        for i in range(n):
            if ok[i]:
                columns[c, i] = raw[c, i] - mean
    wa, ha, wb, hb, _cov, _moved = joint_gauss_newton_of(
        capsule, distance, labels, normal_a, offset_a, normal_b, offset_b, 3, False, 6, 1e-9
    )
    r0 = joint_residuals_of(capsule, distance, order, labels, wa, ha, wb, hb)
    change = np.empty((2, m))
    turn = np.empty((6, 2))  # d normal / d β: wall a's normal, then wall b's
    for c in range(2):
        moved = distance + step * columns[c]
        ma, mha, mb, mhb, _cov, _moved = joint_gauss_newton_of(
            capsule, moved, labels, wa, ha, wb, hb, 3, False, 6, 1e-9
        )
        r1 = joint_residuals_of(capsule, moved, order, labels, ma, mha, mb, mhb)
        for o in range(m):
            change[c, o] = (r1[o] - r0[o]) / step
        for u in range(3):
            turn[u, c] = (ma[u] - wa[u]) / step
            turn[3 + u, c] = (mb[u] - wb[u]) / step
    # M = Xᵀ(I − H)X over the labelled echoes, symmetrised; Xᵀr; s² over m − 6 − 2 degrees of freedom.
    mm = np.zeros((2, 2))
    xr = np.zeros(2)
    for u in range(2):
        for o in range(m):
            xr[u] += columns[u, order[o]] * r0[o]
        for v in range(2):
            for o in range(m):
                mm[u, v] += columns[u, order[o]] * change[v, o]
    sym = np.empty((2, 2))
    for u in range(2):
        for v in range(2):
            sym[u, v] = 0.5 * (mm[u, v] + mm[v, u])
    s2 = (r0 @ r0) / max(m - 6 - 2, 1)
    m_inv, invertible = lu_solve(sym, np.eye(2))
    if not invertible:
        return np.pi, np.pi
    for u in range(2):
        for v in range(2):
            if not np.isfinite(m_inv[u, v]):
                return np.pi, np.pi
    if not np.all(np.linalg.eigvalsh(sym) > 0):
        return np.pi, np.pi
    beta = m_inv @ xr
    out = np.empty(2)
    for k in range(2):
        dk = turn[3 * k : 3 * k + 3]
        shift = dk @ beta
        cov = s2 * m_inv
        trace = 0.0  # tr(D_k (s² M⁻¹) D_kᵀ)
        for u in range(3):
            for w in range(2):
                t = 0.0
                for v in range(2):
                    t += dk[u, v] * cov[v, w]
                trace += t * dk[u, w]
        out[k] = min(float(np.sqrt(shift @ shift + trace)), np.pi)
    return out[0], out[1]


def fixed_pitch_wall(
    capsules: np.ndarray, distance: np.ndarray, phi: float, phi_se: float, normal0: np.ndarray, iterations: int = 4
) -> tuple[Wall, float, float]:
    """The wall facing direction ``φ`` that best meets the mirror-echo condition ``n·p_c + d = h``.

    ``n = (sin ψ, cos ψ cos φ, cos ψ sin φ)``: the ranges fix the yaw ψ (the
    capsules span 24 cm along x) and the offset h, the amplitudes fix φ.
    Gauss-Newton in (ψ, h).

    Returns
    -------
    wall, normal standard error (rad, RMS of the yaw and φ errors), offset standard error (m)
    """
    n, h, se_n, se_h = _fixed_pitch_wall(
        np.asarray(capsules, dtype=np.float64),
        np.asarray(distance, dtype=np.float64),
        float(phi),
        float(phi_se),
        float(normal0[0]),
        int(iterations),
    )
    return Wall(n, h), se_n, se_h


@kernel
def _pitch_frame(psi: float, cp: float, sp: float) -> tuple[np.ndarray, np.ndarray]:
    """The normal at yaw ``psi`` facing ``(cos φ, sin φ)`` in the rotation plane, and its derivative ∂n/∂ψ."""
    sy, cy = np.sin(psi), np.cos(psi)
    return np.array([sy, cy * cp, cy * sp]), np.array([cy, -sy * cp, -sy * sp])


@kernel
def _fixed_pitch_wall(
    p: np.ndarray, d: np.ndarray, phi: float, phi_se: float, yaw_sine: float, iterations: int
) -> tuple[np.ndarray, float, float, float]:
    """:func:`fixed_pitch_wall` as a kernel: normal, offset and their standard errors.

    The products with the capsules are written out echo by echo (BLAS calls cost more than their
    arithmetic on a wall's few hundred echoes; sums and products round as they did to within a few ulp).
    """
    m = d.shape[0]
    cp, sp = np.cos(phi), np.sin(phi)
    psi = np.arcsin(min(max(yaw_sine, -1.0), 1.0))
    n, dn = _pitch_frame(psi, cp, sp)
    r = np.empty(m)
    x = np.empty(m)
    for i in range(m):
        r[i] = p[i, 0] * n[0] + p[i, 1] * n[1] + p[i, 2] * n[2] + d[i]
    h = pairwise_sum(r, 0, m) / m
    for _ in range(iterations):
        # Least squares of r + x·δψ − δh = 0 (x = p·∂n/∂ψ) in closed form: δψ from the centred x and r, δh
        # from the means.  Quadratic convergence: stop once the step is below rounding.
        _mirror_terms(p, d, n, dn, h, r, x)
        x_mean = pairwise_sum(x, 0, m) / m
        sxx = 0.0
        sxr = 0.0
        for i in range(m):
            xc = x[i] - x_mean
            sxx += xc * xc
            sxr += xc * r[i]
        step_psi = -sxr / sxx if sxx > 0 else 0.0
        psi += step_psi
        h += pairwise_sum(r, 0, m) / m + x_mean * step_psi
        n, dn = _pitch_frame(psi, cp, sp)
        if abs(step_psi) < 1e-13:
            break
    _mirror_terms(p, d, n, dn, h, r, x)
    # JᵀJ of the columns ∂r/∂ψ = p·∂n/∂ψ and ∂r/∂h = −1: [[Σx², −Σx], [−Σx, m]]
    sxx = 0.0
    srr = 0.0
    for i in range(m):
        sxx += x[i] * x[i]
        srr += r[i] * r[i]
    sx = pairwise_sum(x, 0, m)
    det = sxx * m - sx * sx
    if det > 1e-3 * sxx * m:  # well conditioned: its inverse in closed form (≤ 1e-12 of the SVD's, tested)
        inv00, inv11 = m / det, sxx / det
    else:  # (nearly) one capsule's lever arm: the pseudo-inverse of the rank-deficient matrix
        jtj = np.empty((2, 2))
        jtj[0, 0], jtj[0, 1], jtj[1, 0], jtj[1, 1] = sxx, -sx, -sx, float(m)
        pinv = np.linalg.pinv(jtj)
        inv00, inv11 = pinv[0, 0], pinv[1, 1]
    s2 = srr / max(m - 2, 1)
    # φ's own error moves h through the capsules' lever arm: ∂r/∂φ = p·∂n/∂φ.
    dn1, dn2 = -np.cos(psi) * sp, np.cos(psi) * cp
    for i in range(m):
        x[i] = p[i, 1] * dn1 + p[i, 2] * dn2
    dh_dphi = pairwise_sum(x, 0, m) / m
    se_n = np.sqrt(max(s2 * inv00, 0.0) + phi_se**2)
    se_h = np.sqrt(max(s2 * inv11, 0.0) + (dh_dphi * phi_se) ** 2)
    return n, h, se_n, se_h


@kernel
def _mirror_terms(
    p: np.ndarray, d: np.ndarray, n: np.ndarray, dn: np.ndarray, h: float, r: np.ndarray, x: np.ndarray
) -> None:
    """Into ``r`` and ``x``: the mirror-echo residuals ``n·p_c + d − h`` and their derivatives ``p_c·∂n/∂ψ``."""
    for i in range(d.shape[0]):
        r[i] = p[i, 0] * n[0] + p[i, 1] * n[1] + p[i, 2] * n[2] + d[i] - h
        x[i] = p[i, 0] * dn[0] + p[i, 1] * dn[1] + p[i, 2] * dn[2]
