"""What a target's echo amplitudes across γ say: the beam pattern's peak, its flanks, where one echo ends.

One target's echo follows the beam pattern ``D(γ − β)²`` across the sweep: in ``log A`` a parabola opening
down about the target's bearing β (Kleeman & Kuc; Leonard & Durrant-Whyte centre a region of constant depth
on it).  Its peak gives a bearing where the region's ends do not (a cut end); a step no beam pattern makes is
one echo taking over from another; an echo that stops strong at a region's end was cut, not faded.

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.errors import InternalError
from lelsonar.reconstruct.estimate.robust import fast_median, median
from lelsonar.reconstruct.estimate.surfaces.amplitude_top import (
    NO_TOP,
    PLATEAU,
    PLATEAU_TOP,
    UNSORTED,
    lstsq_full_rank,
    pinv,
    quadratic_design,
    rising_top,
    sorted_top,
    top_in_order,
)
from lelsonar.signal.directivity import PISTON_FIRST_NULL, piston_directivity

__all__ = [
    "PLATEAU",
    "bearing_from_amplitude",
    "log_amplitude_curvature",
    "extrapolated_peak",
    "vertex_at_curvature",
    "peak_at_bearing",
    "weaker_at",
    "amplitude_jump",
    "unfaded_ends",
    "end_crossing_stderr",
    "piston_power",
    "capsule_peak_spread",
    "log_echoes_in_order",
    "log_amplitude_noise",
]


def bearing_from_amplitude(gamma: np.ndarray, amplitude: np.ndarray) -> tuple[float, float] | None:
    """The beam pattern's peak across γ: the vertex of a parabola in ``log A`` over the top of the region.

    ``D(ψ)²`` is symmetric about the target's direction and, in ``log``, close to
    a parabola over its upper half, so the vertex of that fit is the bearing
    even when the region is cut on one side, as long as its peak is in it.

    Parameters
    ----------
    gamma : (k,) array
        Steps' γ, rad.
    amplitude : (k,) array
        Each step's echo peak amplitude, V (NaN: none).

    Returns
    -------
    (bearing, σ) in rad, or None when the amplitudes have no interior peak.
    """
    return _peak_bearing(gamma, amplitude, True)


def _peak_bearing(gamma: np.ndarray, amplitude: np.ndarray, with_stderr: bool) -> tuple[float, float] | None:
    """:func:`bearing_from_amplitude`; without ``with_stderr`` the vertex of a parabola's top comes with a NaN σ
    (the covariance is the fit's dearest part, and a caller that reads the bearing alone skips it)."""
    g = np.ascontiguousarray(gamma, dtype=np.float64)
    a = np.ascontiguousarray(amplitude, dtype=np.float64)
    # The readings in γ order, and the top's or the plateau's (one compiled pass where γ rises step by step, as a
    # sweep's does; NumPy's argsort otherwise, whose order of equal γ the pass does not guess).
    found = rising_top(g, a, PLATEAU) if g.ndim == 1 and g.shape == a.shape else None
    if found is None or found[0] == UNSORTED:
        found = sorted_top(g, a)
    kind, g, first, last, gt, at = found
    if kind == NO_TOP:
        return None
    # A receiver that clips flattens the top: the plateau's centre is the peak when both of its ends are
    # inside the region (an unclipped echo on either side), and nothing can be said when one is not.
    if kind == PLATEAU_TOP:
        if first == 0 or last == g.size - 1:
            return None
        step = fast_median(np.diff(g))
        width = float(g[last]) - float(g[first])
        return 0.5 * (float(g[first]) + float(g[last])), math.hypot(step, width / gt.size) / math.sqrt(12.0)
    la = np.log(at)
    g0 = float(np.add.reduce(gt)) / gt.size  # np.mean's sum and division
    u = gt - g0
    m = quadratic_design(u)
    coef = lstsq_full_rank(m, la)
    if coef is None:
        return None
    c0, b, c = coef.tolist()
    if not c < 0:
        return None
    vertex = -b / (2 * c)
    # The vertex must be held by the samples on both of its sides, not extrapolated past the region's end.
    if np.count_nonzero(u < vertex) < 2 or np.count_nonzero(u > vertex) < 2:
        return None
    if not with_stderr:
        return g0 + vertex, float("nan")
    res = la - m @ coef
    dof = max(u.size - 3, 1)
    cov = float(res @ res) / dof * pinv(m.T @ m)
    # Delta method on −b/(2c).
    jac = np.array([0.0, -1 / (2 * c), b / (2 * c * c)])
    var = float(jac @ cov @ jac)
    return g0 + vertex, math.sqrt(max(var, 0.0))


def log_amplitude_curvature(gamma: np.ndarray, amplitude: np.ndarray, *, plateau: bool = False) -> float | None:
    """The beam pattern's curvature in ``log A`` across γ, from a region whose peak is inside it.

    Every echo of a rotating transceiver, a mirror's, a corner's or an edge's,
    follows ``D(γ − β)²`` across γ; in ``log`` its top is close to a parabola
    ``log A ≈ P − k (γ − β)²``.  A sweep's uncut regions give ``k`` for that
    sweep's own capsules (no beam model assumed).

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).
    plateau : bool
        Fit a top whose largest values are equal too (a flat top under the receiver's full scale is the
        amplitude's quantisation, or a wide echo), rather than say nothing.

    Returns
    -------
    ``k`` (1/rad², > 0), or None when the top of the amplitudes is no parabola opening down.
    """
    g = np.ascontiguousarray(gamma, dtype=np.float64)
    a = np.ascontiguousarray(amplitude, dtype=np.float64)
    if g.ndim != 1 or g.shape != a.shape:
        raise InternalError(f"one γ per amplitude: {g.shape} γ, {a.shape} amplitudes")
    # Too few samples on the top, or (unless a plateau may be fitted) a clipped plateau: no curvature.
    gt, at = top_in_order(g, a, PLATEAU, plateau)
    if gt.size == 0:
        return None
    u = gt - float(np.add.reduce(gt)) / gt.size  # np.mean's sum and division
    coef = lstsq_full_rank(quadratic_design(u), np.log(at))
    if coef is None:
        return None
    return float(-coef[2]) if coef[2] < 0 else None


def extrapolated_peak(
    gamma: np.ndarray, amplitude: np.ndarray, curvature: float, *, before: float, after: float, sigmas: float = 3.0
) -> float | None:
    """The peak amplitude of a region whose peak lies past a cut end, from the flank it shows.

    With the sweep's beam curvature ``k`` fixed, ``log A + k u² = P − k v² + 2 k v u``
    is a line in ``u``: its slope puts the vertex ``v``, and ``P`` follows.
    On the flank the piston pattern falls faster than its parabola, so the
    slope overstates how far the peak is and ``P`` overstates the peak: an
    upper estimate, safe to call an echo weak by, never strong.  A few steps'
    amplitude noise moves the slope, and ``P`` grows as ``k v²`` with the
    vertex's distance: the estimate is the largest ``P`` over the vertices
    within ``sigmas`` σ of the line's fit (its residuals' σ through the slope
    and the level), inside the reach; with too few steps for a residual, none.

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).
    curvature : float
        ``k`` of :func:`log_amplitude_curvature`, 1/rad².
    before, after : float
        rad: how far before the first and after the last step the vertex may lie (0 on a side the
        region's echo faded on: its peak is not there).

    Returns
    -------
    The peak amplitude, or None when the vertex falls outside that reach or too few steps have echoes.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if np.count_nonzero(ok) < 3 or not curvature > 0:
        return None
    g, a = g[ok], a[ok]
    g0 = float(np.mean(g))
    u = g - g0
    y = np.log(a) + curvature * u * u
    slope, icpt = np.polyfit(u, y, 1)
    v = float(slope) / (2 * curvature)
    lo, hi = float(u.min()) - before, float(u.max()) + after
    if not lo <= v <= hi:
        return None
    # The line's own σ (u is centred: slope and level are independent), from its residuals.
    res = y - (float(slope) * u + float(icpt))
    s2 = float(res @ res) / (u.size - 2)
    suu = float(u @ u)
    if not suu > 0:
        return None
    dv = sigmas * math.sqrt(s2 / suu) / (2 * curvature)
    far = max(abs(max(lo, v - dv)), abs(min(hi, v + dv)))
    peak = math.exp(float(icpt) + sigmas * math.sqrt(s2 / u.size) + curvature * far * far)
    return max(peak, float(a.max()))


def vertex_at_curvature(g: np.ndarray, a: np.ndarray, k: float) -> tuple[float, float] | None:
    """The vertex of ``log A = P − k (γ − v)²`` with the sweep's beam curvature ``k`` fixed (the line in ``u`` of
    :func:`extrapolated_peak`), and 3 σ of it through its residuals (rad); None: too few amplitudes."""
    ok = np.isfinite(a) & (a > 0)
    if np.count_nonzero(ok) < 3 or not (math.isfinite(k) and k > 0):
        return None
    g, la = g[ok], np.log(a[ok])
    g0 = float(np.mean(g))
    u = g - g0
    y = la + k * u * u
    suu = float(u @ u)
    if not suu > 0:
        return None
    slope = float(u @ (y - y.mean())) / suu
    res = y - y.mean() - slope * u
    s2 = float(res @ res) / max(u.size - 2, 1)
    return g0 + slope / (2.0 * k), 3.0 * math.sqrt(s2 / suu) / (2.0 * k)


def peak_at_bearing(
    gamma: np.ndarray, amplitude: np.ndarray, bearing: float, curvature: float
) -> tuple[float, float] | None:
    """The peak amplitude of an echo whose bearing is known from elsewhere, from the flank a region shows.

    Every echo of a rotating transceiver follows the beam ``D(γ − β)²``, in
    ``log`` close to ``P − k (γ − β)²`` (:func:`log_amplitude_curvature`).  With
    ``β`` placed by the geometry (a plane's trace), each step gives the peak,
    ``A(γ) · exp(k (γ − β)²)``, and their median is the estimate.  The piston
    falls at least as fast as its parabola off the top (within a few % of it
    over a wide main lobe, much faster on a narrow one's far flank), so the
    estimate does not overstate the peak by more than that: safe to call an
    echo strong by.  It is close to the peak (safe to call an echo weak by)
    only where some step lies within the top the curvature was fitted over
    (``k (γ − β)² ≤ log 2``).

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).
    bearing : float
        The echo's bearing, rad.
    curvature : float
        ``k`` of :func:`log_amplitude_curvature`, 1/rad².

    Returns
    -------
    (peak amplitude, ``k`` times the nearest step's squared offset from ``bearing``), or None when no step
    has an amplitude or the curvature is not positive.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if not ok.any() or not curvature > 0:
        return None
    off = np.angle(np.exp(1j * (g[ok] - bearing)))  # wrapped to (−π, π]
    peaks = a[ok] * np.exp(curvature * off * off)
    return fast_median(peaks), float(curvature * np.min(off * off))


def weaker_at(gamma: np.ndarray, amplitude: np.ndarray, bearing: float, *, sigmas: float = 3.0) -> bool:
    """Whether a region's echo is weaker at ``bearing``, inside its span, than elsewhere in it beyond what one
    beam pattern and the amplitude noise allow: a target there would be the strongest echo of its own region.

    One target's echo follows ``D(γ − β)²``, largest at ``γ = β``: every step's amplitude is at most the
    peak, and the steps on either side of ``β`` are within the beam's change over one step of it (at most
    ``8 R Δγ / L`` in ``log``, as :func:`amplitude_jump` bounds it, ``R`` the region's range of log amplitude
    over its span ``L``).  The region's largest amplitude above the larger of the two steps around
    ``β`` by more than that and ``sigmas`` σ of a two-step difference of the amplitude noise contradicts a
    target at ``β``.

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).
    bearing : float
        rad.
    sigmas : float

    Returns
    -------
    True where the amplitudes contradict a target at ``bearing``; False where they do not, where ``bearing``
    lies outside the steps' span, or where too few steps have an amplitude to say.
    """
    g, la = log_echoes_in_order(gamma, amplitude)
    if g.size < 5:
        return False
    if not g[0] < bearing < g[-1]:
        return False
    span = float(g[-1] - g[0])
    slope, sigma = _beam_slope_and_noise(la, span)
    i = int(np.searchsorted(g, bearing))
    there = max(float(la[i - 1]), float(la[i]))
    step = float(g[i] - g[i - 1])
    return float(la.max()) - there > slope * step + sigmas * math.sqrt(2.0) * sigma


def amplitude_jump(gamma: np.ndarray, amplitude: np.ndarray, *, sigmas: float = 3.0) -> tuple[float, int] | None:
    """Where one echo takes over from another inside a region: an amplitude step no beam pattern makes.

    One target's echo follows ``D(γ − β)²`` across γ, in ``log`` a parabola
    ``log A = P − k (γ − β)²`` opening down.  Over a region of span ``L`` whose
    amplitudes range over ``R = log(A_max / A_min)``, such a parabola changes by
    at most ``4 R |Δγ| / L`` between two steps ``Δγ`` apart (its slope is
    largest at the end farthest from its vertex, ``2 R / max(u, L − u) ≤ 4 R / L``).
    A piston's flank falls faster than its parabola, at most twice as steep
    down to 35 dB under its peak, so the bound is doubled: ``8 R |Δγ| / L``.

    A jump beyond it (and beyond ``sigmas`` σ of the steps' amplitude noise, σ
    from the second differences' median absolute deviation) that persists,
    the two-step changes across it (from the step before it, and to the step
    after next) beyond their bound the same way, is one echo taking over from another at the same range: a weak
    edge's diffraction beside a strong mirror whose foot leaves its face, say.
    One step out of line is not (a ringing echo bends one step's amplitude).

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).
    sigmas : float
        How many σ of the amplitude noise a jump must exceed the bound by.

    Returns
    -------
    (γ midway between the two steps of the largest such jump, how many of the region's steps with an
    amplitude lie on its shorter side), or None.
    """
    g, la = log_echoes_in_order(gamma, amplitude)
    if g.size < 6:
        return None
    span = float(g[-1] - g[0])
    if not span > 0:
        return None
    slope, sigma = _beam_slope_and_noise(la, span)
    noise = sigmas * math.sqrt(2.0) * sigma

    def beyond(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """How far the change from step i to step j exceeds one beam pattern's, signed as the change (0: not)."""
        change = la[j] - la[i]
        excess = np.abs(change) - (slope * (g[j] - g[i]) + noise)
        return np.where(excess > 0, np.sign(change) * excess, 0.0)

    # Jump k lies between steps k and k + 1; it persists if k − 1 to k + 1 and k to k + 2 jump the same way.
    k = np.arange(1, g.size - 2)
    one = beyond(k, k + 1)
    before, after = beyond(k - 1, k + 1), beyond(k, k + 2)
    persists = ((one > 0) & (before > 0) & (after > 0)) | ((one < 0) & (before < 0) & (after < 0))
    one = np.abs(one)
    if not persists.any():
        return None
    j = int(k[persists][int(np.argmax(one[persists]))])
    return 0.5 * float(g[j] + g[j + 1]), min(j + 1, g.size - j - 1)


def log_echoes_in_order(gamma: np.ndarray, amplitude: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The steps with an echo, in γ order: their γ and ``log A``."""
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    g, la = g[ok], np.log(a[ok])
    order = np.argsort(g)
    return g[order], la[order]


def _beam_slope_and_noise(la: np.ndarray, span: float) -> tuple[float, float]:
    """The steepest change of log amplitude one beam pattern can make over a region (per rad) and the log
    amplitudes' noise σ (:func:`log_amplitude_noise`), for :func:`amplitude_jump` and :func:`unfaded_ends`.

    ``la``: the region's log amplitudes in γ order; ``span``: its γ extent, rad.  The slope bound is
    ``8 Δ/span`` (``Δ`` the region's range of log amplitude).
    """
    return 8.0 * float(la.max() - la.min()) / span, log_amplitude_noise(la)


def log_amplitude_noise(la: np.ndarray) -> float:
    """The noise σ of a region's log amplitudes in γ order: robust (1.4826 MAD) from their second differences,
    whose variance is 6 σ² for white noise, so a beam pattern's parabola (a constant second difference) does not
    count."""
    second = np.diff(la, 2)
    return 1.4826 * median(np.abs(second - median(second))) / math.sqrt(6.0)


def unfaded_ends(gamma: np.ndarray, amplitude: np.ndarray, *, sigmas: float = 3.0) -> tuple[bool, bool] | None:
    """Which ends of a region the echo stops at while still strong: not where the beam pattern fades it.

    A region at one range ends on each side where ``D(γ − β)²`` falls under
    the receiver's threshold, the same threshold on both sides (one range), so
    its two end amplitudes are equal up to where each crossing falls within
    its step: at most the beam's change over one step at the end.  With the
    region's amplitudes spanning ``R = log(A_max / A_min)`` over a span ``L``,
    that change is at most ``8 R Δγ / L`` (the parabola's end slope ``4 R / L``,
    doubled for a piston's flank, as in :func:`amplitude_jump`).  An end whose
    amplitude exceeds the other's by more than that (and by ``sigmas`` σ of
    the amplitude noise) is not a fade: the echo stops there because its
    mirror does (the foot leaves the wall where the wall ends), and the
    region's centre is not the wall's bearing.

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none), in sweep order.
    sigmas : float
        How many σ of the amplitude noise the difference must exceed the bound by.

    Returns
    -------
    (the first end is not a fade, the last end is not a fade), or None when too few steps have an amplitude.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if np.count_nonzero(ok) < 5:
        return None
    g, la = g[ok], np.log(a[ok])
    span = abs(float(g[-1] - g[0]))
    if not span > 0:
        return None
    step = fast_median(np.abs(np.diff(g)))
    slope, sigma = _beam_slope_and_noise(la, span)
    # A difference of two steps' log amplitudes has variance 2 σ².
    bound = slope * step + sigmas * math.sqrt(2.0) * sigma
    diff = float(la[0] - la[-1])
    return diff > bound, -diff > bound


def end_crossing_stderr(gamma: np.ndarray, amplitude: np.ndarray) -> tuple[float, float]:
    """How far the amplitude noise moves where a region's echo crosses the receiver's threshold, at each end.

    A region ends where ``D(γ − β)²`` falls under the threshold.  A noise of σ in ``log A`` moves that
    crossing by ``σ / |∂ log A/∂γ|`` at the end (the beam's log slope there, from a line through the end's
    own steps): an upper bound, as the first of several noisy steps near the threshold to pass it wanders
    less than one crossing would.  The σ is robust (1.4826 MAD of the second differences, whose variance
    is 6 σ² for white noise, as :func:`amplitude_jump` has it); noise-free amplitudes move nothing.  An end
    whose slope is not resolved (flat, clipped) is anywhere in the region: the span's ``1/√12``.

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none), in sweep order.

    Returns
    -------
    (σ at the first end, σ at the last end), rad; (0, 0) when too few steps have an amplitude.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if np.count_nonzero(ok) < 6:
        return 0.0, 0.0
    g, la = g[ok], np.log(a[ok])
    span = abs(float(g[-1] - g[0]))
    _, sigma = _beam_slope_and_noise(la, span) if span > 0 else (0.0, 0.0)
    if not sigma > 0:
        return 0.0, 0.0
    m = max(3, g.size // 6)
    out = []
    for sel in (slice(0, m), slice(g.size - m, g.size)):
        slope = float(np.polyfit(g[sel], la[sel], 1)[0])
        out.append(min(sigma / abs(slope), span / math.sqrt(12.0)) if slope != 0 else span / math.sqrt(12.0))
    return out[0], out[1]


def piston_power(psi: float, curvature: float) -> float:
    """A piston transceiver's two-way beam pattern ``D(ψ)²``, ``D = 2·J1(ka·sinψ)/(ka·sinψ)``.

    ``ka`` comes from the sweep's own beam curvature ``k`` (:func:`log_amplitude_curvature`): near the
    axis ``log D² ≈ −(ka)²ψ²/4``, so ``ka = 2√k``.  Off the top the piston falls faster than that
    parabola, so taking an echo back to the axis with it does not understate the echo's peak.

    Parameters
    ----------
    psi : float
        Angle off the beam's axis, rad.
    curvature : float
        ``k``, 1/rad².

    Returns
    -------
    ``D(ψ)²`` in (0, 1]; 0 at or past the first null (nothing there says how strong the echo is), NaN when
    ``k`` is not positive.
    """
    if not curvature > 0:
        return float("nan")
    ka = 2.0 * math.sqrt(curvature)
    if ka * abs(math.sin(psi)) >= PISTON_FIRST_NULL:
        return 0.0
    return float(piston_directivity(np.array(psi), ka) ** 2)


def capsule_peak_spread(gamma: np.ndarray, amplitude: np.ndarray) -> float:
    """How far the capsules' own beam-pattern peaks disagree: the bearing's share of echoes summed into one.

    One target's echo reaches every capsule with the same beam pattern ``D(γ − β)²`` (the capsules' beams are
    parallel; their ranges differ by centimetres, their spreading by a few %), so each capsule's own peak
    (:func:`bearing_from_amplitude` on its amplitudes alone) is the same β up to its noise.  A second echo
    summing into the amplitude window (a double bounce at a like range) adds with a phase that differs from
    capsule to capsule, since their paths differ by wavelengths: each capsule's peak moves its own way.  The
    spread of their peaks (sample standard deviation) is then the size of that shift, which their median
    does not average away and which the parabola's residuals of the step medians do not show.

    Parameters
    ----------
    gamma : (k,) array
        Steps' γ, rad.
    amplitude : (k, n_capsules) array
        Each step's echo amplitude per capsule, V (NaN: none).

    Returns
    -------
    The spread, rad (0 with fewer than two capsules that show a peak).
    """
    a = np.asarray(amplitude, dtype=np.float64)
    peaks = [p[0] for c in range(a.shape[1]) for p in [_peak_bearing(gamma, a[:, c], False)] if p is not None]
    return float(np.std(peaks, ddof=1)) if len(peaks) >= 2 else 0.0
