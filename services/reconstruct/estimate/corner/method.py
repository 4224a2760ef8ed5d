"""The method ``"corner"``: the joint corner model, then each wall refined on its own echoes.

:mod:`lelsonar.reconstruct.estimate.corner.model` labels every echo of the scan (wall a,
wall b, the edge, outlier) and fits both walls jointly.  Here each wall gets
its final plane — its direction in the rotation plane from where its echoes
are strongest (:func:`amplitude_pitch`), its yaw and offset from the ranges
(:func:`fixed_pitch_wall`), or the paper-corrected points checked against the
joint fit where the sweep never passed the amplitude peak — and its trust
verdict; the critical step is where the boresight meets the final planes'
edge (:func:`corner_edge`).
"""

from __future__ import annotations

import math
import time

import numpy as np

from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate import fit as F
from lelsonar.reconstruct.estimate.corner.model import (
    ECHO_EDGE,
    ECHO_OUTLIER,
    ECHO_WALL_A,
    ECHO_WALL_B,
    CornerModel,
    ScanPoints,
    Wall,
    band_offsets,
    echo_residuals,
    edge_alternatives,
    edge_line,
    edge_shared_shares,
    fit_corner_model,
    joint_gauss_newton_arrays,
    joint_residuals_arrays,
    labelled_order,
    lu_solve,
    mirror_residuals,
    roll_angle,
    scan_points,
)
from lelsonar.reconstruct.estimate.correct import AXIS_Y, AXIS_Z
from lelsonar.reconstruct.estimate.estimators import diagnostics, fit_adaptive, run_estimator
from lelsonar.reconstruct.estimate.fit import fast_median
from lelsonar.reconstruct.estimate.lel import pairwise_sum
from lelsonar.reconstruct.estimate.options import FitOptions, ScanFit
from lelsonar.reconstruct.estimate.quality import (
    DEGRADED,
    UNRELIABLE,
    QualityLimits,
    assess_beside_unexplained,
    assess_plane,
    unexplained_finding,
)
from lelsonar.reconstruct.estimate.results import EdgeLine, FailureReason, FitFailure, PlaneFit, PlaneResult
from lelsonar.reconstruct.estimate.split import critical_step, split_subsets
from lelsonar.reconstruct.estimate.unexplained import echoes_against_walls
from lelsonar.signal.compiled import kernel
from lelsonar.signal.energy import ECHO_PEAK_WINDOW

__all__ = ["corner_edge", "amplitude_pitch", "fixed_pitch_wall", "walk_stderr", "fit_corner"]


def corner_edge(
    plane_a: PlaneResult, plane_b: PlaneResult, *, min_angle: float = np.deg2rad(5.0)
) -> EdgeLine | FitFailure:
    """The line where the two planes meet.

    Direction ``n_a × n_b`` (normalised) and the point of the line closest to
    the origin, as :func:`lelsonar.reconstruct.estimate.corner.model.edge_line` gives
    them, with first-order standard errors.

    Returns FitFailure if a plane is missing or the planes are within
    ``min_angle`` of parallel.
    """
    if not isinstance(plane_a, PlaneFit) or not isinstance(plane_b, PlaneFit):
        return FitFailure(FailureReason.TOO_FEW_POINTS, "the edge needs both planes", "edge", 0)
    na, nb = plane_a.normal, plane_b.normal
    angle = float(np.arccos(min(max(float(na @ nb), -1.0), 1.0)))  # (np.clip of a scalar costs more)
    line = edge_line(Wall(na, plane_a.offset), Wall(nb, plane_b.offset), min_angle)
    if line is None:
        return FitFailure(
            FailureReason.DEGENERATE_GEOMETRY,
            f"the planes are {np.rad2deg(angle):.1f}° apart, nearly parallel",
            "edge",
            0,
        )
    point, direction = line
    s = math.sin(angle)  # (math's sin and sqrt on floats: the same numbers as NumPy's, without the ufunc calls)
    # First order: an offset error δh moves the line by δh / sin(angle); a tilt δ of a normal moves it by h·δ
    # and turns it by δ / sin(angle).
    point_se = (
        math.sqrt(
            plane_a.offset_stderr**2
            + plane_b.offset_stderr**2
            + (plane_a.offset * plane_a.normal_stderr) ** 2
            + (plane_b.offset * plane_b.normal_stderr) ** 2
        )
        / s
    )
    direction_se = float(np.hypot(plane_a.normal_stderr, plane_b.normal_stderr) / s)
    # (edge_line's fresh arrays: a finite point and a unit direction of two valid planes, an angle in [0, π])
    return EdgeLine._owned(point, direction, angle, point_se, direction_se)


