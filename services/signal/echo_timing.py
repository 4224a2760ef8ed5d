"""Echo times that do not walk with the echo's amplitude, and the test of a writer's ranges that do.

A board's comparator sets the time of flight where the echo first crosses a
threshold.  The echo's envelope rises over a few carrier
cycles (the transducers' Q), so on a weaker echo the crossing comes later:
``t(A) ≈ onset + rise·f(threshold/A)``.  Over a sweep a wall's echo weakens
off its normal (``D(ψ)²``), so such ranges carry a bias of millimetres to
centimetres that follows the beam angle — and the wall's direction, which
the corner model reads partly from millimetre range differences across
capsules and steps (eq. 9, 15), turns by degrees.

Here each echo is timed again from its waveform, by **constant fraction**:
the time its envelope rises through a fixed fraction of its own peak
(:func:`echo_onsets`).  For echoes of one shape that time is the same
distance after the onset whatever their strength.  The writer's range minus
this one, against the log of the echo's peak (:func:`range_walk`), is flat
for a board that times the onset and falls for one that times a threshold
crossing; where it falls by more than its noise allows, the ranges are
re-timed (:func:`walk_free_ranges`), keeping the writer's zero: the median
offset over the strongest echoes, whose crossing is nearest their onset.

Pure functions over arrays; the assembly keeps each reading's window as a
sample is placed (:class:`~lelsonar.reconstruct.stream.assembly.ScanAssembly`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from lelsonar.errors import ConfigError
from lelsonar.signal.compiled import kernel

__all__ = [
    "TIMING_WINDOW",
    "CONSTANT_FRACTION",
    "FLOOR_TIME",
    "CARRIER",
    "echo_onsets",
    "hilbert_transform",
    "typical_edges",
    "RangeWalk",
    "range_walk",
    "walk_free_ranges",
    "walk_finding",
]

#: Where an echo is re-timed, s around the writer's time of flight.  A threshold crossing lies up to one
#: envelope rise after the onset (a 0.3–0.6 ms burst rises for half its length), so the onset may lie well
#: before the time of flight; the first 0.1 ms give the noise floor.
TIMING_WINDOW = (-5.0e-4, 5.0e-4)
#: The envelope level, as a share of the echo's own peak, that times it.  Half way up the rising edge: far
#: above the noise on the weakest echo a comparator fires on, and below where a neighbouring echo's tail or
#: the converter's clipping bends the edge.
CONSTANT_FRACTION = 0.5
#: The noise floor is taken over the window's first 0.1 ms (before any onset the window is meant to hold).
FLOOR_TIME = 1.0e-4
#: A peak is a maximum of the smoothed envelope over ±50 µs (two carrier cycles) at least this many robust
#: noise σ above the floor.
_PEAK_HALF_WIDTH = 5.0e-5
_PEAK_SIGMA = 8.0
#: The rising edge's span that measures an echo's shape (:func:`typical_edges`), as shares of its peak, and
#: how far from the scan's median it may lie: weak echoes' noise moves the 20 % point by up to ~10 %; two echoes
#: adding within the rise lengthen it by 25 % (stress `extreme` 17).
_EDGE = (0.2, 0.8)
_EDGE_TOLERANCE = 0.2
#: Share of its steepest rise under which a slowing rise marks the echo's own peak inside a merged hump.
_KNEE = 0.3
#: Carrier the envelope is smoothed over (one period); 40 kHz capsules (paper §3).
CARRIER = 40_000.0


def echo_onsets(
    windows: np.ndarray,
    sample_rate: float,
    tof_at: np.ndarray,
    fraction: float = CONSTANT_FRACTION,
    *,
    level: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Constant-fraction time of the echo that set each reading's time of flight.

    The envelope is the analytic signal's modulus (Hilbert transform) of each window less its floor's
    mean, smoothed over one carrier period.  The echo is the first local maximum of the envelope (over
    ±50 µs) from 50 µs before the time of flight on that stands 8 robust σ over the floor (the median
    and MAD of the window's first 0.1 ms); it is timed where the envelope last rises through
    ``floor + fraction·(peak − floor)`` before that maximum, interpolated between samples.  An echo
    whose window is clipped (a converter's rail: two consecutive samples at the window's extreme, or three
    at the extreme of all ``windows``) is not timed: its peak, so its fraction, is not the echo's.

    Parameters
    ----------
    windows : (N, W) array
        V, :data:`TIMING_WINDOW` around each time of flight.
    sample_rate : float
        Hz.
    tof_at : (N,) array
        The reading's time of flight after each window's first sample, s.
    fraction : float
        Share of the peak that times the echo, in (0, 1).
    level : (N,) array, optional
        Time each echo instead where its envelope rises through this level over its floor (V; at most
        ``fraction`` of its peak), clipped echoes too: a level near the noise's is crossed near the onset of a
        strong echo, whatever its peak (the echoes recovered after a noise trigger,
        :meth:`~lelsonar.reconstruct.stream.assembly.ScanAssembly.recovered_echoes`).

    Returns
    -------
    onset : (N,) array
        The constant-fraction time minus the time of flight, s (negative: before it); NaN where the
        echo could not be timed.
    peak : (N,) array
        The echo's envelope peak over the floor, V (of a clipped echo: the clipped envelope's); NaN where no
        echo was found.
    edge : (N,) array
        s from 20 % to 80 % of the peak on the rising edge: the echo's shape (:func:`typical_edges`); NaN where
        not timed.
    """
    if not 0.0 < fraction < 1.0:
        raise ConfigError(f"the constant fraction must be in (0, 1), got {fraction}")
    w = np.asarray(windows, dtype=np.float64)
    n, width = w.shape
    head = max(int(round(FLOOR_TIME * sample_rate)), 4)
    if n == 0 or width < 2 * head:
        return np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    x = (w - w[:, :head].mean(axis=-1, keepdims=True)).astype(np.float32)
    hilbert = hilbert_transform(x)  # the analytic signal's modulus is √(x² + H{x}²)
    tof_at = np.asarray(tof_at, dtype=np.float64)
    half = max(int(round(_PEAK_HALF_WIDTH * sample_rate)), 1)
    start = np.round(tof_at * sample_rate).astype(np.int64) - half  # from 50 µs before the time of flight
    levels = np.full(n, np.nan) if level is None else np.asarray(level, dtype=np.float64)
    return _time_envelopes(
        w,
        x,
        hilbert,
        tof_at,
        start,
        float(sample_rate),
        head,
        max(int(round(sample_rate / CARRIER)), 1),
        half,
        float(fraction),
        levels,
    )


