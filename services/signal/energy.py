"""The energy indicator that finds the corner (paper §4, eq. 10–14).

Pure functions: arrays in, typed results out, no I/O.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtri  # the standard normal's quantile

from lelsonar.energy_model import EnergyModel
from lelsonar.errors import ConfigError
from lelsonar.signal.compiled import kernel
from lelsonar.signal.summation import pairwise_sum

__all__ = [
    "EnergyModel",
    "ECHO_PEAK_WINDOW",
    "PRE_ECHO_WINDOW",
    "waveform_energy",
    "waveform_energy_agrees",
    "echo_amplitude",
    "echo_window_starts",
    "echo_window_width",
    "window_peak",
    "total_energy",
    "fit_energy_model",
    "median_range",
    "energy_ratio",
    "NOISE_FALSE_ALARM",
    "echoes_over_noise",
    "noise_level",
    "ranges_backed",
]


def waveform_energy(waveforms: np.ndarray, sample_rate: float) -> np.ndarray:
    """Signal energy of each waveform, the paper's eq. (10).

    ``E_i^γ = ∫ w²(t) dt``, integrated by the rectangle rule.

    Parameters
    ----------
    waveforms : (..., n_samples) array
        Echo signal, V.
    sample_rate : float
        Hz.

    Returns
    -------
    (...) array
        Energy, V²·s.
    """
    w = np.asarray(waveforms, dtype=np.float64)
    # np.vecdot: one dot product per waveform, the same arithmetic whatever the leading shape (a step's
    # (k, n) or a scan's (steps, k, n)); cheaper on a step than an einsum.
    return np.vecdot(w, w) / float(sample_rate)


_largest = np.maximum.reduce  # ndarray.max without its Python-level wrapper

#: Where :func:`echo_amplitude` looks, s after the time of flight: the comparator fires on the
#: echo's rising edge, and a 40 kHz transceiver's echo peaks within ~0.2 ms of its onset.  Short, so
#: a later echo (the corner's, a few cm further) does not leak in.
ECHO_PEAK_WINDOW = (0.0, 4.0e-4)
#: The same length just before the time of flight: where a first echo has not begun yet.  Its peak against
#: the echo's (:func:`echo_amplitude` with each window) says whether the waveform holds an echo where the
#: range puts it.
PRE_ECHO_WINDOW = (-4.0e-4, 0.0)


def echo_window_width(sample_rate: float, window: tuple[float, float] = ECHO_PEAK_WINDOW) -> int:
    """Samples in :func:`echo_amplitude`'s window (at least one)."""
    return window_samples(sample_rate, window[0], window[1])


@kernel
def window_samples(sample_rate: float, lo: float, hi: float) -> int:
    """:func:`echo_window_width` of the window (``lo``, ``hi``) s (compiled: the ingest's kernel uses it)."""
    return max(int(np.rint((hi - lo) * sample_rate)), 1)


def echo_window_starts(
    n_samples: int, sample_rate: float, t0: float, round_trips, window: tuple[float, float] = ECHO_PEAK_WINDOW
) -> list[int]:
    """First sample of :func:`echo_amplitude`'s window for each round trip, in a waveform of ``n_samples``;
    -1 where there is none (:func:`echo_window_start` of each)."""
    return [echo_window_start(n_samples, sample_rate, t0, float(t), window[0]) for t in round_trips]


@kernel
def echo_window_start(n_samples: int, sample_rate: float, t0: float, round_trip: float, lo: float) -> int:
    """First sample of the window that starts ``lo`` s after ``round_trip``; -1 where there is none.

    The sample nearest ``round_trip + lo`` (half to even), clipped at 0; none without an echo
    (``round_trip`` NaN, infinite or not positive) or when the window starts at or after the end.
    """
    if round_trip > 0.0 and math.isfinite(round_trip):
        x = (round_trip + lo - t0) * sample_rate
        if x < n_samples:
            a = int(np.rint(x)) if x > 0.0 else 0
            if a < n_samples:
                return a
    return -1


