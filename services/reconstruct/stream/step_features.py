"""The per-sample pass: everything one step's readings and waveforms give, in one compiled pass.

A sample's readings and waveforms are worked on once, as it is placed, while its samples are in the cache
(:func:`place_step`): the contract's checks of a sample not validated yet (its samples finite among them),
the carried eq. (10) energies checked against the waveforms in float32
(:func:`~lelsonar.signal.energy.energy_agrees`, one sum of squares a waveform) instead of integrated again in
float64, each reading's range and round trip, the first echo's peak
(:func:`~lelsonar.signal.energy.echo_amplitude`'s window) and, on every :data:`RISE_STRIDE`-th step, the peak
just before it and the DC level (for the writer checks), each waveform around its time of flight (and around
the first echo after it, where the reading may be the noise a board fired on:
:func:`~lelsonar.reconstruct.stream.candidates.candidate_echo`), and the step's E^γ, E0(d_m) and R (§4,
eq. 11–12; :func:`settle_step`, :func:`~lelsonar.signal.energy.step_energy_ratio`).
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.codec import MAX_RANGE_M
from lelsonar.reconstruct.stream.candidates import candidate_echo
from lelsonar.signal.compiled import array_at, float32_at, kernel, prefetch, summing_kernel
from lelsonar.signal.echo_timing import TIMING_WINDOW
from lelsonar.signal.energy import (
    ECHO_PEAK_WINDOW,
    PRE_ECHO_WINDOW,
    echo_window_start,
    energy_agrees,
    step_energy_ratio,
    window_samples,
)
from lelsonar.signal.extrema import largest_magnitude

#: The ranges are checked (against the waveforms, against the time of flight) on every this-many-th step by
#: index: each check is a median over the scan, and a quarter of a 184-step scan's readings is 184 of them.
RISE_STRIDE = 4

#: The (steps, k) arrays of a scan, in the order of their block (:meth:`ScanAssembly._allocate`): range (m; NaN: no
#: echo or not received), eq. (10) energy (V²·s; 0), first echo's peak (V; NaN: none), the peak just before it
#: (V; NaN: none or not a sampled step), |mean| of the waveform (V), distance / (c·tof/2) (NaN: not both); where
#: each reading's timing window starts (``_timing_at``: its time of flight after the window's first sample, s)
#: and, for a reading that may be the noise a board fired on, its candidate echo's (``_candidate_at``: the echo's
#: first crossing after its window's first sample, s; ``_candidate_start``: that sample's time after firing, s).
PER_CAPSULE = (
    "distance",
    "sensor_energy",
    "echo_amplitude",
    "pre_echo_peak",
    "dc_level",
    "range_tof_ratio",
    "_timing_at",
    "_candidate_at",
    "_candidate_start",
)
#: The (steps,) float arrays: γ measured and commanded (rad; NaN until received), E^γ (eq. 11), E0(d_m)
#: (eq. 12), R = E^γ / E0(d_m) (0 without a range).
PER_STEP = ("gamma", "gamma_commanded", "step_energy", "expected_energy", "ratio")

#: :func:`place_step`'s refusals (nothing written): a sample not validated that its screen does not clear (a
#: check of the contract, or a NaN or infinite sum of squares: NaN or infinite samples, or squares that
#: overflowed float32), a range without a speed of sound.
UNCHECKED, NO_SOUND_SPEED = -1, -2
#: In its result otherwise: the carried energies agree and were written; the rest counts unflagged ranges.
AGREED = 1
#: ... plus this where a reading's candidate echo was found before the scan kept any (their windows not allocated
#: yet: :meth:`ScanAssembly._keep_candidates` copies this step's); the unflagged ranges count below it.
CANDIDATES = 1 << 24


@kernel
def place_step(
    waveforms,
    values,
    scan,
    m,
    step,
    checked,
    time_ns,
    recovered,
    per_capsule,
    per_step,
    acquired_ns,
    received,
    recovered_mask,
    timing_windows,
    candidate_windows,
):
    """Everything one step's readings and waveforms give, in one pass while they are in the cache: unless the
    sample was validated, the checks of the contract on its readings (:func:`lelsonar.codec.validate_body`'s
    screen: γ and the motor's readings finite, each valid echo's range finite, positive and below
    ``codec.MAX_RANGE_M``); each waveform's samples checked finite, its carried eq. (10) energy checked
    (:func:`~lelsonar.signal.energy.energy_agrees`, float32 sum of squares), each reading's range and round
    trip (one from the other at the speed of sound where only one is given), the first echo's peak
    (:func:`~lelsonar.signal.energy.echo_amplitude`'s window), and on
    every :data:`RISE_STRIDE`-th step the peak just before it, the DC level and distance / (c·tof/2); written
    into row ``step`` of the scan's arrays, with γ, the time and the step's origin; each waveform around its
    time of flight (:data:`~lelsonar.signal.echo_timing.TIMING_WINDOW`), to re-time the echo if need be,
    and where the reading may be the noise a board fired on, the same around its first echo after
    (:func:`~lelsonar.reconstruct.stream.candidates.candidate_echo`); and, where the carried energies were
    written, the step's E^γ, E0(d_m) and R (:func:`settle_step`, eq. 11–12).

    Parameters
    ----------
    waveforms : (k, n) float32 array
        The k waveforms (V), in the order of the scan's capsules (k: the scan's, ``per_capsule.shape[2]``).
        (:func:`place_rows` reads them where they lie instead: the bytes ``buf``, each waveform's ``n`` samples
        from ``buf[starts[i]]`` on.)
    values : (≥ 6·k + 5,) float64 array
        Each waveform's sample rate (Hz) and t0 (s); γ measured and commanded (rad); the motor's load,
        voltage and temperature; each reading's ``echo_valid, distance, time_of_flight`` (same order); the
        ``m`` carried energies (V²·s), m = k or 0 (none to check).
    scan : (7,) float64 array
        The scan's speed of sound (m/s; NaN: none stated), the timing windows' rate (Hz), and its energy
        model φ0, φ1, φ2, d_min, d_max (eq. 12).
    checked : bool
        The sample was validated (:func:`lelsonar.codec.validate_body`): its samples are finite, so a
        non-finite sum of squares is an overflow (the energies then disagree); otherwise that, or a reading
        the screen does not clear, is ``UNCHECKED`` (for the caller to validate it, naming the culprit).
    time_ns, recovered : int, bool
        The sample's acquisition time and origin (the acquirer's log).
    per_capsule, per_step : (9, steps, k), (5, steps) float64 arrays
        The scan's blocks (:data:`PER_CAPSULE`, :data:`PER_STEP`).
    acquired_ns, received, recovered_mask : (steps,) arrays
        The scan's ``time_ns``, ``received``, ``recovered_mask``.
    timing_windows : (steps, k, width) float32 array
        Where each waveform's window around its time of flight goes, if its rate is the windows' (``scan[1]``)
        and the window lies inside it (its start's offset from the time of flight into ``_timing_at``).
    candidate_windows : (steps, k, width) float32 array
        Where a waveform's window around its candidate echo goes (:func:`candidate_echo`; the echo's crossing
        after the window's start into ``_candidate_at``, the start's time into ``_candidate_start``).

    Returns
    -------
    int
        A refusal (< 0, nothing written), else ``AGREED`` if the carried energies were each waveform's and
        written (not written otherwise, nor E^γ, E0 and R), plus twice the readings without an echo that carry
        a range anyway, plus ``CANDIDATES`` if a candidate echo's window was found but not kept
        (``candidate_windows`` not allocated yet).
    """
    k, n = waveforms.shape
    starts = np.arange(k) * (4 * n)
    return place_rows(
        waveforms.reshape(k * n).view(np.uint8),
        starts,
        n,
        values,
        scan,
        m,
        step,
        checked,
        time_ns,
        recovered,
        per_capsule,
        per_step,
        acquired_ns,
        received,
        recovered_mask,
        timing_windows,
        candidate_windows,
    )


@kernel
def place_rows(
    buf,
    starts,
    n,
    values,
    scan,
    m,
    step,
    checked,
    time_ns,
    recovered,
    per_capsule,
    per_step,
    acquired_ns,
    received,
    recovered_mask,
    timing_windows,
    candidate_windows,
):
    """:func:`place_step` of the k waveforms of ``n`` samples that lie in the bytes ``buf`` (1-d uint8), the i-th
    from byte ``starts[i]`` on: read there (:func:`~lelsonar.signal.compiled.float32_at`), each in one pass while
    it is in the cache."""

    k = starts.size
    # Where the readings and the carried energies start in ``values`` (indexed, not sliced: a slice of an array
    # costs an atomic reference count, and the pass makes dozens).
    r0, e0 = 2 * k + 5, 5 * k + 5
    if not checked:
        # codec._validate_sample's screen (a sum is finite only if each term is), refusing nothing it clears.
        if not math.isfinite(
            values[2 * k] + values[2 * k + 1] + values[2 * k + 2] + values[2 * k + 3] + values[2 * k + 4]
        ):
            return UNCHECKED
        for i in range(k):
            d, t = values[r0 + 3 * i + 1], values[r0 + 3 * i + 2]
            if values[r0 + 3 * i] != 0.0 and not (math.isfinite(t + d) and 0.0 < d < MAX_RANGE_M and t > 0.0):
                return UNCHECKED
    agreed = m == k
    sampled = step % RISE_STRIDE == 0
    # A sampled step's DC levels come from the same read of each waveform (:func:`row_sums`), written into its row
    # (NaN: the waveform's sum was not exact, summed again below), which a refusal leaves NaN again, as it was (the
    # step is not received).
    levelled = sampled and n > 0
    dc = per_capsule[4, step]
    for i in range(k):
        squares, total, top, low = streamed_sums(buf, starts[i], n, levelled)
        if levelled:
            dc[i] = exact_mean(total, top, low, n)
        if not math.isfinite(squares):  # NaN or infinite samples (or float32 overflow)
            if not checked:
                if levelled:
                    dc[:] = np.nan
                return UNCHECKED
            agreed = False
        elif agreed:
            agreed = energy_agrees(values[e0 + i], float(squares), n, values[2 * i])
    c, timing_rate = scan[0], scan[1]
    for i in range(k):
        at = r0 + 3 * i
        if values[at] != 0.0 and not (values[at + 1] > 0.0 and values[at + 2] > 0.0) and not c == c:
            if levelled:
                dc[:] = np.nan
            return NO_SOUND_SPEED
    width = timing_windows.shape[2]
    kept = candidate_windows.shape[2] == width
    unflagged = 0
    unkept = False
    for i in range(k):
        d, t = values[r0 + 3 * i + 1], values[r0 + 3 * i + 2]
        rate, t0 = values[2 * i], values[2 * i + 1]
        ratio = np.nan
        if values[r0 + 3 * i] != 0.0:  # echo_valid
            if not (d > 0.0 and t > 0.0):
                if d > 0.0:
                    t = 2.0 * d / c
                else:
                    d = 0.5 * c * t
            elif c == c:
                ratio = d / (0.5 * c * t)
        else:
            if d > 0.0:  # NaN compares false: only a positive range counts
                unflagged += 1
            d = t = np.nan
        per_capsule[0, step, i] = d  # distance
        if agreed:
            per_capsule[1, step, i] = values[e0 + i]  # sensor_energy
        row = float32_at(buf, starts[i], n)
        per_capsule[2, step, i] = window_peak(row, rate, t0, t, ECHO_PEAK_WINDOW[0], ECHO_PEAK_WINDOW[1])
        if width > 0 and rate == timing_rate and t > 0.0:  # NaN compares false: no echo, nothing to time
            a = int(round((t + TIMING_WINDOW[0] - t0) * rate))
            if a >= 0 and a + width <= n:
                for j in range(width):  # (a loop: a slice assignment checks for overlap first)
                    timing_windows[step, i, j] = row[a + j]
                per_capsule[6, step, i] = t - (t0 + a / rate)  # _timing_at
                b = candidate_echo(row, a, width, rate)
                if b >= 0:
                    c0 = (
                        b + a - width // 2
                    )  # the crossing in the middle of its window, as the time of flight in its own
                    if c0 + width <= n:
                        if kept:
                            for j in range(width):
                                candidate_windows[step, i, j] = row[c0 + j]
                        else:
                            unkept = True
                        per_capsule[7, step, i] = (b + a - c0) / rate  # _candidate_at
                        per_capsule[8, step, i] = t0 + c0 / rate  # _candidate_start
        if sampled:
            per_capsule[5, step, i] = ratio  # range_tof_ratio
            if n > 0:
                per_capsule[3, step, i] = window_peak(  # pre_echo_peak
                    row, rate, t0, t, PRE_ECHO_WINDOW[0], PRE_ECHO_WINDOW[1]
                )
    if levelled:
        _inexact_dc_levels(buf, starts, n, dc)
    per_step[0, step], per_step[1, step] = values[2 * k], values[2 * k + 1]  # γ measured, commanded
    if agreed:
        settle_step(per_capsule, per_step, step, scan)
    acquired_ns[step] = time_ns
    received[step] = True
    recovered_mask[step] = recovered
    return (AGREED if agreed else 0) + 2 * unflagged + (CANDIDATES if unkept else 0)


@kernel
def prefetch_rows(per_capsule, per_step, timing_windows, step, rows, k, width):
    """Ask for the lines of row ``step`` of a scan's blocks and timing windows (their addresses: the (9, rows, k) and
    (5, rows) float64 blocks, the (rows, k, width) float32 windows), which :func:`place_rows` writes the step into:
    they arrive while it reads the sample, where each store would otherwise wait for its line."""
    capsules = array_at(per_capsule, len(PER_CAPSULE) * rows * k * 8, np.uint8)
    for p in range(len(PER_CAPSULE)):
        first = (p * rows + step) * k * 8
        prefetch(capsules, first)
        prefetch(capsules, first + k * 8 - 1)
    steps = array_at(per_step, len(PER_STEP) * rows * 8, np.uint8)
    for p in range(len(PER_STEP)):
        prefetch(steps, (p * rows + step) * 8)
    size = k * width * 4
    if size > 0:
        windows = array_at(timing_windows, rows * size, np.uint8)
        for q in range(0, size, 64):
            prefetch(windows, step * size + q)
        prefetch(windows, step * size + size - 1)


@kernel
def settle_step(per_capsule, per_step, step, scan):
    """Row ``step``'s E^γ (eq. 11), E0(d_m) (eq. 12, where the step has a range) and R = E^γ / E0(d_m) (§4; 0
    without a range) into ``per_step``, from its ranges and eq. (10) energies in ``per_capsule``
    (:func:`~lelsonar.signal.energy.step_energy_ratio` of the model in ``scan[2:7]``: φ0, φ1, φ2, d_min,
    d_max)."""
    e, e0, r, ranged = step_energy_ratio(
        per_capsule[1, step], per_capsule[0, step], scan[2], scan[3], scan[4], scan[5], scan[6]
    )
    per_step[2, step] = e
    if ranged:
        per_step[3, step] = e0
    per_step[4, step] = r


@kernel
def window_peak(row, rate, t0, round_trip, lo, hi):
    """The largest |w| of ``row`` over the window (``lo``, ``hi``) s after ``round_trip``
    (:func:`~lelsonar.signal.energy.echo_amplitude` of one waveform: exact, in float32); NaN: none."""
    n = row.size
    a = echo_window_start(n, rate, t0, round_trip, lo)
    if a < 0:
        return np.nan
    return largest_magnitude(row, a, min(a + window_samples(rate, lo, hi), n))


@kernel
def dc_levels(waveforms, out):
    """|mean| of each float32 waveform (row), V, into ``out``: :func:`dc_levels_at` of the rows."""
    k, n = waveforms.shape
    dc_levels_at(waveforms.reshape(k * n).view(np.uint8), np.arange(k) * (4 * n), n, out)


@kernel
def dc_levels_at(buf, starts, n, out):
    """|mean| of each float32 waveform of ``n`` samples in the bytes ``buf``, the i-th from byte ``starts[i]`` on
    (read there: :func:`~lelsonar.signal.compiled.float32_at`), V, into ``out``, bit for bit what ``np.mean(...,
    dtype=np.float64)`` gives: that sums the samples in float64 in order (through its cast, not pairwise).

    In-order float64 additions cannot run side by side without changing the rounding, so they are done exactly
    instead where they can be, where every order gives the same number: in any order where the samples' binades
    are few enough (:func:`exact_mean`), else scaled to integers that add up exactly (:func:`_inexact_dc_levels`);
    only a waveform that fits neither is summed in order.
    """
    if n == 0:
        return
    for i in range(starts.size):
        _, total, top, low = row_sums(float32_at(buf, starts[i], n))
        out[i] = exact_mean(total, top, low, n)
    _inexact_dc_levels(buf, starts, n, out)


#: Samples of a waveform summed in one go by :func:`streamed_sums` (1 KB), and how far ahead of them, in bytes, the
#: payload is asked for: the processor's own prefetch stops at each 4 KB page, so a pass left to it waits for
#: memory at every page of a 56 KB sample.
STREAM_CHUNK, STREAM_AHEAD = 256, 2048


@kernel
def streamed_sums(buf, start, n, levelled):
    """:func:`sum_of_squares` (and, if ``levelled``, the rest of :func:`row_sums`; else 0, 0 and 2^32 − 1) of the
    float32 waveform of ``n`` samples at byte ``start`` of ``buf``, read in chunks of :data:`STREAM_CHUNK` samples,
    each while the bytes :data:`STREAM_AHEAD` after it are fetched.  The extremes are :func:`row_sums`' and the
    sums are added up in another order: the float64 sum is the same wherever :func:`exact_mean` uses it, and the
    sum of squares within the bound the energy check allows for any order."""
    squares = np.float32(0.0)
    total = 0.0
    top = np.uint32(0)
    low = np.uint32(0xFFFFFFFF)
    last = buf.size - 1
    for c in range(0, n, STREAM_CHUNK):
        at = start + 4 * c
        for q in range(0, 4 * STREAM_CHUNK, 64):
            prefetch(buf, min(at + STREAM_AHEAD + q, last))
        row = float32_at(buf, at, min(STREAM_CHUNK, n - c))
        if levelled:
            s, t, hi, lo = row_sums(row)
            total += t
            top = max(top, hi)
            low = min(low, lo)
        else:
            s = sum_of_squares(row)
        squares += s
    return squares, total, top, low


@summing_kernel
def sum_of_squares(row):
    """The float32 sum of the float32 ``row``'s squares, its terms added in any order (vector lanes): the bound of
    :func:`~lelsonar.signal.energy.energy_agrees` holds for every order, and a NaN or infinite sample makes it
    NaN or infinite in every order."""
    total = np.float32(0.0)
    for j in range(row.size):
        total += row[j] * row[j]
    return total


@summing_kernel
def row_sums(row):
    """One read of the float32 ``row`` from memory: :func:`sum_of_squares`, the float64 sum of its samples in any
    order (exact, the in-order sum, where :func:`exact_mean` says so), and the largest and the smallest nonzero
    magnitude's bit pattern shifted left once (the sign shifted out: ``top``; ``low``, that less one: 2^32 − 1 if
    none)."""
    patterns = row.view(np.uint32)
    squares = np.float32(0.0)
    top = np.uint32(0)
    low = np.uint32(0xFFFFFFFF)
    for j in range(row.size):
        x = row[j]
        squares += x * x
        v = np.uint32(patterns[j] << np.uint32(1))
        top = max(top, v)
        low = min(low, np.uint32(v - np.uint32(1)))  # (zero wraps round to the largest)
    # The float64 sum in a loop of its own (the row is in the cache by now): beside the float32 lanes it halves
    # their width.
    total = 0.0
    for j in range(row.size):
        total += row[j]
    return squares, total, top, low


@kernel
def exact_mean(total, top, low, n):
    """|total / n|, ``total`` the float64 sum of ``n`` float32 samples in any order whose largest and smallest
    nonzero magnitudes are ``top`` and ``low`` (:func:`row_sums`), if that sum is exact (then it is the in-order
    one, and this is ``np.mean``'s to the bit); NaN otherwise (and for no samples).

    Every sample is a multiple of the smallest one's unit in the last place, 2^(e_min − 150) (e: the biased
    exponent, 1 for a subnormal), and below 2^(e_max − 126); so is every partial sum of n < 2^b of them, below
    2^(b + e_max − 126).  All are exact in float64's 53 bits if e_max − e_min ≤ 29 − b: each addition then
    rounds nothing, whatever the order.  (A NaN or an infinity, e_max 255, is left to the in-order sum.)"""
    if n == 0:
        return np.nan
    e_max = np.int64(top >> np.uint32(24))
    e_min = max((np.int64(low) + 1) >> 24, 1)  # (256 for none: no sample but zeros, an exact sum of 0)
    b = 0
    while (1 << b) < n:
        b += 1
    if e_max < 255 and e_max - e_min <= 29 - b:
        return abs(total / n)
    return np.nan


@kernel
def _inexact_dc_levels(buf, starts, n, out):
    """:func:`dc_levels_at` of the rows whose ``out`` is NaN (not summed exactly in any order): scaled by 2^s so
    that each sample is an integer and all of them together stay below 2^52, the samples add up in int64 (side by
    side), and every partial sum of the in-order float64 additions was exact too — the same number.  A waveform
    whose samples do not all fit (a dynamic range beyond ~2^40 at ``n`` samples) is summed in order."""
    k = starts.size
    if n == 0:
        return
    bits = 0
    while (1 << bits) < n:
        bits += 1
    inexact_rows = 0
    for i in range(k):
        if out[i] == out[i]:
            continue
        row = float32_at(buf, starts[i], n)
        s = 52 - bits - ((_largest_bits(row) >> 23) - 126)  # |sample| < 2^(exponent + 1): n of them < 2^52 after 2^s
        total, inexact = _scaled_sum(row, 2.0**s)
        if inexact:
            inexact_rows += 1  # left NaN: summed in order below
        else:
            out[i] = abs(float(total) * 2.0**-s / n)
    if inexact_rows:
        _dc_levels_in_order(buf, starts, n, out)


@kernel
def _dc_levels_in_order(buf, starts, n, out):
    """:func:`dc_levels_at` of the rows whose ``out`` is NaN, each summed in float64 in order, four rows side by
    side: the additions of a row wait on one another, those of four rows do not."""
    k = starts.size
    rows = np.empty(k, np.int64)
    count = 0
    for i in range(k):
        if out[i] != out[i]:
            rows[count] = i
            count += 1
    for g in range(0, count, 4):
        # A group of fewer than four repeats its last row (its sums computed twice, written once).
        a, b = rows[g], rows[min(g + 1, count - 1)]
        c, d = rows[min(g + 2, count - 1)], rows[min(g + 3, count - 1)]
        ra, rb = float32_at(buf, starts[a], n), float32_at(buf, starts[b], n)
        rc, rd = float32_at(buf, starts[c], n), float32_at(buf, starts[d], n)
        ta = tb = tc = td = 0.0
        for j in range(n):
            ta += float(ra[j])
            tb += float(rb[j])
            tc += float(rc[j])
            td += float(rd[j])
        out[a], out[b], out[c], out[d] = abs(ta / n), abs(tb / n), abs(tc / n), abs(td / n)


@kernel
def _largest_bits(row):
    """The largest |sample|'s float32 bit pattern (an int: its exponent in bits 23–30)."""
    patterns = row.view(np.int32)
    top = np.int32(0)
    for j in range(patterns.size):
        top = max(top, patterns[j] & np.int32(0x7FFFFFFF))
    return top


@kernel
def _scaled_sum(row, scale):
    """Σ row·scale in int64, and whether any term was not an integer."""
    total = np.int64(0)
    inexact = np.int64(0)
    for j in range(row.size):
        y = np.float64(row[j]) * scale
        whole = np.int64(y)
        total += whole
        inexact |= np.int64(np.float64(whole) != y)
    return total, inexact != 0