def hilbert_transform(x: np.ndarray) -> np.ndarray:
    """The Hilbert transform H{x} of each row of ``x`` (N, W), by two real FFTs: −j on the positive frequencies,
    DC and Nyquist dropped (scipy.signal.hilbert's).

    Zero-padded to twice its length: the FFT's wrap-around would carry the echo's ringing tail at the window's
    end onto its start, a leak that follows the echo's timing in the samples (a sub-mm drift).  The result has
    the padded length; its first W samples are the rows'.
    """
    size = sfft.next_fast_len(2 * x.shape[-1], real=True)
    spectrum = sfft.rfft(x, size, axis=-1)
    spectrum[:, 0] = 0.0
    if size % 2 == 0:
        spectrum[:, -1] = 0.0
    spectrum *= -1j
    return sfft.irfft(spectrum, size, axis=-1)


@kernel
def _time_envelopes(w, x, hilbert, tof_at, start, sample_rate, head, period, half, fraction, levels):
    """:func:`echo_onsets` from each window ``w`` (N, W), less its floor's mean ``x`` (float32), and the
    Hilbert transform of ``x`` (``hilbert``, (N, ≥ W) float32): the envelope, its smoothing, the floor, the peak,
    the knee and the crossings, one window at a time (a kernel: as NumPy over the whole block it pays per-call
    overhead for every window of a scan's screen).

    ``start`` is the first sample the echo's peak is looked for from, ``period`` the carrier period and
    ``half`` the peak's half width, in samples; ``levels`` :func:`echo_onsets`' ``level`` (all NaN: none); the
    rest as :func:`echo_onsets`.  Returns its ``(onset, peak, edge)``.
    """
    n, width = w.shape
    onset, peak, edge = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    # A converter's rail: two consecutive samples at the window's extreme (a flat top), or three samples at
    # the extreme of all the windows (at 5 samples a carrier cycle a clipped cycle may hold only one).
    top_all, bottom_all = w.max(), w.min()
    floor, sigma = np.empty(n), np.empty(n)
    k_peaks, found, clipped = np.zeros(n, np.int64), np.zeros(n, np.bool_), np.zeros(n, np.bool_)
    smooth = np.empty((n, width))
    env = np.empty(width)
    rise = np.zeros(width)
    ordered, deviation = np.empty(head), np.empty(head)  # the floor's stretch, reused row after row
    for r in range(n):
        row = w[r]
        hi, lo = row.max(), row.min()
        at_top = at_bottom = 0
        for i in range(width):
            if row[i] == top_all:
                at_top += 1
            if row[i] == bottom_all:
                at_bottom += 1
            if i > 0 and ((row[i] == hi and row[i - 1] == hi) or (row[i] == lo and row[i - 1] == lo)):
                clipped[r] = True
        if at_top >= 3 or at_bottom >= 3:
            clipped[r] = True
        for i in range(width):
            env[i] = np.hypot(x[r, i], hilbert[r, i])  # the analytic signal's modulus, rounded to float32
        e = smooth[r]
        _moving_mean(env, period, e)
        floor[r] = _head_median(e, head, ordered)
        for i in range(head):
            deviation[i] = abs(e[i] - floor[r])
        sigma[r] = 1.4826 * _head_median(deviation, head, ordered)
        # The echo: the first local maximum from 50 µs before the time of flight on that stands 8 σ over the
        # floor; ``j`` where the envelope first stands out of the noise.
        level = floor[r] + _PEAK_SIGMA * sigma[r]
        j = k_peak = -1
        for i in range(max(start[r], 0), width):
            if e[i] > level:
                if j < 0:
                    j = i
                if _local_maximum(e, i, half):
                    k_peak = i
                    break
        found[r] = k_peak >= 0
        if j < 0:
            j = 0
        if k_peak < 0:
            k_peak = 0
        # A later echo that starts rising before this one's peak merges with it into one hump, whose peak is
        # not this echo's.  Between the two the rise slows almost to a stop and picks up again: where the
        # envelope's rise over a carrier period falls under a third of its steepest (after the steepest, before
        # the hump's peak) this echo has peaked.  (An echo alone slows down only at its peak: no change.)
        for i in range(max(j, period), k_peak + 1):
            rise[i] = e[i] - e[i - period]
        # (The first steepest and the first slowest, as argmax and argmin pick them; 0 where nothing rises.)
        steepest = 0
        for i in range(j, k_peak + 1):
            if i == j or rise[i] > rise[steepest]:
                steepest = i
        knee = steepest
        for i in range(steepest + 1, k_peak + 1):
            if rise[i] < rise[knee]:
                knee = i
        # ... and the hump rises again after the knee by more than the noise could (a noisy rise on a weak echo
        # can dip anywhere near its top).
        if (
            knee < k_peak - period
            and rise[knee] < _KNEE * rise[steepest]
            and e[k_peak] - e[knee] > max(0.2 * (e[knee] - floor[r]), _PEAK_SIGMA * sigma[r])
        ):
            k_peak = knee
        k_peaks[r] = k_peak
    # An earlier echo under the threshold still ringing in the window's first 0.1 ms: this echo rises on its
    # tail, from no floor the fraction can be taken over.  Neither timed nor given a peak (the writer's range
    # stands).
    tail = np.median(floor) + _PEAK_SIGMA * np.median(sigma)
    for r in range(n):
        if not (found[r] and floor[r] <= tail):
            continue
        e, k_peak = smooth[r], k_peaks[r]
        peak[r] = e[k_peak] - floor[r]
        share = fraction
        if levels[r] == levels[r]:  # a level given: a clipped echo's onset is its own
            share = min(levels[r] / peak[r], fraction)
        j, crossing = _fraction_crossing(e, floor[r], k_peak, share)
        # The edge starts inside the window, after the floor's stretch began.
        if j >= head // 2 and (not clipped[r] or levels[r] == levels[r]):
            onset[r] = crossing / sample_rate - tof_at[r]
            low = _fraction_crossing(e, floor[r], k_peak, _EDGE[0])[1]
            high = _fraction_crossing(e, floor[r], k_peak, _EDGE[1])[1]
            edge[r] = (high - low) / sample_rate
    return onset, peak, edge