def window_peak(windows: np.ndarray) -> np.ndarray:
    """The largest ``|w|`` of each window (last axis): exact, in the samples' own type."""
    return _largest(np.abs(windows), axis=-1)


def echo_amplitude(
    waveforms: np.ndarray,
    sample_rate: float,
    t0: float,
    round_trip: np.ndarray,
    window: tuple[float, float] = ECHO_PEAK_WINDOW,
) -> np.ndarray:
    """Peak amplitude of the first echo alone: the largest ``|w|`` just after its time of flight.

    The paper's ``E_i^γ`` (eq. 10) integrates the whole waveform, so a step
    whose first echo is a wall still rings with the corner's echo later on.
    The peak right after the time of flight belongs to the echo that set the
    range; it follows the beam pattern ``D(ψ)²`` of the angle between the beam
    and the wall's normal.

    Parameters
    ----------
    waveforms : (..., n_samples) array
        V.
    sample_rate : float
        Hz.
    t0 : float
        Time of the first sample after firing, s.
    round_trip : (...) array
        Time of flight of the first echo, s (NaN: no echo).
    window : (float, float)
        Start and end of the search after the time of flight, s (:func:`echo_window_starts`,
        :func:`echo_window_width`; a window running off the end stops there).

    Returns
    -------
    (...) array
        V; NaN where there is no echo or the window leaves the waveform.
    """
    w = np.asarray(waveforms)
    if w.dtype.kind != "f":
        w = w.astype(np.float64)
    n = w.shape[-1]
    out = np.full(w.shape[:-1], np.nan)
    if n == 0 or not out.size:  # no waveform recorded: no amplitude
        return out
    tof = np.asarray(round_trip, dtype=np.float64)
    if tof.shape != out.shape:
        tof = np.broadcast_to(tof, out.shape)
    starts = echo_window_starts(n, sample_rate, t0, tof.ravel().tolist(), window)
    rows = [i for i, a in enumerate(starts) if a >= 0]
    if rows:
        # Every window at once, one gather (|w| and max are exact in float32: float32 samples are never
        # converted); a window running off the end repeats the last sample, which leaves the max unchanged.
        first = np.array([starts[i] for i in rows])
        cols = np.minimum(first[:, None] + np.arange(echo_window_width(sample_rate, window)), n - 1)
        out.reshape(-1)[rows] = window_peak(w.reshape(-1, n)[np.array(rows)[:, None], cols])
    return out


#: Probability that the noise alone reaches :func:`echoes_over_noise`'s level anywhere in the record a board
#: listened to before it fired: one reading in a thousand of a noise-only record is taken for an echo.
NOISE_FALSE_ALARM = 1.0e-3