def amplitude_pitch(
    gamma: np.ndarray,
    amplitude: np.ndarray,
    distance: np.ndarray,
    *,
    top_db: float = 10.0,
    min_steps_each_side: int = 2,
) -> tuple[float, float] | None:
    """The direction a wall faces in the rotation plane, from where its echoes are strongest.

    A mirror echo's amplitude is ``∝ D(ψ)²/(2d)`` (design notes §8), ψ the
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

    A mirror echo's amplitude (design notes §8) varies continuously with the
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
    """Vertex ``−b/2a`` of ``le = aγ² + bγ + c``, its standard error and ``a``.

    False if not a significant peak inside."""
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
    (design notes §8), so ``log D²`` is even about the wall's direction: a
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
    a comparator's walk (design notes §8), or what is left of it after constant-fraction re-timing, whose
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
    wa, ha, wb, hb, _cov, _moved = joint_gauss_newton_arrays(
        capsule, distance, labels, normal_a, offset_a, normal_b, offset_b, 3, False, 6, 1e-9
    )
    r0 = joint_residuals_arrays(capsule, distance, order, labels, wa, ha, wb, hb)
    change = np.empty((2, m))
    turn = np.empty((6, 2))  # d normal / d β: wall a's normal, then wall b's
    for c in range(2):
        moved = distance + step * columns[c]
        ma, mha, mb, mhb, _cov, _moved = joint_gauss_newton_arrays(
            capsule, moved, labels, wa, ha, wb, hb, 3, False, 6, 1e-9
        )
        r1 = joint_residuals_arrays(capsule, moved, order, labels, ma, mha, mb, mhb)
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
        out[k] = min(np.sqrt(shift @ shift + trace), np.pi)
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


def _corner_wall(
    data: F.PlaneData,
    wall: Wall,
    wall_se: tuple[float, float],
    opts: FitOptions,
    t0: float,
    note: str,
    amplitude: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None,
    flags: list[str],
    edge_is_walls: bool = False,
    max_disagreement: float = np.deg2rad(10.0),
    walk_se=lambda: 0.0,
    tie_suspect: bool = False,
    common_roll: float = 0.0,
) -> PlaneResult:
    """One wall of the joint model, refined on its own echoes.

    With the echoes' own amplitudes, the wall's direction in the rotation
    plane comes from where they are strongest (:func:`amplitude_pitch`) and
    its yaw and offset from the ranges (:func:`fixed_pitch_wall`): unbiased
    whatever the tilt, and as precise as the corrected points on axis-aligned
    walls.  It is kept only if it agrees with the joint model's direction
    (unbiased, if imprecise) within ``opts.tilt_test_sigma`` of their combined
    standard error: a later echo leaking into the amplitudes would pull the
    peak off the wall's normal.

    Without them (no waveforms, or the peak outside the sweep): the
    paper-corrected points (§4) give the most precise normal when the wall is
    axis-aligned; the joint model (mirror and edge echoes together) is
    unbiased whatever the tilt.  If the LS normal of the corrected points
    (eq. 15) agrees with the joint normal within ``opts.tilt_test_sigma`` of the
    joint standard error, keep it with the offset from the mirror-echo
    condition, and standard errors the joint model's at least (the corrected
    points cannot see a tilt below that, so their own covariance would
    overclaim); otherwise keep the joint wall with the joint model's standard
    errors (its edge echoes tie the direction; the wall's own echoes alone
    would overstate them).

    ``amplitude`` holds the wall's echoes as ``(gamma, peak amplitude,
    distance, capsules)``, or None.  Reasons to call the plane unreliable are
    appended to ``flags``: corrected points and joint fit more than
    ``max_disagreement`` (rad) apart both as they are and with the corrected
    points turned about x by ``common_roll`` (rad: the L's roll as the other
    wall's joint fit shows it, which the corrected points cannot see); a direction that rests on the joint fit
    while the model's edge echoes are mostly a wall's as well
    (``edge_is_walls``: the edge that ties the walls' directions together
    was not identified).  ``walk_se()`` (rad, :func:`walk_stderr`; asked only here) is added in quadrature
    to the joint normal's standard error where the direction rests on the ranges (the amplitudes place it
    free of any walk).
    ``tie_suspect``: the other wall's echoes may be the corner cluster's, so the edge that ties this wall's
    direction to it may be wrong; the joint wall then reports the standard errors of its own echoes at
    least (the joint covariance assumes the tie).
    """
    mask = np.ones(data.n, dtype=bool)
    se_joint, se_h_joint = wall_se
    pitch = amplitude_pitch(*amplitude[:3]) if amplitude is not None else None
    fitted = None
    if pitch is not None:
        phi, phi_se = pitch
        fitted, se_n, se_h = fixed_pitch_wall(amplitude[3], amplitude[2], phi, phi_se, wall.normal)
        off = float(np.arccos(min(max(float(fitted.normal @ wall.normal), -1.0), 1.0)))
        if not (math.isfinite(se_joint) and off <= opts.tilt_test_sigma * np.hypot(se_joint, se_n)):
            fitted = None
            if math.isfinite(se_joint):
                # The amplitudes are the only sensor of the wall's direction in the rotation plane that a
                # common roll cannot fool; a joint fit they contradict has not found that direction.
                flags.append(
                    f"its echoes are strongest at γ = {np.rad2deg(phi):.1f}°, {np.rad2deg(off):.1f}° from "
                    f"the joint fit's normal (over {opts.tilt_test_sigma:g}σ)"
                )
    if fitted is not None:
        diag = diagnostics(
            "corner model; amplitude pitch; gauss-newton",
            t0,
            notes=(
                note,
                f"echoes strongest at γ = {np.rad2deg(phi):.2f}° ± {np.rad2deg(phi_se):.2f}°: "
                "the wall's direction; yaw and offset from the ranges",
            ),
        )
        return F.make_plane_fit(
            data,
            fitted.normal / fitted.offset,
            method="corner",
            inlier_mask=mask,
            diagnostics=diag,
            model="constant-depth",
            stderr=(se_n, se_h),
        )
    if edge_is_walls:
        flags.append(
            "its direction rests on edge echoes that a wall explains as well: the corner edge that ties "
            "the walls together was not identified"
        )
    theta_p = F.ls_theta(data.points)
    n_p = theta_p / np.linalg.norm(theta_p)
    walk = walk_se()
    se_n, se_h = float(np.hypot(se_joint, walk)), se_h_joint
    angle = float(np.arccos(min(max(float(n_p @ wall.normal), -1.0), 1.0)))
    # The test is the joint fit's own: a walk that may have turned it does not make the roll-blind
    # corrected points more likely right; it only widens what either may miss by.
    agree = math.isfinite(se_joint) and angle <= opts.tilt_test_sigma * se_joint
    # The corrected points take the wall's direction in the rotation plane from the axis they assume (§4; a
    # roll ρ of the wall moves them by r·ρ only, r the capsules' few-cm lever): on an L rolled about x they
    # sit the roll from the truth whatever the data.  So they disagree with the joint fit only if they do both
    # as they are (no roll) and turned by the L's roll as the other wall shows it: a wall turned apart from
    # the other (one taken for the corner cluster) still disagrees.
    # n_p turned about x by the roll: lelsonar.geometry.rotation_x's turn written out as one dot product on floats
    # (its one-angle path still builds a matrix and an array for the product)
    c, s = math.cos(common_roll), math.sin(common_roll)
    (p_x, p_y, p_z), (n_x, n_y, n_z) = n_p.tolist(), wall.normal.tolist()
    turned_cos = p_x * n_x + (c * p_y - s * p_z) * n_y + (s * p_y + c * p_z) * n_z
    turned = math.acos(min(max(turned_cos, -1.0), 1.0))
    apart = min(angle, turned)
    if agree:
        h = float(np.mean(data.capsules @ n_p + data.distance))
        theta, model = n_p / h, "paper"
    else:
        theta, model = wall.normal / wall.offset, "constant-depth"
        if apart > max_disagreement:
            # Neither can be trusted: a wall tilted this far is outside what the corrected points describe,
            # and a joint fit this far off its axis has likely taken the edge's echoes for the wall's.
            flags.append(
                f"its direction is ambiguous: the corrected points and the joint fit differ by "
                f"{np.rad2deg(angle):.1f}°, and by {np.rad2deg(turned):.1f}° "
                f"allowing for the {np.rad2deg(common_roll):.1f}° roll the other wall shows"
            )
    verdict = "corrected-points normal, mirror-echo offset" if agree else "joint-model wall"
    diag = diagnostics(
        "corner model; lstsq",
        t0,
        notes=(
            note,
            f"joint normal {np.rad2deg(angle):.2f}° from the "
            f"corrected-points normal ({np.rad2deg(apart):.2f}° allowing for "
            f"the L's roll; joint σ {np.rad2deg(se_n):.2f}°, of "
            f"which {np.rad2deg(walk):.2f}° for a walk with the "
            "echoes' amplitude) -> " + verdict,
        ),
    )
    fit = F.make_plane_fit(data, theta, method="corner", inlier_mask=mask, diagnostics=diag, model=model)
    if isinstance(fit, PlaneFit) and math.isfinite(se_n) and math.isfinite(se_h):
        if agree or tie_suspect:
            # The corrected points cannot see a roll below the joint fit's σ: their own covariance overclaims.
            # A joint wall tied to a suspect wall: the joint σ assumes a tie that may be wrong.
            se_n, se_h = max(fit.normal_stderr, se_n), max(fit.offset_stderr, se_h)
        # Else the joint wall's σ is the joint fit's: the edge's echoes tie its direction to the other wall's,
        # which the covariance of its own echoes alone (the direction through the capsules' few-cm radial
        # lever, eq. 9) leaves out, overstating it up to tens of degrees.
        fit = fit.replace_scalars(normal_stderr=se_n, offset_stderr=se_h)
    return fit


def _single_wall(
    pts,
    gamma: np.ndarray,
    distance: np.ndarray,
    geometry: ArrayGeometry,
    label: str,
    axis: np.ndarray,
    opts: FitOptions,
    echo_amplitude: np.ndarray | None,
    t0: float,
) -> tuple[PlaneFit, F.PlaneData] | None:
    """One wall on its own, where the joint model found no pair of walls (a sweep that sees one wall only).

    The densest band of mirror-implied positions in the wall's window gives its echoes (assigned at the joint
    model's tolerances, loosest first); its direction in the rotation plane comes from where they are
    strongest (:func:`amplitude_pitch`), its yaw and offset from the ranges (:func:`fixed_pitch_wall`).  No
    edge ties it to anything, so without the amplitude peak inside the sweep there is no single-wall plane
    (None: the caller keeps its fallback).
    """
    if echo_amplitude is None:
        return None
    cos_t = np.cos(opts.corner_beam_half_angle)
    seen = pts.beam @ axis >= cos_t
    bands = band_offsets(pts.capsule[seen] @ axis + pts.distance[seen], max_bands=1, min_count=opts.min_points)
    if bands.size == 0 or bands[0] <= 0:
        return None
    amp = np.asarray(echo_amplitude, dtype=np.float64)[pts.step, pts.capsule_index]
    wall, se_n, se_h, m, phi = Wall(np.asarray(axis, dtype=np.float64), float(bands[0])), np.inf, np.inf, None, None
    tol = opts.corner_tolerance
    for t in (2.5 * tol, 1.5 * tol, tol):
        m = (pts.beam @ wall.normal >= cos_t) & (np.abs(mirror_residuals(wall, pts)) <= t)
        if np.count_nonzero(m) < opts.min_points:
            return None
        pitch = amplitude_pitch(pts.gamma[m], amp[m], pts.distance[m])
        if pitch is None:
            return None
        phi = pitch
        wall, se_n, se_h = fixed_pitch_wall(pts.capsule[m], pts.distance[m], pitch[0], pitch[1], wall.normal)
    sel = np.full(distance.shape, np.nan)
    sel[pts.step[m], pts.capsule_index[m]] = pts.distance[m]
    data = F.plane_data(geometry, gamma, sel, np.unique(pts.step[m]), label, axis)
    diag = diagnostics(
        "corner model, one wall; amplitude pitch; gauss-newton",
        t0,
        notes=(
            f"no pair of walls: wall {label} alone on {int(np.count_nonzero(m))} echoes of its band",
            f"echoes strongest at γ = {np.rad2deg(phi[0]):.2f}° ± "
            f"{np.rad2deg(phi[1]):.2f}°: the wall's direction; yaw and offset from "
            "the ranges",
        ),
    )
    fit = F.make_plane_fit(
        data,
        wall.normal / wall.offset,
        method="corner",
        inlier_mask=np.ones(data.n, dtype=bool),
        diagnostics=diag,
        model="constant-depth",
        stderr=(se_n, se_h),
    )
    if not isinstance(fit, PlaneFit):
        return None
    unexplained = float(np.mean(~m[seen])) if np.any(seen) else 0.0
    return assess_plane(fit, gamma, edge_echoes=0, findings=unexplained_finding(unexplained)), data


#: The quality limits the corner model's own findings use (frozen: one instance serves every scan).
_LIMITS = QualityLimits()

#: Range the echo's amplitude window (:data:`~lelsonar.signal.energy.ECHO_PEAK_WINDOW`) spans beyond
#: the echo's own, m: half its length times a speed of sound at the warm end of a lab's (35 °C, ~352 m/s).
ECHO_WINDOW_RANGE = ECHO_PEAK_WINDOW[1] * 352.0 / 2.0


def edge_in_echo_window(
    model: CornerModel, pts: ScanPoints, beam_half_angle: float, residuals: np.ndarray | None = None
) -> np.ndarray:
    """Mask of the echoes whose amplitude window also holds the corner's double bounce.

    The double bounce returns from ``ρ·sin(opening)`` (eq. of
    :func:`~lelsonar.reconstruct.estimate.corner.model.edge_range_terms`), never nearer
    than either wall, and as strongly as a wall at that range (design notes
    §8); a far wall's mirror echo where the boresight also faces the edge is
    followed by it within centimetres, inside the window whose peak
    :func:`~lelsonar.signal.energy.echo_amplitude` takes.  That peak is
    then the corner's, and it pulls :func:`amplitude_pitch` toward the edge's
    direction.  ``residuals``: the model walls' :func:`~lelsonar.reconstruct.estimate.corner.model.echo_residuals`,
    if the caller has them.
    """
    if residuals is None:
        residuals = echo_residuals(model.wall_a, model.wall_b, pts, beam_half_angle)
    gap = -residuals[2]  # ρ·sin(opening) − d; inf: no edge
    return np.isfinite(gap) & (gap <= ECHO_WINDOW_RANGE)


def _wall_echoes(
    labels: np.ndarray, k: int, leaks: np.ndarray, pts: ScanPoints, echo_amp: np.ndarray | None
) -> tuple[
    tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None
]:
    """The echoes labelled ``k``, as :func:`~lelsonar.reconstruct.estimate.fit.plane_data_of` takes them (capsules
    ``(n, 1, 3)``, boresights, ranges ``(n, 1)``, steps), and for :func:`_corner_wall` the ``(γ, amplitude,
    range, capsule)`` of those whose amplitude window holds no double bounce (None without amplitudes)."""
    found = _gather_wall(
        labels,
        k,
        leaks,
        pts.step,
        pts.gamma,
        pts.capsule,
        pts.distance,
        pts.beam,
        np.zeros(0) if echo_amp is None else echo_amp,
        echo_amp is not None,
    )
    return found[:4], (None if echo_amp is None else found[4:])


@kernel
def _gather_wall(
    labels: np.ndarray,
    k: int,
    leaks: np.ndarray,
    step: np.ndarray,
    gamma: np.ndarray,
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    amplitude: np.ndarray,
    with_amplitude: bool,
):
    """:func:`_wall_echoes` as one kernel (the same rows as boolean indexing, in order)."""
    n = 0
    n_own = 0
    for i in range(labels.shape[0]):
        if labels[i] == k:
            n += 1
            if with_amplitude and not leaks[i]:
                n_own += 1
    caps = np.empty((n, 1, 3))
    bm = np.empty((n, 3))
    dist = np.empty((n, 1))
    st = np.empty(n, dtype=np.intp)
    g_own = np.empty(n_own)
    a_own = np.empty(n_own)
    d_own = np.empty(n_own)
    c_own = np.empty((n_own, 3))
    j = 0
    o = 0
    for i in range(labels.shape[0]):
        if labels[i] != k:
            continue
        for u in range(3):
            caps[j, 0, u] = capsule[i, u]
            bm[j, u] = beam[i, u]
        dist[j, 0] = distance[i]
        st[j] = step[i]
        j += 1
        if with_amplitude and not leaks[i]:
            g_own[o], a_own[o], d_own[o] = gamma[i], amplitude[i], distance[i]
            for u in range(3):
                c_own[o, u] = capsule[i, u]
            o += 1
    return caps, bm, dist, st, g_own, a_own, d_own, c_own


def fit_corner(
    gamma: np.ndarray,
    distance: np.ndarray,
    ratio: np.ndarray,
    geometry: ArrayGeometry,
    opts: FitOptions,
    echo_amplitude: np.ndarray | None = None,
) -> ScanFit:
    """The method ``"corner"``: both walls and the edge from all the echoes.

    The joint model (:func:`fit_corner_model`) labels every echo (wall a,
    wall b, edge, outlier); each wall is then refined on its own echoes
    (:func:`_corner_wall`: its direction from the echoes' amplitudes where
    ``echo_amplitude`` is given and the peak was swept, else from the
    paper-corrected points checked against the joint fit) and given its trust
    verdict.  The critical step is where the boresight points at the final
    planes' edge, which does not scatter with the energy noise.  Where no pair
    of walls shows bands of echoes, it falls back to ``"adaptive"`` on the
    energy split (degraded), except for a wall that shows a band and whose
    amplitude peak was swept: that wall is fitted alone (:func:`_single_wall`).

    Parameters
    ----------
    gamma, distance, ratio, geometry, opts
        As for every scan-level method (:class:`lelsonar.reconstruct.estimate.pipeline.Method`).
    echo_amplitude : (n_steps, n_capsules) array, optional
        Peak amplitude of each capsule's first echo alone, V.
    """
    t0 = time.perf_counter()
    g = np.asarray(gamma, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    pts = scan_points(geometry, g, d)
    model = fit_corner_model(
        pts,
        AXIS_Y,
        AXIS_Z,
        beam_half_angle=opts.corner_beam_half_angle,
        tolerance=opts.corner_tolerance,
        min_points=opts.min_points,
        significance=opts.tilt_test_sigma,
    )
    if model is None:
        crit = critical_step(ratio, opts.critical_peak_fraction)
        split = split_subsets(g, crit)
        data = [
            F.plane_data(geometry, g, d, steps, label, axis)
            for steps, label, axis in ((split.steps_a, "a", AXIS_Y), (split.steps_b, "b", AXIS_Z))
        ]
        out = [run_estimator(fit_adaptive, "adaptive", dd, None, opts) for dd in data]
        # Nothing checked these planes against the other wall or the edge, and the energy split assumes both
        # walls and the corner were swept: a plane can be centimetres off with clean residuals.
        fallback = (
            (
                DEGRADED,
                "no pair of walls explains the scan's echoes (one wall, or none, shows a band): "
                "energy-split fallback, unchecked against the other wall and the edge",
            ),
        )
        out = [assess_plane(p, g, findings=fallback) if isinstance(p, PlaneFit) else p for p in out]
        for k, (label, axis) in enumerate((("a", AXIS_Y), ("b", AXIS_Z))):
            single = _single_wall(pts, g, d, geometry, label, axis, opts, echo_amplitude, t0)
            if single is not None:
                out[k], data[k] = single
        return ScanFit(out[0], out[1], data[0], data[1], crit)
    # Echoes per label, counted once: outliers (-1), wall a, wall b, edge.
    n_outlier, n_wall_a, n_wall_b, n_edge = np.bincount(model.labels - ECHO_OUTLIER, minlength=4).tolist()
    note = (
        f"corner model: {model.hypotheses} band pairs; echoes: {n_wall_a} wall a, {n_wall_b} wall b, "
        f"{n_edge} edge, {n_outlier} outliers (tolerance {1000 * model.tolerance:.0f} mm)"
    )
    amplitudes = None if echo_amplitude is None else np.asarray(echo_amplitude, dtype=np.float64)
    out: list[PlaneResult] = []
    datas: list[F.PlaneData] = []
    # Echoes a wall could have returned as well as the edge can move the offset by up to the tolerance; a
    # share of them beyond max_offset_stderr / tolerance could move it past what a good plane may miss by.
    limits = _LIMITS
    shared_limit = limits.max_offset_stderr / model.tolerance
    residuals = echo_residuals(model.wall_a, model.wall_b, pts, opts.corner_beam_half_angle)  # (3, N), once
    # Of the echoes no part explains, those a wall should have returned instead (not another surface's); only
    # asked where the share could degrade a plane (under it neither share is named).
    unexplained, against = n_outlier / pts.n, n_outlier / pts.n
    if unexplained > limits.degraded_unexplained:
        own = np.stack([model.labels == ECHO_WALL_A, model.labels == ECHO_WALL_B])
        cosines = np.stack([pts.beam @ model.wall_a.normal, pts.beam @ model.wall_b.normal])
        against = (
            np.count_nonzero(
                echoes_against_walls(residuals[:2], cosines, own, model.labels == ECHO_OUTLIER, opts.min_points)
            )
            / pts.n
        )
    shares = edge_shared_shares(model, pts, opts.corner_beam_half_angle, residuals)
    edge_is_walls = shares[ECHO_EDGE] > shared_limit
    alternatives = edge_alternatives(model, pts, opts.corner_beam_half_angle, opts.min_points)
    leaks = edge_in_echo_window(model, pts, opts.corner_beam_half_angle, residuals)
    # Each echo's own peak amplitude, once a scan (NaN: none)
    echo_amp = None if amplitudes is None else amplitudes[pts.step, pts.capsule_index]
    walk: list[tuple[float, float]] = []
    # Per wall: the share of its echoes the edge explains as well, and whether the corner's double bounces
    # (with the wall where they put it) explain the scan about as well: either way the wall may be the
    # corner cluster.  The same share of echoes as above could hold the offset; an alternative leaving no
    # more than the share of unexplained echoes that already degrades a plane explains the scan about as well.
    edge_shared = {k: shares[k] > shared_limit for k in (ECHO_WALL_A, ECHO_WALL_B)}
    joint_walls = {ECHO_WALL_A: (model.wall_a.normal, AXIS_Y), ECHO_WALL_B: (model.wall_b.normal, AXIS_Z)}
    as_cluster = {
        k: alternatives[k][0] > shared_limit and alternatives[k][1] <= limits.degraded_unexplained * pts.n
        for k in (ECHO_WALL_A, ECHO_WALL_B)
    }

    def walk_se(k: int) -> float:
        # Three more joint fits: only for a wall whose direction rests on the ranges, once a scan.
        if not walk:
            walk.append((0.0, 0.0) if echo_amp is None else walk_stderr(model, pts, echo_amp))
        return walk[0][k]

    for k, label, axis, wall in ((ECHO_WALL_A, "a", AXIS_Y, model.wall_a), (ECHO_WALL_B, "b", AXIS_Z, model.wall_b)):
        rows, amplitude = _wall_echoes(model.labels, k, leaks, pts, echo_amp)
        # The wall's echoes one by one, in the scan's order (step, then capsule) as plane_data keeps them.
        data = F.plane_data_of(*rows, label, axis)
        datas.append(data)
        fail = F.check_points(data.points, label, opts.min_points)
        if fail is not None:
            out.append(
                FitFailure(
                    fail.reason,
                    f"corner: {rows[0].shape[0]} echoes of wall {label}; " + fail.detail,
                    label,
                    fail.n_points,
                )
            )
            continue
        flags: list[str] = []
        if model.outside[k]:
            flags.append(
                "the joint fit turns it beyond the tilt window around its nominal axis: the model cannot place it"
            )
        other = ECHO_WALL_B if k == ECHO_WALL_A else ECHO_WALL_A
        fit = _corner_wall(
            data,
            wall,
            model.wall_stderr(k),
            opts,
            t0,
            note,
            amplitude,
            flags,
            edge_is_walls,
            walk_se=lambda k=k: walk_se(k),
            tie_suspect=edge_shared[other] or as_cluster[other],
            common_roll=roll_angle(*joint_walls[other]),
        )
        findings = tuple((UNRELIABLE, f) for f in flags)
        shared = shares[k]
        if edge_shared[k]:
            findings += (
                (
                    DEGRADED,
                    f"{100 * shared:.0f} % of its echoes fit the corner edge as well (within "
                    f"{1000 * model.tolerance:.0f} mm): the corner cluster may hold its offset",
                ),
            )
        as_edge, lost = alternatives[k]
        if as_cluster[k]:
            findings += (
                (
                    DEGRADED,
                    f"{100 * as_edge:.0f} % of its echoes are the corner's double bounces with the "
                    f"wall where they put it, a pair that explains all but {max(lost, 0)} of the "
                    "echoes the model explains: the corner cluster may have passed for the wall",
                ),
            )
        out.append(
            assess_beside_unexplained(
                fit, g, unexplained, against, edge_echoes=n_edge, findings=findings, at=len(flags)
            )
            if isinstance(fit, PlaneFit)
            else fit
        )
    # The critical step: where the boresight points at the edge of the final planes.  A common roll
    # of both walls about x barely changes any range, so the final normals (amplitude peaks, or the
    # corrected points) place the edge's direction better than the joint fit's.
    edge = corner_edge(out[0], out[1])
    crit = None
    if isinstance(edge, EdgeLine):
        point = edge.point
        if abs(edge.direction[0]) > 1e-9:
            point = point - edge.direction * (point[0] / edge.direction[0])
        crit = int(np.argmin(np.abs(g - np.arctan2(point[2], point[1]))))
    return ScanFit(out[0], out[1], datas[0], datas[1], crit, edge)