@kernel
def _head_median(x, m, ordered):
    """``np.median(x[:m])`` bit for bit (NaN in, NaN out), sorted into ``ordered`` (at least ``m`` long) instead
    of a fresh array: a few dozen samples a row, where the allocation would cost more than the sort."""
    for i in range(m):
        v = x[i]
        if v != v:
            return np.nan
        j = i
        while j > 0 and ordered[j - 1] > v:
            ordered[j] = ordered[j - 1]
            j -= 1
        ordered[j] = v
    if m % 2:
        return ordered[m // 2]
    return (ordered[m // 2 - 1] + ordered[m // 2]) / 2.0


@kernel
def _moving_mean(x, size, out):
    """``out``: the mean of ``x`` over ``size`` samples centred on each (the ends repeated beyond), summed as
    scipy.ndimage.uniform_filter1d(mode="nearest") sums it: a running sum, so the same to the last bit."""
    n = x.size
    before = size // 2
    after = size - before - 1
    total = 0.0
    for i in range(-before, after + 1):
        total += x[min(max(i, 0), n - 1)]
    out[0] = total / size
    for i in range(1, n):
        total += x[min(i + after, n - 1)] - x[max(i - 1 - before, 0)]
        out[i] = total / size


@kernel
def _local_maximum(x, i, half):
    """Whether ``x[i]`` is the maximum of ``x`` over ±``half`` samples around it (the ends repeated beyond)."""
    for k in range(i + 1, min(i + half, x.size - 1) + 1):  # ahead first: on a rising edge the next is higher
        if x[k] > x[i]:
            return False
    for k in range(max(i - half, 0), i):
        if x[k] > x[i]:
            return False
    return True


@kernel
def _fraction_crossing(env, floor, k_peak, fraction):
    """Where an envelope last rises through ``floor + fraction·(env[k_peak] − floor)`` before ``k_peak``:
    the last sample under that level (-1: none) and the crossing, in samples, interpolated linearly."""
    level = floor + fraction * (env[k_peak] - floor)
    j = -1
    for i in range(k_peak - 1, -1, -1):
        if env[i] < level:
            j = i
            break
    jj = max(j, 0)
    e0, e1 = env[jj], env[min(jj + 1, env.size - 1)]
    return j, jj + (level - e0) / (e1 - e0)


@kernel
def typical_edges(edge):
    """Which echoes have the scan's usual shape: a rising edge (``edge``, :func:`echo_onsets`) within 20 % of
    the median's.

    Constant-fraction times are amplitude-free only for echoes of one shape.  Two echoes a few mm apart
    (a wall's mirror echo and the corner's double bounce near the edge's direction) interfere into an
    envelope of another shape, weaker for cancelling, timed elsewhere: left in, they make a board that times
    the onset look as if it walked.  Their edge is shorter or longer than the lone echoes'.

    Parameters
    ----------
    edge : float64 array
        s, of any shape.

    Returns
    -------
    bool array of ``edge``'s shape
        False where the edge is NaN or atypical.
    """
    e = edge.flatten()
    ok = np.isfinite(e)
    if not ok.any():
        return ok.reshape(edge.shape)
    typical = np.median(e[ok])
    return (ok & (np.abs(e - typical) <= _EDGE_TOLERANCE * typical)).reshape(edge.shape)


@dataclass(frozen=True)
class RangeWalk:
    """How a writer's ranges follow the echoes' strength (:func:`range_walk`).

    Attributes
    ----------
    n : int
        Echoes timed from their waveforms.
    slope : float
        m of range per unit of ln(peak): the writer's range minus the re-timed one against the log of the
        echo's peak (0 for a board that times the onset; negative for one that times a threshold crossing).
    slope_stderr : float
        m, its standard error from the scatter about the line.
    walk : float
        m, the range the slope moves between the 10th and 90th percentile of the peaks (positive: weaker
        echoes read farther).
    reference : float
        m, the median offset (writer − re-timed) over the strongest quarter of the echoes: the writer's zero.
    detected : bool
        The walk is over ``min_walk`` and ``z`` standard errors.
    untimed : int
        Echoes found in their windows but not timed (clipped at their peak): their ranges stay the writer's.
    curve : tuple of (ln peak, offset, spread) triples
        The offsets' median and robust σ in bins of ln(peak) (m): the walk's own shape, which need not be a
        line, and its scatter (the writer's jitter, the re-timing's noise, and the walk across the bin).
    """

    n: int
    slope: float
    slope_stderr: float
    walk: float
    reference: float
    detected: bool
    untimed: int = 0
    curve: tuple[tuple[float, float, float], ...] = ()

    def expected(self, peak: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The offset :attr:`curve` gives an echo of ``peak`` V and its scatter (m), and whether the peak lies
        inside the curve's span (outside, both are the end bin's)."""
        x, y, s = (np.array(v) for v in zip(*self.curve)) if self.curve else (np.zeros(1),) * 3
        with np.errstate(divide="ignore", invalid="ignore"):
            a = np.log(np.asarray(peak, dtype=np.float64))
        return np.interp(a, x, y), np.interp(a, x, s), (a >= x[0]) & (a <= x[-1])


#: Fewest re-timed echoes the test rests on (``RANGE_CHECK_MIN`` of the assembly's other scan-wide checks).
MIN_TIMED = 16
#: Smallest walk that is corrected: 3 mm over the echoes' range of strength, half the range noise
#: :class:`~lelsonar.reconstruct.estimate.quality.QualityLimits` expects (6 mm) and 70 % of a carrier half-cycle.
MIN_WALK = 0.003
#: Echoes per bin of :attr:`RangeWalk.curve` (at most 10 bins).
_PER_BIN = 24
#: An echo whose own offset is this many robust σ of its bin off the curve is re-timed by the curve
#: instead (its window held a neighbour's echo, or the writer's comparator slipped a cycle).
_TRUST = 3.0
#: Standard errors the walk must stand out by among the weaker and among the stronger half of the echoes.
_HALF_Z = 3.0
#: Standard errors the walk must stand out by: a flat writer (onset-timed) passes it by chance once in
#: ~30 000 scans (one-sided normal tail at 4σ).
WALK_Z = 4.0


def range_walk(
    offset: np.ndarray, peak: np.ndarray, *, min_walk: float = MIN_WALK, z: float = WALK_Z, halves: bool = True
) -> RangeWalk:
    """Whether the writer's ranges walk with the echoes' amplitude.

    A least-squares line of ``offset`` against ``ln(peak)``, after dropping offsets more than 5 robust σ
    from their median (a cycle slip of the writer's comparator, an echo timed on a neighbour).

    Parameters
    ----------
    offset : (N,) array
        m, each echo's writer range minus its re-timed range ``c/2·(tof + onset)`` (NaN: not timed).
    peak : (N,) array
        V, its envelope peak (:func:`echo_onsets`).
    min_walk, z : float
        The detection's lines (:data:`MIN_WALK`, :data:`WALK_Z`).
    halves : bool
        Also ask that the walk runs through the weaker and the stronger half of the echoes alike (False: a
        screen, e.g. on a sample of the echoes before all are re-timed).
    """
    o = np.asarray(offset, dtype=np.float64).ravel()
    a = np.asarray(peak, dtype=np.float64).ravel()
    untimed = int(np.count_nonzero(np.isfinite(a) & ~np.isfinite(o)))
    ok = np.isfinite(o) & np.isfinite(a) & (a > 0)
    n, line, curve = _walk_line(o[ok], np.log(a[ok]))
    slope, stderr, walk, reference, slope_weak, stderr_weak, slope_strong, stderr_strong = line
    if math.isnan(slope):  # too few echoes, or all of one strength
        return RangeWalk(n, math.nan, math.nan, 0.0, 0.0, False, untimed)
    # A comparator's delay falls as 1/√A well above its threshold, so its walk runs through the weaker and
    # the stronger half of the echoes alike.  A trend in one half only is something else: a wall's echo and
    # the corner's a few mm apart (near the edge's direction) add into an envelope of another timing, weak
    # where they cancel, strong where they add, which would make a board that times the onset look as if
    # it walked.
    detected = (
        walk > min_walk
        and -slope > z * stderr
        and (not halves or (-slope_weak > _HALF_Z * stderr_weak and -slope_strong > _HALF_Z * stderr_strong))
    )
    return RangeWalk(
        n,
        slope,
        stderr,
        walk,
        reference,
        bool(detected),
        untimed,
        tuple((float(x), float(y), float(s)) for x, y, s in curve),
    )


@kernel
def _walk_line(o, a):
    """:func:`range_walk`'s statistics of the offsets ``o`` (m) against the log peaks ``a`` of the echoes
    timed: how many are kept, ``(slope, stderr, walk, reference)`` and the slope and its standard error over
    the weaker and the stronger half (NaN: too few), and the curve's ``(ln peak, offset, spread)`` rows.
    (A kernel: in NumPy it is ~60 small calls a final.)"""
    if o.size >= MIN_TIMED:
        med = np.median(o)
        mad = 1.4826 * np.median(np.abs(o - med))
        keep = np.abs(o - med) <= 5.0 * max(mad, 1e-4)
        o, a = o[keep], a[keep]
    line = np.full(8, np.nan)
    n = o.size
    if n < MIN_TIMED or a.max() - a.min() <= 0:
        return n, line, np.empty((0, 3))
    line[0], line[1] = _line(a, o)
    order = np.argsort(a, kind="mergesort")
    ranked = a[order]
    line[2] = -line[0] * (_percentile(ranked, 90.0) - _percentile(ranked, 10.0))
    line[3] = np.median(o[a >= _percentile(ranked, 75.0)])
    upper = a >= np.median(a)
    line[4], line[5] = _line(a[~upper], o[~upper])
    line[6], line[7] = _line(a[upper], o[upper])
    # Bins of ln(peak) as np.array_split cuts the ranking: the first ``n % bins`` one echo larger.
    bins = min(10, max(n // _PER_BIN, 2))
    curve = np.empty((bins, 3))
    size, extra = divmod(n, bins)
    first = 0
    for b in range(bins):
        last = first + size + (1 if b < extra else 0)
        members = order[first:last]
        ob = o[members]
        mid = np.median(ob)
        curve[b, 0] = np.median(a[members])
        curve[b, 1] = mid
        curve[b, 2] = 1.4826 * np.median(np.abs(ob - mid))
        first = last
    return n, line, curve


@kernel
def _percentile(ranked, q):
    """np.percentile(…, q) (its default, linear interpolation, and its rounding) of an ascending array."""
    n = ranked.size
    virtual = (n - 1) * (q / 100.0)
    below = int(math.floor(virtual))
    if virtual >= n - 1:
        return ranked[n - 1]
    t = virtual - below
    lo, hi = ranked[below], ranked[below + 1]
    if t >= 0.5:
        return hi - (hi - lo) * (1.0 - t)
    return lo + (hi - lo) * t


@kernel
def _line(x, y):
    """Least-squares slope of ``y`` against ``x`` and its standard error from the scatter (NaN: too few)."""
    if x.size < 3 or x.max() - x.min() <= 0:
        return math.nan, math.nan
    xm = x - x.mean()
    ym = y - y.mean()
    sxx = np.sum(xm * xm)
    slope = np.sum(xm * ym) / sxx
    resid = ym - slope * xm
    return slope, math.sqrt(np.sum(resid * resid) / (x.size - 2) / sxx)


def walk_free_ranges(distance: np.ndarray, offset: np.ndarray, peak: np.ndarray, walk: RangeWalk) -> np.ndarray:
    """The writer's ranges re-timed where they walk: ``distance − offset + reference`` for each timed echo.

    The strongest echoes keep their range (``reference`` is their median offset), so the planes keep the
    writer's zero; each weaker echo moves by what its crossing came later than theirs.  An echo whose own
    offset lies over 3 robust σ from the walk's :attr:`~RangeWalk.curve` within its span (its window also
    held a later echo that merged with its rise, or the writer slipped a cycle) moves by the curve at its
    peak instead.  (An echo of atypical shape, :func:`typical_edges`, stays out of the test and the curve,
    but is timed as well as the others where it agrees with them.)  An echo found but clipped has walked by
    an unknown amount and is left out (NaN); one not found in its window (no waveform) keeps the writer's
    range.  Unchanged when ``walk.detected`` is False.

    Parameters
    ----------
    distance, offset, peak : arrays of one shape
        m, m, V: the writer's ranges, :func:`range_walk`'s offsets (NaN: not timed) and peaks (NaN: no echo
        found).
    walk : RangeWalk
    """
    d = np.asarray(distance, dtype=np.float64)
    if not walk.detected:
        return d
    o = np.asarray(offset, dtype=np.float64)
    p = np.asarray(peak, dtype=np.float64)
    expected, spread, inside = walk.expected(p)
    own = (np.abs(o - expected) <= _TRUST * np.maximum(spread, 1e-3)) | ~inside
    timed = np.isfinite(o)
    moved = d - np.where(own, o, expected) + walk.reference
    return np.where(timed, moved, np.where(np.isfinite(p), np.nan, d))


def walk_finding(walk: RangeWalk) -> str:
    """The reason each plane carries when its ranges were re-timed."""
    return (
        f"ranges re-timed from the waveforms: the writer's walk {1000 * walk.walk:.1f} mm later on weaker "
        f"echoes ({1000 * walk.slope:+.1f} ± {1000 * walk.slope_stderr:.1f} mm per e-fold of amplitude, "
        f"{walk.n} echoes; a comparator timing a threshold crossing); constant-fraction times used, zero "
        "kept at the strongest echoes'"
    )