def echoes_over_noise(
    windows: np.ndarray,
    sample_rate: float,
    tof_at: np.ndarray,
    listened: np.ndarray,
    floor_time: float,
    false_alarm: float = NOISE_FALSE_ALARM,
) -> tuple[np.ndarray, float, float]:
    """Which readings' waveforms hold an echo at their time of flight, rather than the noise a board's
    comparator fired on.

    A comparator fires at the first sample whose ``|w − DC|`` crosses its threshold.  Set within a few σ of the
    receiver's noise, it fires on the noise before the echo comes: the reading's time of flight then marks no
    echo (its waveform just after holds noise) and its range is no surface's.  Gaussian noise of σ reaches
    ``z·σ`` somewhere in ``N`` samples with probability ``≈ 2N·Q(z)``; a reading is an echo if the largest
    ``|w − DC|`` of :data:`ECHO_PEAK_WINDOW` after its time of flight stands over ``z·σ`` with
    ``2N·Q(z) = false_alarm``, ``N`` the samples the board listened to before it fired.  (Coloured noise has
    fewer independent samples than ``N``: the level is then on the safe side, a weak echo taken for noise
    rather than noise for an echo.)  The DC level and σ are the scan's: the median and the MAD of the
    windows' first ``floor_time`` (before the echoes the windows hold), pooled over the readings.

    Parameters
    ----------
    windows : (N, W) array
        V, each reading's waveform around its time of flight.
    sample_rate : float
        Hz.
    tof_at : (N,) array
        Each reading's time of flight after its window's first sample, s.
    listened : (N,) array
        The time each reading's board listened before it fired (its time of flight), s.
    floor_time : float
        s at the start of each window that hold noise only.
    false_alarm : float
        In (0, 1).

    Returns
    -------
    echo : (N,) bool array
    dc, sigma : float
        The scan's DC level and noise σ, V.
    """
    windows = np.asarray(windows)
    n, width = windows.shape
    head = max(int(round(floor_time * sample_rate)), 1)
    if not 0.0 < false_alarm < 1.0:
        raise ConfigError(f"the false-alarm probability must be in (0, 1), got {false_alarm}")
    if n == 0 or width <= head:
        return np.ones(n, bool), math.nan, math.nan
    floor = np.asarray(windows[:, :head], dtype=np.float64)
    dc = float(np.median(floor))
    sigma = 1.4826 * float(np.median(np.abs(floor - dc)))
    level = noise_level(sigma, listened, sample_rate, false_alarm)
    start = np.round(np.asarray(tof_at, dtype=np.float64) * sample_rate + ECHO_PEAK_WINDOW[0] * sample_rate)
    peak = _peak_after(windows, start, echo_window_width(sample_rate), dc)
    return peak > level, dc, sigma


def noise_level(sigma: float, listened, sample_rate: float, false_alarm: float = NOISE_FALSE_ALARM) -> np.ndarray:
    """The level Gaussian noise of σ reaches anywhere in the record a board listened to with probability
    ``false_alarm``: ``z·σ`` with ``2N·Q(z) = false_alarm``, ``N`` the samples of ``listened`` s
    (:func:`echoes_over_noise`'s line between an echo and the noise).

    Parameters
    ----------
    sigma : float
        V.
    listened : array
        s.
    sample_rate : float
        Hz.
    false_alarm : float
        In (0, 1).

    Returns
    -------
    array of ``listened``'s shape
        V.
    """
    if not 0.0 < false_alarm < 1.0:
        raise ConfigError(f"the false-alarm probability must be in (0, 1), got {false_alarm}")
    samples = np.maximum(np.asarray(listened, dtype=np.float64) * sample_rate, 1.0)
    return -ndtri(false_alarm / (2.0 * samples)) * sigma


@kernel
def _peak_after(windows: np.ndarray, start: np.ndarray, width: int, dc: float) -> np.ndarray:
    """Each row's largest ``|w − dc|`` over its samples ``start`` to ``start + width`` (0 where none is in the
    row, or ``start`` is NaN): :func:`echoes_over_noise`'s peak, without a pass over the whole windows."""
    n, samples = windows.shape
    peak = np.zeros(n)
    for i in range(n):
        if not np.isfinite(start[i]):
            continue
        for j in range(max(int(start[i]), 0), min(int(start[i]) + width, samples)):
            v = abs(windows[i, j] - dc)
            if v > peak[i]:
                peak[i] = v
    return peak


def ranges_backed(distance: np.ndarray, echo: np.ndarray, reach: float) -> np.ndarray:
    """Which readings have a neighbour with an echo (``echo``) within ``reach`` of their range.

    A reading whose waveform shows no echo over the noise (:func:`echoes_over_noise`) is the noise a board
    fired on, or an echo too weak to stand out: a wall's echo off its beam, seen stronger by the capsule
    beside it or at the step before.  The first lands anywhere in the time the board listened; the second
    where its neighbours' echo is.  Neighbours are the same capsule's readings at the adjacent rows (steps)
    and the adjacent capsules' at the same row.

    Parameters
    ----------
    distance : (steps, k) array
        m, NaN: no reading.
    echo : (steps, k) bool array
        The readings that show an echo.
    reach : float
        m.

    Returns
    -------
    (steps, k) bool array
    """
    d = np.asarray(distance, dtype=np.float64)
    shown = np.where(np.asarray(echo, bool) & np.isfinite(d), d, np.nan)
    backed = np.zeros(d.shape, bool)
    pad = np.pad(shown, 1, constant_values=np.nan)
    n, k = d.shape
    with np.errstate(invalid="ignore"):
        for di, dj in ((0, 1), (2, 1), (1, 0), (1, 2)):  # the row before and after, the capsule left and right
            backed |= np.abs(pad[di : di + n, dj : dj + k] - d) <= reach
    return backed


#: float32's unit roundoff and smallest normal number: the rounding bound of :func:`waveform_energy_agrees`.
_FLOAT32_UNIT, _FLOAT32_TINY = 2.0**-24, float(np.finfo(np.float32).tiny)


def waveform_energy_agrees(waveforms: np.ndarray, sample_rate: float, energy) -> bool:
    """Whether ``energy`` is the eq. (10) energy of each waveform, to the rounding of a float32 check.

    A check of claimed :func:`waveform_energy` values (e.g. a writer's), cheaper than recomputing
    them: the float32 samples are squared and summed in float32, without conversion.  A sum of n
    non-negative float32 products is within ``(n + 1)·2⁻²⁴`` of the exact sum relative to it, and
    within ``n`` times the smallest normal float32 absolutely (underflow); the claimed float64 value
    is far closer than that.  So a value outside twice that band is not the waveform's energy, and
    one inside it differs from it by less than float32 rounding of the samples themselves does.

    Parameters
    ----------
    waveforms : (k, n_samples) float32 array
        V (other types are rounded to float32 first).
    sample_rate : float
        Hz.
    energy : sequence of k floats
        The claimed energies, V²·s.

    Returns
    -------
    bool
        False if any claim is off, not finite or negative, or if there is not one a waveform (or the
        float32 squares overflowed).
    """
    w = np.asarray(waveforms)
    if w.dtype != np.float32:
        w = w.astype(np.float32)
    if w.ndim != 2 or len(energy) != len(w):
        return False
    n = w.shape[-1]
    rate = float(sample_rate)
    # (a step's few values: compared in Python, which costs less than more numpy calls would)
    return all(energy_agrees(float(c), s, n, rate) for c, s in zip(energy, np.vecdot(w, w).tolist()))


@kernel
def energy_agrees(claimed: float, sum_of_squares: float, n: int, sample_rate: float) -> bool:
    """Whether ``claimed`` is a waveform's eq. (10) energy, given the float32 sum of its ``n`` squared samples
    (the bound of :func:`waveform_energy_agrees`; compiled: the ingest's kernel uses it)."""
    s = sum_of_squares / sample_rate
    rtol, atol = 2.0 * (n + 1) * _FLOAT32_UNIT, 2.0 * n * _FLOAT32_TINY / sample_rate
    return 0.0 <= claimed < math.inf and abs(claimed - s) <= rtol * max(claimed, s) + atol


def total_energy(sensor_energy: np.ndarray) -> np.ndarray:
    """Total energy of a step over its capsules, the paper's eq. (11).

    Parameters
    ----------
    sensor_energy : (..., n_capsules) array
        ``E_i^γ`` from :func:`waveform_energy`, V²·s.
    """
    e = np.asarray(sensor_energy, dtype=np.float64)
    if e.ndim < 2 or not 0 < e.shape[-1] < 8:
        return np.sum(e, axis=-1)  # (one step, or pairwise beyond 7 capsules)
    return _capsule_sums(np.ascontiguousarray(e.reshape(-1, e.shape[-1]))).reshape(e.shape[:-1])


@kernel
def _capsule_sums(rows: np.ndarray) -> np.ndarray:
    """Each row's sum, term by term in order: ``np.sum(rows, axis=-1)`` to the bit for rows of fewer than 8
    (NumPy's pairwise summation adds those in order; the rig has 4 capsules), without its dispatch."""
    out = np.empty(rows.shape[0])
    for i in range(rows.shape[0]):
        out[i] = step_total_energy(rows[i])
    return out


@kernel
def step_total_energy(row: np.ndarray) -> float:
    """E^γ of one step (eq. 11): the sum of its capsules' eq. (10) energies, ``np.sum``'s to the bit
    (pairwise, in order below 8 terms)."""
    return 0.0 + pairwise_sum(row, 0, row.size)


def fit_energy_model(distance: np.ndarray, energy: np.ndarray) -> EnergyModel:
    """Least-squares calibration of eq. (12) from face-on shots, eq. (13)–(14).

    Solves ``A φ = B`` with the Vandermonde ``A = [d², d, 1]`` and ``B = 1/E``.

    Parameters
    ----------
    distance : (k,) array
        Measured wall distances, m (the paper uses six between 0.9 and 1.8 m).
    energy : (k,) array
        Total energy ``E^{0°}`` of each shot, V²·s.

    Raises
    ------
    ConfigError
        With fewer than three distinct distances or non-positive energies.
    """
    d = np.asarray(distance, dtype=np.float64).ravel()
    e = np.asarray(energy, dtype=np.float64).ravel()
    if d.shape != e.shape:
        raise ConfigError(f"need one energy per distance, got {d.size} distances and {e.size} energies")
    if np.unique(d).size < 3:
        raise ConfigError("the energy model needs shots at three or more distinct distances")
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(e)) and np.all(e > 0) and np.all(d > 0)):
        raise ConfigError("calibration distances and energies must be finite and positive")
    a = np.stack([d * d, d, np.ones_like(d)], axis=1)
    phi, *_ = np.linalg.lstsq(a, 1.0 / e, rcond=None)
    return EnergyModel(float(phi[0]), float(phi[1]), float(phi[2]), d_min=float(d.min()), d_max=float(d.max()))


def median_range(distance: np.ndarray) -> np.ndarray:
    """``d_m``: the median of each step's valid ranges (NaN = no echo), paper §4.

    Parameters
    ----------
    distance : (n_steps, n_capsules) array, m

    Returns
    -------
    (n_steps,) array
        NaN for a step with no valid range.
    """
    d = np.asarray(distance, dtype=np.float64)
    if not d.shape[-1]:
        return np.full(d.shape[:-1], np.nan)
    rows = np.ascontiguousarray(d.reshape(-1, d.shape[-1]))
    return _median_ranges(rows).reshape(d.shape[:-1])


@kernel
def _median_ranges(rows):
    """:func:`step_median_range` of each row (a kernel: np.nanmedian goes through masked arrays)."""
    out = np.empty(rows.shape[0])
    for i in range(rows.shape[0]):
        out[i] = step_median_range(rows[i])
    return out


@kernel
def step_median_range(row):
    """``d_m`` of one step (paper §4): the median of its finite ranges, NaN without one — the mean of the two
    middle values of the sorted finite ranges, found by rank instead of a sort (a step has a few); the ingest
    kernel works out each step's as it is placed."""
    count = 0
    for x in row:
        if math.isfinite(x):
            count += 1
    if count == 0:
        return np.nan
    lo, hi = _middle_pair(row, (count - 1) // 2, count // 2)
    return 0.5 * (lo + hi)


@kernel
def _middle_pair(row, lo, hi):
    """The ``lo``-th and ``hi``-th (from 0) of the non-NaN values of ``row`` in ascending order (where a sort
    puts them), in one pass: each value's rank is counted once for both."""
    a = b = np.nan
    found_a = found_b = False
    for x in row:
        if x == x:
            below = tied = 0
            for y in row:
                if y < x:
                    below += 1
                elif y == x:
                    tied += 1
            if not found_a and below <= lo < below + tied:
                a, found_a = x, True
            if not found_b and below <= hi < below + tied:
                b, found_b = x, True
            if found_a and found_b:
                break
    return a, b


def energy_ratio(
    step_energy: np.ndarray, distance: np.ndarray, model: EnergyModel, *, expected: np.ndarray | None = None
) -> np.ndarray:
    """The indicator ``R = E^γ / E0(d_m)`` of each step (paper §4, Fig. 6).

    Steps with no valid range get R = 0: they cannot be the corner, whose
    double bounce always returns an echo.

    ``expected``, an (n_steps,) array if given, receives ``E0(d_m)`` (eq. 12)
    where ``d_m`` is valid (elsewhere it is left as it is).
    """
    d_m = median_range(distance)
    e = np.ascontiguousarray(step_energy, dtype=np.float64)
    if e.shape != d_m.shape:
        raise ConfigError(f"step_energy must have shape {d_m.shape}, got {e.shape}")
    m = model
    return _ratio_where_ranged(
        e,
        d_m,
        m.phi0,
        m.phi1,
        m.phi2,
        m.d_min,
        m.d_max,
        np.zeros(0) if expected is None else expected,
        expected is not None,
    )


@kernel
def _ratio_where_ranged(
    step_energy: np.ndarray,
    d_m: np.ndarray,
    phi0: float,
    phi1: float,
    phi2: float,
    d_min: float,
    d_max: float,
    expected: np.ndarray,
    write_expected: bool,
) -> np.ndarray:
    """``R = E^γ / E0(d_m)`` where ``d_m`` is finite, else 0 (:func:`energy_ratio`); ``E0`` into ``expected`` there."""
    r = np.zeros(step_energy.shape[0])
    for i in range(step_energy.shape[0]):
        if np.isfinite(d_m[i]):
            e0 = expected_energy_at(d_m[i], phi0, phi1, phi2, d_min, d_max)
            r[i] = step_energy[i] / e0
            if write_expected:
                expected[i] = e0
    return r


@kernel
def expected_energy_at(d: float, phi0: float, phi1: float, phi2: float, d_min: float, d_max: float) -> float:
    """E0(d) = 1 / (φ0·d² + φ1·d + φ2), eq. (12), with ``d`` clipped to the calibrated interval
    [``d_min``, ``d_max``]: ``EnergyModel.expected_energy`` of one range, to the bit."""
    d = min(max(d, d_min), d_max)
    return 1.0 / (phi0 * d * d + phi1 * d + phi2)


@kernel
def step_energy_ratio(
    sensor_energy: np.ndarray,
    distance: np.ndarray,
    phi0: float,
    phi1: float,
    phi2: float,
    d_min: float,
    d_max: float,
) -> tuple[float, float, float, bool]:
    """One step's E^γ (eq. 11, :func:`step_total_energy`), E0(d_m) (eq. 12, :func:`expected_energy_at` of the
    model φ0, φ1, φ2 over [d_min, d_max]) and R = E^γ / E0(d_m) (§4), from its capsules' eq. (10) energies and
    ranges (NaN: no echo); and whether the step has a range (``d_m``, :func:`step_median_range`).  Without one
    E0 is NaN and R is 0: such a step cannot be the corner, whose double bounce always returns an echo.  The
    same numbers as :func:`total_energy` and :func:`energy_ratio` give for the step.
    """
    e = step_total_energy(sensor_energy)
    d_m = step_median_range(distance)
    if not math.isfinite(d_m):
        return e, np.nan, 0.0, False
    e0 = expected_energy_at(d_m, phi0, phi1, phi2, d_min, d_max)
    return e, e0, e / e0, True
